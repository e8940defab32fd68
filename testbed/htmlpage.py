"""The ``report.html`` every evaluation run writes next to its ``report.json``: one self-contained page (tables,
an optional 3-D view, then the plots), the same look for every scenario and for the pipeline's own reports
(:mod:`bodyslam.report`)."""

from __future__ import annotations

from pathlib import Path

from bodyslam.report import table, write_page

__all__ = ["table", "write_report_page"]


def write_report_page(out: Path, scenario: str, intro: str, body_html: str, images: list[str]) -> None:
    """``out/report.html``: title, an ``intro`` paragraph (plain text, escaped), ``body_html`` (already HTML:
    tables, headings), a 3-D view (:func:`bodyslam.report.view_3d`, or none) and the ``images`` (file names next
    to the page)."""
    write_page(Path(out) / "report.html", f"Evaluation of {scenario}", intro, body_html, images)

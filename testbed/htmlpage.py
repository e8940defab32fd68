"""The ``report.html`` every evaluation run writes next to its ``report.json``: one self-contained page (tables,
then the plots), the same look for every scenario."""

from __future__ import annotations

import html
from pathlib import Path

from bodyslam.io import write_text_atomic

__all__ = ["table", "write_report_page"]

_STYLE = """body{font-family:sans-serif;max-width:1100px;margin:2em auto}table{border-collapse:collapse}
td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}td:first-child{text-align:left}
figure{display:inline-block;margin:8px}"""


def table(headers: list[str], rows: list[list]) -> str:
    """An HTML table; cells are escaped, floats shown as given (format them before)."""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_report_page(out: Path, scenario: str, intro: str, body_html: str, images: list[str]) -> None:
    """``out/report.html``: title, an ``intro`` paragraph (plain text, escaped), ``body_html`` (already HTML:
    tables, headings) and the ``images`` (file names next to the page)."""
    imgs = "".join(f'<figure><img src="{html.escape(n)}" alt="{html.escape(n)}"><figcaption>{html.escape(n)}'
                   f"</figcaption></figure>" for n in images)
    title = html.escape(str(scenario))
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Evaluation: {title}</title>
<style>{_STYLE}</style></head><body>
<h1>Evaluation of {title}</h1>
<p>{html.escape(intro)}</p>
{body_html}
{imgs}
</body></html>
"""
    write_text_atomic(Path(out) / "report.html", page)

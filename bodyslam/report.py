"""Self-contained HTML reports: tables, the PNG plots (:mod:`bodyslam.plots`) and a 3-D view of the trajectory that
a person can turn (plotly; its JavaScript inlined, so the page needs no network and is one file to hand on).

- :func:`view_3d`: the trajectory (and the truth where there is one) in the body frame, start and end, each
  marked frame (a lesion) with its 1-sigma ellipsoid; hovering a point shows the frame, time and 1-sigma.
- :func:`write_page`: the page itself (``report.html``), written atomically.

Used by ``bodyslam batch`` (one page per exam), ``bodyslam localize`` and ``testbed evaluate``. A page with a 3-D
view is ~5 MB (plotly's JavaScript); one without is a few kB.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from bodyslam.io import write_text_atomic
from bodyslam.plots import Mark, Path3D, cube_cm

__all__ = ["table", "view_3d", "write_page"]

_STYLE = """body{font-family:sans-serif;max-width:1250px;margin:2em auto;color:#222}table{border-collapse:collapse;
margin:0.5em 0 1em}td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}td:first-child,th:first-child{
text-align:left}figure{display:inline-block;margin:8px;vertical-align:top}img{max-width:100%}
.view3d{border:1px solid #ccc;margin:1em 0}.note{color:#555;font-size:0.9em}"""


def table(headers: list[str] | None, rows: list[list]) -> str:
    """An HTML table (``headers`` None: rows only); cells are escaped, floats shown as given (format them
    before)."""
    head = "<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in headers) + "</tr>" if headers else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table>{head}{body}</table>"


def _hex(c) -> str:
    return "#%02x%02x%02x" % tuple(int(v) for v in c)


def _ellipsoid(centre_cm: np.ndarray, cov_cm2: np.ndarray, n: int = 16):
    """Vertices and triangles of the 1-sigma ellipsoid (a deformed UV sphere)."""
    w, v = np.linalg.eigh((cov_cm2 + cov_cm2.T) / 2)
    A = v * np.sqrt(np.maximum(w, 0.0))
    u, t = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n // 2 + 1))
    sphere = np.stack([np.cos(u) * np.sin(t), np.sin(u) * np.sin(t), np.cos(t)], axis=-1).reshape(-1, 3)
    pts = centre_cm + sphere @ A.T
    rows, cols = t.shape
    i, j, k = [], [], []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a, b, d, e = r * cols + c, r * cols + c + 1, (r + 1) * cols + c, (r + 1) * cols + c + 1
            i += [a, b]
            j += [b, e]
            k += [d, d]
    return pts, i, j, k


def view_3d(paths: list[Path3D], marks: list[Mark] = (), stamps_s: np.ndarray | None = None,
            frames: np.ndarray | None = None, div_id: str = "view3d", max_points: int = 5000,
            body_frame: bool = True) -> str:
    """An HTML ``<div>`` with the 3-D view (needs the page's plotly script: :func:`write_page` adds it). Paths in
    metres, drawn in cm with equal axes; ``stamps_s`` / ``frames`` (of the first path's rows) label the hover text;
    long paths are thinned to ``max_points``. ``body_frame`` False: the first camera frame's axes (dead
    reckoning)."""
    import plotly.graph_objects as go

    traces = []
    for n_path, p in enumerate(paths):
        step = max(1, len(p.p) // max_points)
        idx = np.arange(0, len(p.p), step)
        q = p.p[idx] * 100
        text = None
        if n_path == 0 or p.cov is not None:
            parts = []
            for k in idx:
                s = f"frame {int(frames[k]) if frames is not None else k}"
                if stamps_s is not None:
                    s += f", t {stamps_s[k]:.1f} s"
                if p.cov is not None and np.isfinite(p.cov[k]).all():
                    s += f", 1-sigma {np.sqrt(np.trace(p.cov[k])) * 100:.1f} cm"
                parts.append(s)
            text = parts
        traces.append(go.Scatter3d(x=q[:, 0], y=q[:, 1], z=q[:, 2], mode="lines", name=p.label, text=text,
                                   line=dict(color=_hex(p.colour), width=max(2, 2 * p.width)),
                                   hovertemplate="%{text}<br>x %{x:.1f} cm, y %{y:.1f} cm, z %{z:.1f} cm"
                                   if text else None))
    ends = paths[0].ends_cm() if paths else None
    if ends is not None:
        for q, name, colour, symbol in ((ends[0], "start", "green", "diamond"), (ends[1], "end", "red", "square")):
            traces.append(go.Scatter3d(x=[q[0]], y=[q[1]], z=[q[2]], mode="markers", name=name,
                                       marker=dict(color=colour, size=6, symbol=symbol)))
    for j, m in enumerate(marks):
        q = m.p * 100
        sd = f" +- {np.sqrt(np.trace(m.cov)) * 100:.1f} cm (1-sigma)" if m.cov is not None else ""
        traces.append(go.Scatter3d(x=[q[0]], y=[q[1]], z=[q[2]], mode="markers+text", name=m.label,
                                   text=[m.label], textposition="top center",
                                   marker=dict(color="grey" if m.landmark else "gold", size=5 if m.landmark else 7,
                                               symbol="diamond", line=dict(color="black")),
                                   hovertemplate=f"{html.escape(m.label)}: x %{{x:.1f}}, y %{{y:.1f}}, z %{{z:.1f}} "
                                                 f"cm{sd}<extra></extra>"))
        if m.cov is not None and np.isfinite(m.cov).all() and not m.landmark:
            pts, i, jj, k = _ellipsoid(q, m.cov * 1e4)
            traces.append(go.Mesh3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], i=i, j=jj, k=k, opacity=0.25,
                                    color="orange", name=f"{m.label}: 1-sigma", showlegend=True, hoverinfo="skip"))
    fig = go.Figure(traces)
    # equal axes: one cube around everything drawn (plotly's "data" aspect zooms a long, thin path too close)
    mid, half = cube_cm(paths, marks)
    titles = (("x, patient's left (cm)", "y, anterior (cm)", "z, cranial (cm)") if body_frame
              else ("x (cm)", "y (cm)", "z (cm)"))
    fig.update_layout(height=640, margin=dict(l=0, r=0, t=30, b=0), legend=dict(x=0, y=1),
                      scene=dict(aspectmode="cube", **{f"{a}axis": dict(title=t, range=[mid[i] - half, mid[i] + half])
                                                       for i, (a, t) in enumerate(zip("xyz", titles))}),
                      title=dict(text="Drag to turn, scroll to zoom; hover for frame, time and 1-sigma", x=0.5,
                                 font=dict(size=13)))
    div = fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id,
                      config={"displaylogo": False, "responsive": True})
    return f'<div class="view3d">{div}</div>'


def write_page(out_file: str | Path, title: str, intro: str, body_html: str, images: list[str] = ()) -> None:
    """``out_file``: title, an ``intro`` paragraph (plain text, escaped), ``body_html`` (already HTML: tables,
    headings, :func:`view_3d` divs) and the ``images`` (file names next to the page). Plotly's JavaScript is
    inlined once when the body holds a 3-D view."""
    script = ""
    if 'class="view3d"' in body_html:  # a view without its script would be a blank box
        from plotly.offline import get_plotlyjs

        script = f"<script>{get_plotlyjs()}</script>"
    imgs = "".join(f'<figure><img src="{html.escape(n)}" alt="{html.escape(n)}"><figcaption>{html.escape(n)}'
                   f"</figcaption></figure>" for n in images)
    t = html.escape(str(title))
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{t}</title>
<style>{_STYLE}</style>{script}</head><body>
<h1>{t}</h1>
<p>{html.escape(intro)}</p>
{body_html}
{imgs}
</body></html>
"""
    write_text_atomic(Path(out_file), page)

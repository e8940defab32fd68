"""The HTML report (bodyslam.report): self-contained, and checked in a real browser when one is installed."""

import shutil
import subprocess

import numpy as np
import pytest

from bodyslam.plots import Mark, Path3D
from bodyslam.report import table, view_3d, write_page


def _page(tmp_path):
    t = np.linspace(0, np.pi, 200)
    p = np.stack([0.05 * np.cos(t), 0.05 * np.sin(t), 0.01 * t], axis=1)
    cov = np.repeat((np.eye(3) * 0.01**2)[None], 200, axis=0)
    body = table(["a", "b"], [["<x>", 1.5]]) + view_3d([Path3D("estimate", p, cov_m2=cov), Path3D("truth", p * 1.1)],
                                                        [Mark("polyp", p[100], cov[100])], t, np.arange(200))
    out = tmp_path / "report.html"
    write_page(out, "Exam <1>", "intro & more", body, [])
    return out


def test_the_page_is_one_file_that_needs_no_network(tmp_path):
    html = _page(tmp_path).read_text()
    assert "<script src=" not in html and "cdn.plot.ly" not in html.split("</script>", 1)[1]
    assert "Exam &lt;1&gt;" in html and "&lt;x&gt;" in html  # escaped
    assert html.count('class="view3d"') == 1 and "polyp" in html and "Plotly.newPlot" in html


def _browser() -> str | None:
    return next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)


@pytest.mark.skipif(_browser() is None, reason="no Chromium here (scripts/bootstrap.sh installs Debian's chromium; "
                                                 "this machine could not)")
def test_the_3d_view_renders_in_headless_chromium(tmp_path):
    """Chromium loads the page offline, plotly builds its WebGL scene (the DOM has the plot and its GL container)
    and the screenshot is not blank."""
    page = _page(tmp_path)
    args = [_browser(), "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
            "--virtual-time-budget=8000", "--window-size=1200,1000"]
    dom = subprocess.run(args + ["--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120).stdout
    assert "js-plotly-plot" in dom and "gl-container" in dom, dom[-2000:]
    shot = tmp_path / "shot.png"
    subprocess.run(args + [f"--screenshot={shot}", page.as_uri()], capture_output=True, timeout=120)
    import cv2

    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (1000, 1200)
    # the estimate's line, drawn by WebGL in its colour (31, 119, 180), is on the screen, not only in the DOM
    blue = (np.abs(img[..., ::-1].astype(int) - (31, 119, 180)).max(axis=2) <= 40).sum()
    assert blue > 200, blue

"""The plots (bodyslam.plots, matplotlib): what they draw can be seen in the pixels, and positions get equal axes."""

import numpy as np

from bodyslam.plots import Figure, Mark, Path3D, _trajectory_mpl, cm_text, path_figure, trajectory_figure


def _count(img: np.ndarray, rgb, tol: int = 40) -> int:
    return int((np.abs(img.astype(int) - np.array(rgb)).max(axis=2) <= tol).sum())


def test_figure_draws_its_items_and_positions_get_equal_axes():
    from matplotlib.figure import Figure as MplFigure

    f = Figure("t", "x (cm)", "y (cm)", size=(400, 300), equal=True)
    f.line([0, 10], [0, 1], "a line", (214, 39, 40)).band([0, 10], [0, 0], [1, 1], "a band", (31, 119, 180))
    img = f.image()
    assert img.shape == (300, 400, 3) and img.dtype == np.uint8
    assert _count(img, (214, 39, 40)) > 100  # the red line is there (and the legend's sample)
    ax = MplFigure().add_subplot()
    f.draw(ax)
    assert ax.get_aspect() == 1.0 and ax.get_xlabel() == "x (cm)"
    assert Figure("t", "x", "y").line([0, 1], [0, 1]).image().std() > 0  # not a blank image


def test_trajectory_figure_shows_start_end_marks_and_the_1sigma():
    """A 10 cm arc with a 1 cm 1-sigma and a marked frame: the start's green, the end's red, the mark's gold and
    the path's colour are all in the image; without the covariance the ellipses' extra pixels are gone."""
    t = np.linspace(0, np.pi, 100)
    p = np.stack([0.05 * np.cos(t), 0.05 * np.sin(t), 0.01 * t], axis=1)
    cov = np.repeat((np.eye(3) * 0.01**2)[None], 100, axis=0)
    blue = (31, 119, 180)
    with_cov = trajectory_figure("arc", [Path3D("est", p, blue, 1.8, cov)], [Mark("lesion", p[50], cov[50])])
    without = trajectory_figure("arc", [Path3D("est", p, blue, 1.8)], [Mark("lesion", p[50], cov[50])])
    assert with_cov.shape == (1000, 1200, 3)
    for rgb in ((44, 160, 44), (214, 39, 40), (255, 200, 0)):
        assert _count(with_cov, rgb, 30) > 20, rgb
    assert _count(with_cov, blue, 30) > 1.3 * _count(without, blue, 30)


def test_path_figure_of_a_long_exam_is_in_minutes_with_the_mark():
    t = np.arange(0, 3600, 0.5)
    img = path_figure("exam", t, t * 1e-4, (t * 1e-5) ** 2, [(1800.0, "polyp")])
    assert img.shape == (420, 900, 3) and _count(img, (255, 200, 0), 30) > 20


def test_path_figure_shows_the_landmarks_and_the_stretch_between_them():
    """Each landmark is a full-height grey line with its marker (~500 grey pixels each on a 900 x 420 figure); two or
    more shade the stretch from the first to the last (the axes' height over 60% of the time axis: ~150,000 light
    grey pixels), one alone shades nothing."""
    t = np.arange(0, 100, 0.5)
    plain = path_figure("exam", t, t * 1e-3)
    one = path_figure("exam", t, t * 1e-3, landmarks=[(20.0, "landmark 40")])
    two = path_figure("exam", t, t * 1e-3, landmarks=[(20.0, "landmark 40"), (80.0, "landmark 160")])
    grey, shade = (110, 110, 110), (240, 240, 240)
    assert _count(one, grey, 15) > _count(plain, grey, 15) + 300
    assert _count(two, grey, 15) > _count(one, grey, 15) + 300
    assert _count(one, shade, 4) < _count(plain, shade, 4) + 1000 < _count(two, shade, 4) - 100_000


def test_a_marks_path_label_keeps_the_digits_a_short_clip_needs():
    """A short clip's marked frame 0.34 cm along read "0 cm" with whole centimetres; a whole exam's stay whole."""
    assert cm_text(0.3396) == "0.34 cm"
    assert cm_text(3.396) == "3.4 cm"
    assert cm_text(339.6) == "340 cm"
    assert cm_text(-0.05) == "-0.05 cm"


def test_the_path_band_stays_at_or_above_zero(monkeypatch):
    """A short clip's path travelled can have a 1-sigma larger than itself near the start; the band is cut at zero
    (a capsule travels no negative distance) and keeps its upper edge."""
    bands = []
    monkeypatch.setattr(Figure, "band", lambda self, x, lo, hi, *a, **k: bands.append((np.array(lo), np.array(hi)))
                        or self)
    t = np.arange(6) * 0.5
    path_figure("clip", t, [0.0, 0.001, 0.002, 0.01, 0.02, 0.03], np.full(6, 0.005 ** 2))
    (lo, hi), = bands
    assert lo.min() == 0.0 and np.allclose(lo[3:], [0.5, 1.5, 2.5]) and np.allclose(hi, [0.5, 0.6, 0.7, 1.5, 2.5, 3.5])


def test_trajectory_figure_keeps_its_legend_off_the_panels():
    """A short clip's path ends in the middle of its panels, where a legend inside one hid the end marker (a real
    four-frame clip, session 79): the one legend lies below every panel and no panel has its own."""
    p = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.004], [-0.001, 0.0007, 0.005]])
    cov = np.repeat((np.eye(3) * 0.003**2)[None], 3, axis=0)
    fig = _trajectory_mpl("clip", [Path3D("dead reckoning", p, (214, 39, 40), 1.8, cov)], [], 12, (1200, 1000),
                          False, 4000)
    fig.canvas.draw()
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    legend_top = fig.legends[0].get_window_extent().y1
    assert all(legend_top <= ax.get_window_extent().y0 + 1e-6 for ax in fig.axes[1:])  # the 2-D panels
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["dead reckoning", "1-sigma (dead reckoning)",
                                                                  "start", "end"]


def test_a_landmark_is_a_grey_diamond_without_its_1sigma():
    """A landmark frame (the pylorus, say) beside a marked frame: the legend names both kinds once, the landmark is
    grey and adds no ellipse (the marked frame's gold ring is drawn; a landmark's would be grey)."""
    t = np.linspace(0, np.pi, 100)
    p = np.stack([0.05 * np.cos(t), 0.05 * np.sin(t), 0.01 * t], axis=1)
    cov = np.eye(3) * 0.01**2
    marks = [Mark("frame 50", p[50], cov), Mark("landmark 10", p[10], cov, landmark=True),
             Mark("landmark 90", p[90], cov, landmark=True)]
    fig = _trajectory_mpl("arc", [Path3D("est", p, (31, 119, 180), 1.8)], marks, 12, (1200, 1000), True, 4000)
    fig.canvas.draw()
    assert [x.get_text() for x in fig.legends[0].get_texts()] == ["est", "start", "end", "marked frame", "landmark"]
    grey = (110, 110, 110)
    img = trajectory_figure("arc", [Path3D("est", p, (31, 119, 180), 1.8)], marks)
    no_landmarks = trajectory_figure("arc", [Path3D("est", p, (31, 119, 180), 1.8)], marks[:1])
    assert _count(img, grey, 12) > _count(no_landmarks, grey, 12) + 800  # two diamonds (~140 px) in four views
    coronal = [ax for ax in fig.axes if ax.get_title() == "coronal (front) view"][0]
    rings = [ln for ln in coronal.get_lines() if len(ln.get_xdata()) == 48]  # _ellipse_xy's 48 points
    assert len(rings) == 1  # the marked frame's only

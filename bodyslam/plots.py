"""Plots, drawn with matplotlib (its object API and the Agg canvas: no display, no global state).

Each figure returns an RGB ``uint8`` image; write it with :func:`bodyslam.io.write_image`. Axes carry human labels
with their units (SPEC.md: human-readable outputs say cm, deg ...), and plots of positions have equal axes.

- :class:`Figure`: one axes of lines, step lines, bars, bands, points and 1-sigma ellipses (every report's
  2-D plots).
- :func:`trajectory_figure`: a trajectory in the body frame as a 3-D view and its three anatomical projections
  (coronal, axial, sagittal), with the truth where it exists, the 1-sigma as ellipses along the path, start and end,
  each marked frame (a lesion) with its own 1-sigma ellipse, and each landmark frame.
- :func:`path_figure`: how far along the gut -- the path travelled against time with its 1-sigma band, the
  marked frames and the landmark frames.
- :data:`BODY_AXES`: what the body frame's axes mean (SPEC.md), for labels.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Figure", "trajectory_figure", "path_figure", "cm_text", "cube_cm", "BODY_AXES", "Path3D", "Mark"]

# SPEC.md: x toward the patient's left, y anterior, z cranial
BODY_AXES = ("x, toward the patient's left (cm)", "y, anterior (cm)", "z, cranial (cm)")
_COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (140, 86, 75)]


def _rgb(c) -> tuple[float, float, float]:
    """An RGB 0-255 tuple (this module's colours) as matplotlib's 0-1."""
    return tuple(float(v) / 255.0 for v in c)


def _canvas(w_px: int, h_px: int):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(w_px / 100.0, h_px / 100.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _to_rgb(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _ellipse_xy(centre, cov2, n_sigma: float = 1.0, n: int = 48) -> np.ndarray:
    """Points of the ``n_sigma`` ellipse of a 2-D Gaussian (``(n, 2)``); NaN for a covariance that is not finite."""
    cov2 = np.asarray(cov2, float)
    if not np.isfinite(cov2).all():
        return np.full((n, 2), np.nan)
    w, v = np.linalg.eigh((cov2 + cov2.T) / 2)
    a = np.linspace(0, 2 * np.pi, n)
    circle = np.stack([np.cos(a), np.sin(a)], axis=1) * np.sqrt(np.maximum(w, 0.0)) * n_sigma
    return np.asarray(centre, float) + circle @ v.T


class Figure:
    """One axes: lines, step lines, bars, bands, points and ellipses in data coordinates, then :meth:`image`.
    ``equal``: one unit is as long on both axes (positions); ``log_y``: a logarithmic y axis."""

    def __init__(self, title: str, xlabel: str, ylabel: str, size=(640, 420), log_y: bool = False,
                 equal: bool = False):
        self.title, self.xlabel, self.ylabel = title, xlabel, ylabel
        self.size, self.log_y, self.equal = size, log_y, equal
        self.items: list = []

    def _colour(self, colour):
        return _rgb(colour or _COLOURS[len(self.items) % len(_COLOURS)])

    def line(self, x, y, label: str | None = None, colour=None, step: bool = False, width: float = 2,
             marker: bool = False, dashed: bool = False):
        self.items.append(("line", np.asarray(x, float), np.asarray(y, float), self._colour(colour), label,
                           dict(step=step, width=width, marker=marker, dashed=dashed)))
        return self

    def bars(self, edges, heights, label: str | None = None, colour=None):
        self.items.append(("bars", np.asarray(edges, float), np.asarray(heights, float), self._colour(colour), label,
                           {}))
        return self

    def band(self, x, lo, hi, label: str | None = None, colour=None, alpha: float = 0.25):
        """A shaded band between ``lo`` and ``hi`` (an uncertainty)."""
        self.items.append(("band", np.asarray(x, float), (np.asarray(lo, float), np.asarray(hi, float)),
                           self._colour(colour), label, dict(alpha=alpha)))
        return self

    def points(self, x, y, label: str | None = None, colour=None, marker: str = "o", size: float = 60,
               texts: list[str] | None = None):
        """Markers, each optionally annotated."""
        self.items.append(("points", np.atleast_1d(np.asarray(x, float)), np.atleast_1d(np.asarray(y, float)),
                           self._colour(colour), label, dict(marker=marker, size=size, texts=texts)))
        return self

    def ellipse(self, centre, cov2, label: str | None = None, colour=None, width: float = 1.0):
        """The 1-sigma ellipse of a 2-D position (``cov2``: 2x2, same units as the axes squared)."""
        xy = _ellipse_xy(centre, cov2)
        self.items.append(("line", xy[:, 0], xy[:, 1], self._colour(colour), label,
                           dict(step=False, width=width, marker=False)))
        return self

    def vspan(self, x0: float, x1: float, label: str | None = None, colour=None, alpha: float = 0.12):
        """A shaded stretch of the x axis, the axes' whole height."""
        self.items.append(("vspan", float(x0), float(x1), self._colour(colour), label, dict(alpha=alpha)))
        return self

    def vline(self, x: float, label: str | None = None, colour=None, dashed: bool = True):
        self.items.append(("vline", float(x), None, self._colour(colour), label, dict(dashed=dashed)))
        return self

    def draw(self, ax, legend: bool = True) -> None:
        """Draw onto a matplotlib axes (:func:`trajectory_figure` composes several)."""
        for kind, a, b, c, label, kw in self.items:
            if kind == "line":
                ls = "--" if kw.get("dashed") else "-"
                if kw["step"]:
                    ax.step(a, b, where="post", color=c, lw=kw["width"], ls=ls, label=label)
                else:
                    ax.plot(a, b, color=c, lw=kw["width"], ls=ls, label=label, marker="o" if kw["marker"] else None,
                            ms=4)
            elif kind == "bars":
                ax.bar(a[:-1], b, width=np.diff(a), align="edge", color=c, label=label)
            elif kind == "band":
                ax.fill_between(a, b[0], b[1], color=c, alpha=kw["alpha"], lw=0, label=label)
            elif kind == "points":
                ax.scatter(a, b, color=c, marker=kw["marker"], s=kw["size"], label=label, zorder=5,
                           edgecolors="black", linewidths=0.6)
                for x, y, t in zip(a, b, kw["texts"] or []):
                    ax.annotate(t, (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
            elif kind == "vspan":
                ax.axvspan(a, b, color=c, alpha=kw["alpha"], lw=0, label=label)
            elif kind == "vline":
                ax.axvline(a, color=c, lw=1, ls="--" if kw.get("dashed", True) else "-", label=label)
        if self.log_y:
            ax.set_yscale("log")
        if self.equal:
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(self.title, fontsize=10)
        ax.set_xlabel(self.xlabel)
        ax.set_ylabel(self.ylabel)
        ax.grid(True, alpha=0.3)
        if legend and any(it[4] for it in self.items):
            ax.legend(fontsize=8, loc="best")

    def image(self) -> np.ndarray:
        fig = _canvas(*self.size)
        self.draw(fig.add_subplot())
        return _to_rgb(fig)


class Path3D:
    """One trajectory to draw: positions ``(n, 3)`` in metres (NaN rows skipped), an optional ``(n, 3, 3)``
    covariance (m^2) drawn as 1-sigma ellipses, a label, an RGB colour and a line width."""

    def __init__(self, label: str, positions_m, colour=(31, 119, 180), width: float = 1.8, cov_m2=None):
        self.label, self.p, self.colour, self.width = label, np.asarray(positions_m, float), colour, width
        self.cov = None if cov_m2 is None else np.asarray(cov_m2, float)

    def ends_cm(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The first and the last position with a value (cm), or None when there is none."""
        ok = np.nonzero(np.isfinite(self.p).all(axis=1))[0]
        return (self.p[ok[0]] * 100, self.p[ok[-1]] * 100) if len(ok) else None


def cube_cm(paths: list[Path3D], marks: list = ()) -> tuple[np.ndarray, float]:
    """``(centre, half side)`` in cm of one cube around every position drawn (equal axes in 3-D views; at least
    1 cm, 10% margin)."""
    pts = np.concatenate([p.p for p in paths] + [m.p[None] for m in marks] + [np.zeros((0, 3))]) * 100
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return np.zeros(3), 1.0
    return (pts.min(axis=0) + pts.max(axis=0)) / 2, max(float(np.ptp(pts, axis=0).max()) / 2, 1.0) * 1.1


LANDMARK_RGB = (110, 110, 110)  # a landmark frame's grey in every plot (Mark, path_figure)


class Mark:
    """A marked frame (a lesion): its label, position (m) and 3x3 covariance (m^2); ``landmark``: a landmark frame
    (the pylorus, say), drawn as a grey diamond without its 1-sigma, not as a marked frame's star."""

    def __init__(self, label: str, position_m, cov_m2=None, landmark: bool = False):
        self.label, self.p = label, np.asarray(position_m, float)
        self.cov = None if cov_m2 is None else np.asarray(cov_m2, float)
        self.landmark = bool(landmark)

    def style(self) -> tuple[tuple[int, int, int], str, float]:
        """``(rgb, matplotlib marker, size)``."""
        return (LANDMARK_RGB, "D", 70) if self.landmark else ((255, 200, 0), "*", 220)


def trajectory_figure(title: str, paths: list[Path3D], marks: list[Mark] = (), n_ellipses: int = 12,
                      size=(1200, 1000), body_frame: bool = True, max_points: int = 4000) -> np.ndarray:
    """A 3-D view and the coronal (x-z), axial (x-y) and sagittal (y-z) projections of ``paths`` (body frame, cm,
    equal axes), as an RGB image. The first path with a covariance gets ``n_ellipses`` 1-sigma ellipses along it;
    the first path gets start (triangle) and end (square) markers; each mark is a star with its 1-sigma ellipse
    (a landmark, :class:`Mark`, a grey diamond).
    ``body_frame`` False: the axes are the first camera frame's (dead reckoning), named as such. Paths are thinned
    to ``max_points`` (a plot needs no more points than pixels). One legend, below the panels."""
    return _to_rgb(_trajectory_mpl(title, paths, marks, n_ellipses, size, body_frame, max_points))


def _trajectory_mpl(title: str, paths: list[Path3D], marks, n_ellipses: int, size, body_frame: bool,
                    max_points: int):
    """:func:`trajectory_figure`'s matplotlib figure, before it is drawn."""
    paths = [Path3D(p.label, p.p[:: max(1, len(p.p) // max_points)], p.colour, p.width,
                    None if p.cov is None else p.cov[:: max(1, len(p.p) // max_points)]) for p in paths]
    axes = BODY_AXES if body_frame else ("x, first camera frame (cm)", "y, first camera frame (cm)",
                                         "z, first camera frame (cm)")
    views = (((0, 2, "coronal (front) view"), (0, 1, "axial (from the feet) view"), (1, 2, "sagittal (from the left) view"))
             if body_frame else ((0, 2, "x-z"), (0, 1, "x-y"), (1, 2, "y-z")))
    fig = _canvas(*size)
    fig.suptitle(title, fontsize=12)
    ends = paths[0].ends_cm() if paths else None  # start and end of the first path
    with_cov = next((p for p in paths if p.cov is not None), None)
    ax3 = fig.add_subplot(2, 2, 1, projection="3d")
    for p in paths:
        q = p.p * 100
        ax3.plot(q[:, 0], q[:, 1], q[:, 2], color=_rgb(p.colour), lw=p.width, label=p.label)
    if ends is not None:
        ax3.scatter(*ends[0], color="green", marker="^", s=70, edgecolors="black", label="start")
        ax3.scatter(*ends[1], color="red", marker="s", s=60, edgecolors="black", label="end")
    for m in marks:
        rgb, marker, size = m.style()
        ax3.scatter(*(m.p * 100), color=_rgb(rgb), marker=marker, s=size, edgecolors="black")
        ax3.text(*(m.p * 100), f"  {m.label}", fontsize=8)
    mid, half = cube_cm(paths, marks)
    ax3.set_xlim(mid[0] - half, mid[0] + half)
    ax3.set_ylim(mid[1] - half, mid[1] + half)
    ax3.set_zlim(mid[2] - half, mid[2] + half)
    ax3.set_box_aspect((1, 1, 1))
    short = ("x, left (cm)", "y, anterior (cm)", "z, cranial (cm)") if body_frame else ("x (cm)", "y (cm)", "z (cm)")
    ax3.set_xlabel(short[0], fontsize=8)
    ax3.set_ylabel(short[1], fontsize=8)
    ax3.set_zlabel(short[2], fontsize=8)
    ax3.set_title("3-D view", fontsize=10)
    for slot, (a, b, name) in zip((2, 3, 4), views):
        f = Figure(name, axes[a], axes[b], equal=True)
        for p in paths:
            q = p.p * 100
            f.line(q[:, a], q[:, b], label=p.label, colour=p.colour, width=p.width)
        if with_cov is not None:
            ok = np.nonzero(np.isfinite(with_cov.p).all(axis=1) & np.isfinite(with_cov.cov).all(axis=(1, 2)))[0]
            for j, k in enumerate(ok[np.linspace(0, len(ok) - 1, min(n_ellipses, len(ok))).astype(int)]
                                  if len(ok) else []):
                f.ellipse(with_cov.p[k, [a, b]] * 100, with_cov.cov[k][np.ix_([a, b], [a, b])] * 1e4,
                          label=f"1-sigma ({with_cov.label})" if j == 0 else None, colour=with_cov.colour)
        if ends is not None:
            f.points(ends[0][a], ends[0][b], "start", (44, 160, 44), "^")
            f.points(ends[1][a], ends[1][b], "end", (214, 39, 40), "s")
        for kind in (False, True):  # the marked frames, then the landmarks; each kind named once in the legend
            for j, m in enumerate([mk for mk in marks if mk.landmark == kind]):
                rgb, marker, size = m.style()
                f.points(m.p[a] * 100, m.p[b] * 100, None if j else "landmark" if kind else "marked frame", rgb,
                         marker, size, [m.label])
        for m in marks:
            if m.cov is not None and not m.landmark:
                f.ellipse(m.p[[a, b]] * 100, m.cov[np.ix_([a, b], [a, b])] * 1e4, colour=(200, 150, 0), width=1.5)
        ax = fig.add_subplot(2, 2, slot)
        f.draw(ax, legend=False)
        if slot == 2:  # one legend, the coronal view's items, below the panels: inside one it hid the path's end
            handles, labels = ax.get_legend_handles_labels()
            if handles:
                fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 6), fontsize=9,
                           frameon=False)
    return fig


def cm_text(value_cm: float) -> str:
    """A length in cm for a label, to the precision it needs: whole centimetres from 10 cm (a whole exam), one
    decimal from 1 cm, two below (a short clip's ~0.3 cm would otherwise read "0 cm")."""
    v = float(value_cm)
    digits = 0 if abs(v) >= 10 else 1 if abs(v) >= 1 else 2
    return f"{v:.{digits}f} cm"


def path_figure(title: str, stamps_s, path_m, path_var_m2=None, marks: list[tuple[float, str]] = (),
                size=(900, 420), landmarks: list[tuple[float, str]] = ()) -> np.ndarray:
    """The path travelled from the first frame against time (minutes when the exam is longer than 10 minutes),
    with its 1-sigma band (cut at zero), a dashed line at each marked frame ``(time s, label)`` and a solid grey
    one at each landmark frame ``(time s, label)``, the stretch between the first and the last landmark shaded."""
    t = np.asarray(stamps_s, float)
    minutes = len(t) > 1 and t[-1] - t[0] > 600
    tt = t / 60.0 if minutes else t
    pm = np.asarray(path_m, float) * 100
    f = Figure(title, "time (min)" if minutes else "time (s)", "path travelled from the first frame (cm)", size)
    if path_var_m2 is not None:
        sd = np.sqrt(np.maximum(np.asarray(path_var_m2, float), 0.0)) * 100
        # a path travelled is never negative: near the start its 1-sigma can exceed it (the radius's and the lost
        # steps' share), and a band below zero would show a distance no capsule can have
        f.band(tt, np.maximum(pm - sd, 0.0), pm + sd, "1-sigma", (31, 119, 180))
    f.line(tt, pm, "path travelled", (31, 119, 180))

    def at(ts: float) -> tuple[float, float | None]:
        """A frame's time on the plot's axis and the path travelled then (cm; None: no path)."""
        k = int(np.clip(np.searchsorted(t, ts), 0, len(pm) - 1)) if len(pm) else None
        return (ts / 60.0 if minutes else ts), (None if k is None else float(pm[k]))

    lm_x = [at(ts)[0] for ts, _ in landmarks]
    if len(set(lm_x)) >= 2:  # the stretch between the first and the last landmark (the small bowel, say)
        f.vspan(min(lm_x), max(lm_x), "between the landmarks", (150, 150, 150))
    for j, (ts, label) in enumerate(landmarks):
        x, p_cm = at(ts)
        f.vline(x, None, LANDMARK_RGB, dashed=False)
        f.points(x, p_cm or 0.0, "landmark" if j == 0 else None, LANDMARK_RGB, "D", 50, [label])
    for j, (ts, label) in enumerate(marks):
        x, p_cm = at(ts)
        f.vline(x, None, (200, 150, 0))
        f.points(x, p_cm or 0.0, "marked frame" if j == 0 else None, (255, 200, 0), "*", 200,
                 [label if p_cm is None else f"{label}: {cm_text(p_cm)}"])
    return f.image()

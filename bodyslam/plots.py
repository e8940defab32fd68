"""Small, dependency-free plots (OpenCV drawing): the declared stack has no plotting library.

Each function returns an RGB ``uint8`` image; write it with :func:`bodyslam.io.write_image`. Axes carry their
units in the labels (SPEC.md: human-readable outputs say cm, deg ...).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["Figure"]

_COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (140, 86, 75)]


def _nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    return np.arange(math.ceil(lo / step) * step, hi + 1e-9 * step, step)


class Figure:
    """One axes: lines, step lines and bars in data coordinates, then :meth:`image`."""

    def __init__(self, title: str, xlabel: str, ylabel: str, size=(640, 420), log_y: bool = False):
        self.title, self.xlabel, self.ylabel = title, xlabel, ylabel
        self.log_y = log_y  # y drawn as log10, ticks labelled with the values
        self.w, self.h = size
        self.items: list = []
        self.legend: list[tuple[str, tuple]] = []

    def line(self, x, y, label: str | None = None, colour=None, step: bool = False, width: int = 2,
             marker: bool = False):
        c = colour or _COLOURS[len(self.items) % len(_COLOURS)]
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self.log_y:
            y = np.log10(np.where(y > 0, y, np.nan))
        if step:
            x = np.repeat(x, 2)[1:]
            y = np.repeat(y, 2)[:-1]
        self.items.append(("line", x, y, c, width, marker))
        if label:
            self.legend.append((label, c))
        return self

    def bars(self, edges, heights, label: str | None = None, colour=None):
        c = colour or _COLOURS[len(self.items) % len(_COLOURS)]
        self.items.append(("bars", np.asarray(edges, float), np.asarray(heights, float), c, 0, False))
        if label:
            self.legend.append((label, c))
        return self

    def image(self) -> np.ndarray:
        img = np.full((self.h, self.w, 3), 255, np.uint8)
        L, R, T, B = 70, 20, 36, 50
        xs = np.concatenate([it[1] for it in self.items]) if self.items else np.array([0.0, 1.0])
        zero = [] if self.log_y else [np.array([0.0])]
        ys = np.concatenate([it[2] for it in self.items] + zero) if self.items else np.array([0.0, 1.0])
        xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
        x0, x1 = (xs.min(), xs.max()) if len(xs) else (0.0, 1.0)
        y0, y1 = (ys.min(), ys.max()) if len(ys) else (0.0, 1.0)
        if x1 <= x0:
            x1 = x0 + 1.0
        if y1 <= y0:
            y1 = y0 + 1.0
        y1 += 0.05 * (y1 - y0)

        def px(x, y):
            return (L + (np.asarray(x) - x0) / (x1 - x0) * (self.w - L - R),
                    self.h - B - (np.asarray(y) - y0) / (y1 - y0) * (self.h - T - B))

        font = cv2.FONT_HERSHEY_SIMPLEX
        for t in _nice_ticks(x0, x1):
            u, _ = px(t, y0)
            cv2.line(img, (int(u), self.h - B), (int(u), self.h - B + 5), (0, 0, 0), 1)
            cv2.putText(img, f"{t:g}", (int(u) - 12, self.h - B + 20), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for t in _nice_ticks(y0, y1):
            _, v = px(x0, t)
            cv2.line(img, (L - 5, int(v)), (L, int(v)), (0, 0, 0), 1)
            cv2.line(img, (L, int(v)), (self.w - R, int(v)), (230, 230, 230), 1)
            lab = f"{10 ** t:.3g}" if self.log_y else f"{t:g}"
            cv2.putText(img, lab, (4, int(v) + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for kind, a, b, c, width, marker in self.items:
            if kind == "bars":
                for i in range(len(b)):
                    (ua, vb), (ub, _) = px(a[i], 0.0), px(a[i + 1], 0.0)
                    _, vt = px(a[i], b[i])
                    cv2.rectangle(img, (int(ua), int(vt)), (max(int(ub) - 1, int(ua)), int(vb)), c, -1)
            else:
                ok = np.isfinite(a) & np.isfinite(b)
                u, v = px(a[ok], b[ok])
                pts = np.stack([u, v], axis=1).round().astype(np.int32)
                if len(pts) > 1:
                    cv2.polylines(img, [pts], False, c, width, cv2.LINE_AA)
                if marker:
                    for q in pts:
                        cv2.circle(img, (int(q[0]), int(q[1])), 3, c, -1, cv2.LINE_AA)
        cv2.rectangle(img, (L, T), (self.w - R, self.h - B), (0, 0, 0), 1)
        cv2.putText(img, self.title, (L, 24), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, self.xlabel, (L + (self.w - L - R) // 2 - 60, self.h - 12), font, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
        cv2.putText(img, self.ylabel, (4, T - 8), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for i, (lab, c) in enumerate(self.legend):
            y = T + 18 + 18 * i
            cv2.line(img, (self.w - R - 170, y - 4), (self.w - R - 150, y - 4), c, 3)
            cv2.putText(img, lab, (self.w - R - 145, y), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        return img

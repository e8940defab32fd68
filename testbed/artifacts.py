"""Image artefacts of real capsule frames that the geometric renderer does not produce: gas bubbles.

Bubbles in intestinal fluid show as clusters of circles with thin specular rims, a faint bright interior and a
small highlight where the capsule's LEDs reflect. They are drawn over the rendered colour image (2D, not in
depth: the range image is unchanged) from a seeded per-frame stream, so a sequence stays reproducible.

Scenario keys (``[artifacts]``): ``bubble_prob`` (chance that a frame has a cluster; 0 disables),
``bubble_count`` (range of bubbles per cluster), ``bubble_radius_frac`` (range of radii as a fraction of the
image circle radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Bubbles"]


@dataclass(frozen=True)
class Bubbles:
    bubble_prob: float = 0.0
    bubble_count: tuple[int, int] = (3, 25)
    bubble_radius_frac: tuple[float, float] = (0.02, 0.12)

    def apply(self, rgb: np.ndarray, rng: np.random.Generator, mask: np.ndarray) -> np.ndarray:
        if self.bubble_prob <= 0 or rng.random() >= self.bubble_prob:
            return rgb
        h, w = mask.shape
        ys, xs = np.nonzero(mask)
        r_img = 0.5 * min(np.ptp(xs), np.ptp(ys))
        layer = np.zeros((h, w, 3), np.float32)
        alpha = np.zeros((h, w), np.float32)
        # a cluster: centres scattered around one point
        c0 = np.array([xs.mean(), ys.mean()]) + rng.uniform(-0.6, 0.6, 2) * r_img
        n = int(rng.integers(self.bubble_count[0], self.bubble_count[1] + 1))
        for _ in range(n):
            r = float(rng.uniform(*self.bubble_radius_frac)) * r_img
            c = c0 + rng.normal(0.0, 0.25 * r_img, 2)
            ci = tuple(int(v) for v in np.round(c))
            ri = max(2, int(round(r)))
            inner = np.zeros((h, w), np.uint8)
            cv2.circle(inner, ci, ri, 1, -1, cv2.LINE_AA)
            rim = np.zeros((h, w), np.uint8)
            cv2.circle(rim, ci, ri, 1, max(1, ri // 8), cv2.LINE_AA)
            hl = np.zeros((h, w), np.uint8)
            cv2.circle(hl, (int(c[0] - 0.35 * r), int(c[1] - 0.35 * r)), max(1, ri // 5), 1, -1, cv2.LINE_AA)
            for m, a, col in ((inner, 0.18, (235, 225, 200)), (rim, 0.7, (250, 245, 230)), (hl, 0.9, (255, 255, 255))):
                sel = m > 0
                alpha[sel] = np.maximum(alpha[sel], a)
                layer[sel] = col
        alpha *= mask
        out = rgb.astype(np.float32) * (1 - alpha[..., None]) + layer * alpha[..., None]
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)

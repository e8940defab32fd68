"""Image artefacts of real capsule frames that the geometric renderer does not produce: gas bubbles, and the
capsule camera's own imaging chain (:class:`CameraOptics`).

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

__all__ = ["Bubbles", "CameraOptics"]


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


@dataclass(frozen=True)
class CameraOptics:
    """What a real capsule camera does to its picture after the optics (``[optics]``; every default is off, so
    the ideal scenarios are unchanged). Applied in this order to the noisy 8-bit frame:

    - ``colour_gain`` (r, g, b): a colour response / white balance (PillCam frames have a yellow-brown cast);
    - ``vignetting``: gain ``1 - vignetting (r / r_max)^2`` over the image circle (lens fall-off beyond the
      renderer's LED profile);
    - ``field_stop``: ``"circle"`` or ``"octagon"`` -- everything outside is black; ``stop_radius_frac`` is its
      inscribed radius as a fraction of half the image's shorter side (an octagon's corners reach 1/cos(22.5
      deg) = 1.082 times further);
    - ``overlay_text``: burned-in text (a logo, a frame counter) drawn in the corner, as capsule recorders do;
    - ``jpeg_quality``: a lossy JPEG round trip (0: none) -- 8x8 compression blocks.

    The pipeline is told none of this: ``meta.json`` gives the lens model, not the stop or the overlay.
    """

    colour_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.0
    field_stop: str = "none"
    stop_radius_frac: float = 1.0
    overlay_text: str = ""
    jpeg_quality: int = 0

    def __post_init__(self) -> None:
        from bodyslam.errors import ConfigError

        if self.field_stop not in ("none", "circle", "octagon"):
            raise ConfigError(f"[optics] field_stop must be none, circle or octagon, got {self.field_stop!r}")
        if not (0.3 <= self.stop_radius_frac <= 1.5 and 0 <= self.vignetting < 1 and 0 <= self.jpeg_quality <= 100
                and len(self.colour_gain) == 3 and all(0 < g <= 2 for g in self.colour_gain)):
            raise ConfigError("[optics]: stop_radius_frac in [0.3, 1.5], vignetting in [0, 1), jpeg_quality 0-100, "
                              "colour_gain three numbers in (0, 2]")

    @property
    def active(self) -> bool:
        return self != CameraOptics()

    def stop_mask(self, h: int, w: int) -> np.ndarray:
        """The field stop's open area (bool ``(h, w)``)."""
        if self.field_stop == "none":
            return np.ones((h, w), bool)
        cx, cy, r = (w - 1) / 2, (h - 1) / 2, self.stop_radius_frac * min(h, w) / 2
        if self.field_stop == "circle":
            yy, xx = np.mgrid[:h, :w]
            return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        R = r / np.cos(np.pi / 8)  # the octagon's circumradius; its sides are flat toward the image axes
        ang = np.pi / 8 + np.arange(8) * np.pi / 4
        pts = np.c_[cx + R * np.cos(ang), cy + R * np.sin(ang)]
        m = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(m, np.rint(pts * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        return m.astype(bool)

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        if not self.active:
            return rgb
        h, w = rgb.shape[:2]
        img = rgb.astype(np.float32) * np.asarray(self.colour_gain, np.float32)
        if self.vignetting > 0:
            yy, xx = np.mgrid[:h, :w]
            r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (min(h, w) / 2) ** 2
            img *= (1.0 - self.vignetting * np.minimum(r2, 1.0))[..., None]
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        img[~self.stop_mask(h, w)] = 0
        if self.overlay_text:
            scale = h / 640
            cv2.putText(img, self.overlay_text, (int(0.03 * w), int(0.06 * h)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                        (235, 235, 235), max(1, int(round(2 * scale))), cv2.LINE_AA)
        if self.jpeg_quality:
            ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)])
            img = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
        return np.ascontiguousarray(img)

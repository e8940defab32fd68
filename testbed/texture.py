"""Mucosa textures for the tube wall.

Data form: an albedo texture is ``float32 (n_around, n_along, 3)`` RGB in [0, 1]; row ``i`` is the angle
``phi = 2 pi i / n_around`` around the lumen, column ``j`` the arc length ``s = length_m * j / n_along``. It wraps in
both directions (the procedural one is periodic by construction: every component is synthesised in the Fourier
domain of the torus), so the wall has no seam around the circumference and repeats every ``length_m`` along it.

Components of :func:`procedural_mucosa`: smooth colour variation, fine villous grain (this is what feature
matchers latch onto), branching vessels (ridged noise) and circular folds (bands of constant ``s``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from bodyslam.errors import InputError
from bodyslam.io import read_image

__all__ = ["Texture", "procedural_mucosa", "texture_from_image"]


@dataclass(frozen=True, eq=False)
class Texture:
    """A periodic albedo texture with a mip pyramid (level ``l`` averages ``2^l x 2^l`` texels)."""

    albedo: np.ndarray  # (n_around, n_along, 3) float32 in [0, 1]
    length_m: float  # physical length along the lumen covered by one repeat

    def __post_init__(self) -> None:
        a = self.albedo
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 8 or a.shape[1] < 8:
            raise InputError(f"texture must be (n_around >= 8, n_along >= 8, 3), got {a.shape}")
        pyr = [np.ascontiguousarray(a, dtype=np.float32)]
        while min(pyr[-1].shape[:2]) >= 8 and pyr[-1].shape[0] % 2 == 0 and pyr[-1].shape[1] % 2 == 0:
            p = pyr[-1]
            pyr.append(0.25 * (p[0::2, 0::2] + p[1::2, 0::2] + p[0::2, 1::2] + p[1::2, 1::2]))
        object.__setattr__(self, "pyramid", pyr)

    def sample(self, s_m: np.ndarray, phi_rad: np.ndarray, footprint_m: np.ndarray | None = None) -> np.ndarray:
        """Bilinear, mip-mapped albedo at wall coordinates. Arrays of equal shape; returns ``shape + (3,)``.

        ``footprint_m`` is the size of a pixel's footprint on the wall; the mip level is chosen to match it
        (trilinear), which removes the aliasing of one ray per pixel.
        """
        shape = np.shape(s_m)
        s = np.asarray(s_m, dtype=np.float32).reshape(-1)
        ph = np.asarray(phi_rad, dtype=np.float32).reshape(-1)
        n_along = self.albedo.shape[1]
        n_levels = len(self.pyramid)
        if footprint_m is None:
            return self._sample_level(0, s, ph).reshape(shape + (3,))
        texel_m = self.length_m / n_along
        level = np.log2(np.maximum(np.asarray(footprint_m, np.float32).reshape(-1) / np.float32(texel_m), 1.0))
        level = np.minimum(level, np.float32(n_levels - 1.001))
        lo = level.astype(np.int32)  # level >= 0: truncation is floor
        frac = (level - lo)[:, None]
        out = np.empty((len(s), 3), np.float32)
        # Each point blends its two nearest mip levels (trilinear); points are grouped by their lower level.
        for lv in np.unique(lo):
            sel = np.nonzero(lo == lv)[0] if lo.min() != lo.max() else slice(None)
            a0 = self._sample_level(lv, s[sel], ph[sel])
            a1 = self._sample_level(lv + 1, s[sel], ph[sel])
            out[sel] = a0 + frac[sel] * (a1 - a0)
        return out.reshape(shape + (3,))

    def _sample_level(self, lv: int, s: np.ndarray, ph: np.ndarray) -> np.ndarray:
        tex = self.pyramid[min(int(lv), len(self.pyramid) - 1)]
        h, wd = tex.shape[:2]
        mx = np.mod(s * np.float32(wd / self.length_m) - np.float32(0.5), np.float32(wd))
        my = np.mod(ph * np.float32(h / (2 * np.pi)) - np.float32(0.5), np.float32(h))
        return _remap_points(tex, mx, my)


def _remap_points(tex: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear wrap-around lookups of ``n`` points (cv2.remap needs 2-D maps under 32767 per side)."""
    n = len(mx)
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mx2 = np.pad(mx, (0, pad)).reshape(rows, cols)
    my2 = np.pad(my, (0, pad)).reshape(rows, cols)
    out = cv2.remap(tex, mx2, my2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, tex.shape[2])[:n]


def _periodic_noise(shape, rng, beta: float, low_cut: float = 0.0, high_cut: float | None = None) -> np.ndarray:
    """Zero-mean, unit-std noise with power spectrum ~ 1/f^beta on a torus (periodic in both axes)."""
    fy = np.fft.fftfreq(shape[0])[:, None] * 1024.0  # cycles per 1024 texels (texels are ~square on the wall)
    fx = np.fft.rfftfreq(shape[1])[None, :] * 1024.0
    f = np.hypot(fy, fx)
    amp = np.where(f > 0, (f + 1e-6) ** (-beta / 2.0), 0.0)
    if low_cut > 0:
        amp *= 1.0 - np.exp(-((f / low_cut) ** 2))
    if high_cut is not None:
        amp *= np.exp(-((f / high_cut) ** 2))
    spec = amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape))
    n = np.fft.irfft2(spec, s=shape)
    return (n - n.mean()) / (n.std() + 1e-12)


def procedural_mucosa(
    rng: np.random.Generator | int | None,
    n_around: int = 512,
    n_along: int = 1024,
    length_m: float = 0.2,
    base_rgb: tuple[float, float, float] = (0.88, 0.46, 0.32),
    fold_spacing_m: float = 0.008,
    fold_strength: float = 0.35,
    vessel_strength: float = 0.6,
    grain_strength: float = 0.12,
) -> Texture:
    """A seeded small-bowel mucosa texture (see module docstring). Periodic around and along the lumen."""
    rng = np.random.default_rng(rng)
    shape = (n_around, n_along)
    base = np.asarray(base_rgb, np.float32)
    low = _periodic_noise(shape, rng, beta=3.0)  # broad colour/brightness variation
    hue = _periodic_noise(shape, rng, beta=3.0)
    grain = _periodic_noise(shape, rng, beta=0.8, low_cut=40.0, high_cut=400.0)  # villi-scale detail
    blobs = _periodic_noise(shape, rng, beta=1.6, low_cut=15.0)  # lymphoid/patchy spots
    ridged = 1.0 - np.abs(_periodic_noise(shape, rng, beta=2.6, low_cut=3.0))
    vessels = np.clip((ridged - 0.80) / 0.20, 0.0, 1.0) ** 2
    j = np.arange(n_along)[None, :] * (length_m / n_along)
    n_folds = max(1, int(round(length_m / fold_spacing_m)))
    wobble = 0.25 * _periodic_noise(shape, rng, beta=3.5)
    folds = 0.5 + 0.5 * np.cos(2 * np.pi * n_folds * (j / length_m) + wobble)  # constant-s bands, wavy
    folds = folds**4 * np.clip(0.6 + 0.5 * _periodic_noise(shape, rng, beta=3.0), 0.0, 1.0)  # folds fade in/out
    shade = 1.0 + 0.10 * low + grain_strength * grain + 0.06 * blobs - fold_strength * folds
    rgb = base[None, None, :] * shade[..., None]
    rgb[..., 0] *= 1.0 + 0.05 * hue
    rgb[..., 2] *= 1.0 - 0.08 * hue
    vessel_rgb = np.array([0.55, 0.12, 0.12], np.float32)
    rgb = rgb * (1 - vessel_strength * vessels[..., None]) + vessel_strength * vessels[..., None] * vessel_rgb
    return Texture(np.clip(rgb, 0.0, 1.0).astype(np.float32), float(length_m))


def texture_from_image(path: str | Path, length_m: float) -> Texture:
    """A user texture image: rows run around the lumen, columns along it; it is tiled (wrapped) both ways.

    The image is cropped to even dimensions for the mip pyramid. Seams show unless the image itself tiles.
    """
    img = read_image(path).astype(np.float32) / 255.0
    h, w = img.shape[:2]
    if h < 8 or w < 8:
        raise InputError(f"{path}: texture image too small ({w}x{h}); need at least 8x8")
    img = img[: h - h % 2, : w - w % 2]
    return Texture(img, float(length_m))

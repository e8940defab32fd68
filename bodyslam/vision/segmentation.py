"""Statistical Region Merging (Nock & Nielsen 2004; dissertation Sec. 3.2.1.1, Eq. 3.1) of colour frames.

Pixel pairs of the 4-neighbourhood are visited in increasing order of their largest per-channel difference;
two regions ``R, R'`` merge when, in every colour channel, ``|mean(R) - mean(R')| <= sqrt(b2(R) + b2(R'))`` with
``b2(R) = g^2 / (2 Q |R|) * (min(g, |R|) ln(1 + |R|) + ln(6 |I|^2))`` (the paper's bound with
``delta = 1 / (6 |I|^2)``; ``g = 256`` levels, ``|I|`` the number of pixels). ``Q`` sets the coarseness: the
dissertation uses 16. ``b2`` is multiplied by ``relax = 0.1`` as in the reference implementation most users know
(Fiji's SRM plug-in): with the paper's bound as printed (``relax = 1``) and Q = 16, a capsule frame merges into
1-4 regions and the tunnel is lost (measured on testbed frames; STACK-NOTES.md), unlike Fig. 3.3. Only pixels
inside the valid field-of-view mask take part; outside is label -1 (at the working size, a pixel whose footprint
straddles the mask's edge is outside too).

Speed: the merge loop is sequential union-find (SRM's order matters), so numpy cannot vectorise it. It is
compiled (``_srm_merge.c``, built by ``pip install`` where a C compiler is at hand: ~15 ns per pixel pair) and
otherwise runs the same loop in Python (~0.7 us per pair; logged once); both give the same regions bit for bit
(tested). A 64-pixel frame (fast mode's classification) takes 1.5 ms against 5.2 ms with the Python loop.
:func:`srm` segments a copy resized so its longer side is ``work_px`` (default 96 pixels: the classifier's
region features are coarse, see :mod:`bodyslam.vision.classify`) and returns labels at that size;
``work_px=None`` segments at full resolution (``bodyslam segment --full``).

Data form: :class:`Segmentation` with ``labels (h, w) int32`` (-1 outside the mask, else 0..n-1),
``means (n, 3) float64`` RGB region means and ``sizes (n,)`` pixel counts, at the working resolution.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from bodyslam.errors import ConfigError, InputError

__all__ = ["Segmentation", "srm", "paint_regions"]

log = logging.getLogger(__name__)

# the share of a working pixel's footprint that must lie in the field of view (_resize_for_work): all of it, less
# float rounding
INSIDE_FRAC = 1.0 - 1e-6

try:  # the merge loop compiled (setup.py builds it where a C compiler is at hand); else the same loop in Python
    from bodyslam.vision import _srm_merge as _merge_c
except ImportError:
    _merge_c = None
_warned = False


def _warn_python_loop() -> None:
    global _warned
    if not _warned:
        _warned = True
        log.info("SRM: the compiled merge loop (bodyslam/vision/_srm_merge.c) is not built here; using the same "
                 "loop in Python, ~3.5x slower segmentation (reinstall with a C compiler: pip install -e .)")


@dataclass(frozen=True, eq=False)
class Segmentation:
    labels: np.ndarray
    means: np.ndarray
    sizes: np.ndarray

    @property
    def n_regions(self) -> int:
        return len(self.sizes)


def _resize_for_work(rgb: np.ndarray, mask: np.ndarray, work_px: int | None):
    h, w = mask.shape
    if work_px is None or max(h, w) <= work_px:
        return rgb, mask
    s = work_px / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return small, _work_mask(mask, size)


_WORK_MASKS: dict = {}  # (size, mask bytes) -> the working mask: an exam's frames share one field of view


def _work_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The field-of-view ``mask`` at the working ``size`` (w, h).

    A working pixel takes part only when every frame pixel it averages lies inside the field of view: one that
    straddles the field stop's edge averages in the black outside, and those pixels formed a dark one-pixel line
    along the stop that the classifier took for the darkest region (session 29: on all four real PillCam frames
    and on the realistic testbed's octagon-stopped frames, 1% of the field, width 0, on the rim). Until then a
    nearest-neighbour resize kept them. Remembered for the last few masks (a frame's resize of its mask was a
    tenth of its segmentation)."""
    key = (size, mask.shape, mask.dtype.str, mask.tobytes())
    m = _WORK_MASKS.get(key)
    if m is None:
        m = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= INSIDE_FRAC
        m.flags.writeable = False
        if len(_WORK_MASKS) >= 8:
            _WORK_MASKS.pop(next(iter(_WORK_MASKS)))
        _WORK_MASKS[key] = m
    return m


def srm(rgb: np.ndarray, mask: np.ndarray | None = None, Q: float = 16.0, work_px: int | None = 96,
        relax: float = 0.1) -> Segmentation:
    """Segment an RGB ``uint8 (h, w, 3)`` frame (see module docstring; ``relax`` scales the merge bound)."""
    rgb = np.asarray(rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"SRM needs an RGB or grey image, got shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise InputError(f"SRM needs 8-bit images, got {rgb.dtype}")
    if not Q > 0:
        raise ConfigError(f"SRM's Q must be positive, got {Q}")
    if mask is None:
        mask = np.ones(rgb.shape[:2], bool)
    if mask.shape != rgb.shape[:2]:
        raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, image is {rgb.shape[1]}x{rgb.shape[0]}")
    img, m = _resize_for_work(rgb, mask, work_px)
    h, w = m.shape
    n_pix = int(m.sum())
    if n_pix == 0:
        raise InputError("the field-of-view mask is empty")
    flat = img.reshape(-1, 3).astype(np.float64)
    idx = np.arange(h * w).reshape(h, w)
    # 4-neighbour pairs inside the mask, sorted by the largest channel difference (stable: reproducible)
    pa = np.concatenate([idx[:, :-1][m[:, :-1] & m[:, 1:]], idx[:-1, :][m[:-1, :] & m[1:, :]]])
    pb = np.concatenate([idx[:, 1:][m[:, :-1] & m[:, 1:]], idx[1:, :][m[:-1, :] & m[1:, :]]])
    # the differences are whole levels 0..255 (taken in int16, exactly): as uint8 the stable sort is a radix sort,
    # same order, ~5x faster
    px = img.reshape(-1, 3).astype(np.int16)
    d3 = np.abs(px[pa] - px[pb])
    diff = np.maximum(np.maximum(d3[:, 0], d3[:, 1]), d3[:, 2]).astype(np.uint8)  # max over 3: ~3x .max(axis=1)
    order = np.argsort(diff, kind="stable")
    pa, pb = pa[order], pb[order]

    g = 256.0
    log_term = math.log(6.0 * n_pix * n_pix)
    k = relax * g * g / (2.0 * Q)
    # b2 of a region of n pixels, for every n (a table: the loop then does no log or min)
    nn = np.arange(n_pix + 1, dtype=np.float64)
    nn[0] = 1.0
    b2_tab = k / nn * (np.minimum(g, nn) * np.log1p(nn) + log_term)
    if _merge_c is not None:
        parent = np.arange(h * w, dtype=np.intp)
        # the sums are written in place: ``flat`` is this call's own copy and is not read again
        _merge_c.merge(pa.astype(np.intp, copy=False), pb.astype(np.intp, copy=False), b2_tab, parent,
                       np.ones(h * w, np.intp), flat)
    else:
        _warn_python_loop()
        parent = _merge_python(pa.tolist(), pb.tolist(), b2_tab.tolist(), flat)
    roots = np.asarray(parent)
    while True:  # pointer jumping: every pixel's root, vectorised
        nxt = roots[roots]
        if np.array_equal(nxt, roots):
            break
        roots = nxt
    roots[~m.ravel()] = -1
    labels = _region_labels(roots).reshape(h, w)
    valid = labels >= 0
    n_reg = int(labels.max()) + 1
    sizes = np.bincount(labels[valid], minlength=n_reg)
    means = np.stack([np.bincount(labels[valid], weights=img[..., c][valid], minlength=n_reg) for c in range(3)],
                     axis=1) / np.maximum(sizes, 1)[:, None]
    return Segmentation(labels, means, sizes)


def _region_labels(roots: np.ndarray) -> np.ndarray:
    """Each pixel's region number ``int32 (n,)`` from its root pixel ``roots (n,)`` (-1: outside the field, and
    -1 there): the root's rank among the roots, as ``np.unique(roots, return_inverse=True)`` numbers them,
    without its sort (a root is its own root)."""
    inside = roots >= 0
    rank = np.cumsum((roots == np.arange(len(roots))) & inside) - 1
    return np.where(inside, rank[np.maximum(roots, 0)], -1).astype(np.int32)


def _merge_python(pa: list[int], pb: list[int], b2_tab: list[float], flat: np.ndarray) -> list[int]:
    """SRM's merge loop in Python (where the compiled one, ``_srm_merge.c``, was not built): the pairs in their
    order, union-find with path halving; returns the parents. Kruskal-style merging in edge order; the union-find
    is inlined (no function calls: the loop is the cost of classification); the result does not depend on how
    the roots are found."""
    n = len(flat)
    parent = list(range(n))
    size = [1] * n
    sr, sg, sb = (flat[:, c].tolist() for c in range(3))  # per-channel running sums of each root
    for a, b in zip(pa, pb):
        while parent[a] != a:
            parent[a] = a = parent[parent[a]]
        while parent[b] != b:
            parent[b] = b = parent[parent[b]]
        if a == b:
            continue
        na, nb = size[a], size[b]
        thr = b2_tab[na] + b2_tab[nb]
        d = sr[a] / na - sr[b] / nb
        if d * d > thr:
            continue
        d = sg[a] / na - sg[b] / nb
        if d * d > thr:
            continue
        d = sb[a] / na - sb[b] / nb
        if d * d > thr:
            continue
        if na < nb:
            a, b = b, a
        parent[b] = a
        size[a] = na + nb
        sr[a] += sr[b]
        sg[a] += sg[b]
        sb[a] += sb[b]
    return parent


def paint_regions(seg: Segmentation, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Each region drawn in its mean colour (Fig. 3.3), black outside the mask; resized to ``shape`` (h, w)."""
    out = np.zeros(seg.labels.shape + (3,), np.uint8)
    valid = seg.labels >= 0
    out[valid] = np.rint(seg.means[seg.labels[valid]]).astype(np.uint8)
    if shape is not None and shape != out.shape[:2]:
        out = cv2.resize(out, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return out

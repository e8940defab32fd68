"""Each step's scale tied to its neighbours' by the depths of the points they share.

Why: the tube fit (:func:`bodyslam.vision.motion.fit_tube`) reads each step's length in units of the lumen radius
it assumes. Where the lumen is not that cylinder -- narrower, wider, folded, a contraction in view -- the step
comes out too long or too short by a factor that changes from step to step (on the realistic testbed's reporting
seeds the steps err by ~25% of their length at every distance, +60% where the gut is 0.6-0.8 cm wide and -10% where
it is 1.4-1.6 cm). One step cannot see that factor: scaling the whole scene changes no pixel. Two consecutive steps
can see how their factors differ. Steps ``a`` (frames k-1 -> k) and ``b`` (k -> k+1) both see the wall in frame
k: triangulated with each step's own fitted motion, the same wall point lies at depth ``z s_a`` for ``a`` and
``z s_b`` for ``b``, ``s`` being each step's length over the true one. The median over the points both steps
matched of ``log(depth_b / depth_a)`` is ``log(s_b / s_a)``, the *scale link* of step ``b``
(:func:`scale_link`; on realistic tuning seeds 567-570 it follows the truth with a correlation of 0.98 over 274
links, its error 0.05 in log at the median absolute deviation).

The links alone would drift (each errs a little, and they add up along a chain), so each step's log scale ``x``
is solved from both (:func:`chain_factors`): its links, and a prior that ``x`` is 0 with a 1-sigma that grows with
the fit's own relative uncertainty (:data:`STEP_SD_FIT`, :data:`STEP_SD_FLOOR`). Well-fitted steps hold the chain;
a poorly fitted step between two good ones is pulled to what its links say. The step's length is then divided by
``exp(x)``; its 1-sigma is left as it was (the lumen-shape share of it, ``lumen_shape_sd_rel``, is what this
corrects in part, and keeping it errs on the safe side). The exam-wide level is not this module's: the lumen scale
(:mod:`bodyslam.vision.lumen_scale`) sets it, and the prior keeps the chain's mean log scale near 0.

Only where the radius is a prior (as the lumen scale; :func:`bodyslam.vision.odometry.lumen_scale_measured`): on
the ideal tube the radius is told exactly, the steps err by ~0.001 cm, and the links' own noise would add more.

Chosen on realistic tuning seeds 562-565 and 567-570 (``sift``, the steps' stored matches; docs/RESULTS.md, "Each
step's scale tied to its neighbours'"): the steps' distance error with each run's best single factor removed
0.0513 -> 0.0488 cm (7 of the 8 seeds lower, one equal); the constants below moved it by less than 0.001 cm
either way. Links between steps that are too short (no parallax) are meaningless (log ratios of 7-11 were seen)
and are left out: :data:`MIN_STEP_RADII`, :data:`MIN_LINK_POINTS`, :data:`MAX_LINK_LOG`. Reporting seeds 700-709
(once, ``bodyslam motion`` on session 31's frames): the per-step distance error 0.0558 -> 0.0543 cm, lower on 9
of the 10 seeds and equal on one, p90 0.136 -> 0.130 cm; the fusion within noise (smoothed 3.74 -> 3.75 cm).

Chunking: a step's link needs the previous step's points, so a chunk hands on the points of its first and last
steps (:class:`Signature`) and whoever joins the chunks links the seams with the same function: the result does
not depend on the chunking.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import solveh_banded
from scipy.spatial import cKDTree

from bodyslam.camera import CameraModel
from bodyslam.geometry import rotvec_to_matrix
from bodyslam.steps import MEASURED, StepMotion

__all__ = ["Signature", "step_signatures", "scale_link", "linked", "chain_factors", "chained", "chain_summary",
           "MIN_PARALLAX_RAD", "LINK_TOL_PX", "MIN_LINK_POINTS", "MAX_LINK_LOG", "MIN_STEP_RADII"]

MIN_PARALLAX_RAD = 0.02  # a point's two rays must part by this (~1.1 deg) for its depth to count
LINK_TOL_PX = 1.0  # a point of step a's frame 2 and one of step b's frame 1 are the same within this (SIFT's
#                    keypoints are the same points exactly; tracked corners lie within a pixel of the detected ones)
MIN_LINK_POINTS = 10  # fewer shared points: no link
MAX_LINK_LOG = 2.0  # |log ratio| above this (a factor of 7.4) is no measurement of the scale but a failed one
LINK_SD_MAD_FACTOR = 3.0  # a link's 1-sigma: LINK_SD_MAD_FACTOR * MAD / sqrt(n) + LINK_SD_FLOOR; the MAD's
LINK_SD_FLOOR = 0.1  # own figure was ~3-8x optimistic against the truth on the tuning seeds
LINK_MAD_MIN = 0.02
STEP_SD_FIT = 0.5  # a step's prior 1-sigma on its log scale: STEP_SD_FIT * (fit's 1-sigma / distance) + STEP_SD_FLOOR
STEP_SD_FLOOR = 0.05
MIN_STEP_RADII = 0.04  # a step shorter than this many lumen radii (0.5 mm at 1.25 cm) takes no part


@dataclass(frozen=True, eq=False)
class Signature:
    """The points of one frame of a fitted step: pixel positions ``(n, 2)`` and the log of their depth along
    the ray (m), triangulated with the step's own motion."""

    pts_px: np.ndarray
    log_depth: np.ndarray

    def to_json(self) -> list:
        """Rows ``[x, y, log depth]``; exact (:func:`step_signatures` rounds them), so a link from a batch chunk's
        handed-on points equals the one made in memory."""
        return [[float(x), float(y), float(z)] for (x, y), z in zip(self.pts_px, self.log_depth)]

    @classmethod
    def from_json(cls, rows: list | None) -> "Signature | None":
        if rows is None:
            return None
        a = np.asarray(rows, float).reshape(-1, 3)
        return cls(a[:, :2], a[:, 2])


def step_signatures(pts1_px: np.ndarray, pts2_px: np.ndarray, params: np.ndarray,
                    camera: CameraModel) -> tuple[Signature, Signature]:
    """Both frames' :class:`Signature` of a fitted step: its matches triangulated with the fit's rotation and
    translation (``params``: the tube fit's 10-vector, :func:`bodyslam.vision.motion.fit_tube`); only points in
    front of both cameras whose rays part by :data:`MIN_PARALLAX_RAD`."""
    b1, v1 = camera.unproject(np.asarray(pts1_px, float))
    b2, v2 = camera.unproject(np.asarray(pts2_px, float))
    R = rotvec_to_matrix(np.asarray(params, float)[None, 0:3])[0]
    t = np.asarray(params, float)[3:6]
    c = b2 @ R.T  # frame-2 rays in frame-1 axes: X = l1 b1 = t + l2 R b2
    a11, a12, a22 = np.sum(b1 * b1, 1), -np.sum(b1 * c, 1), np.sum(c * c, 1)
    r1, r2 = b1 @ t, -(c @ t)
    det = a11 * a22 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (a22 * r1 - a12 * r2) / det
        l2 = (a11 * r2 - a12 * r1) / det
    parallax = np.arccos(np.clip(np.sum(b1 * c, 1), -1.0, 1.0))
    keep = v1 & v2 & (parallax > MIN_PARALLAX_RAD) & (l1 > 0) & (l2 > 0) & np.isfinite(l1) & np.isfinite(l2)
    p1, p2 = np.asarray(pts1_px, float)[keep], np.asarray(pts2_px, float)[keep]
    # rounded far below the noise (1e-3 px, 1e-6 of depth) so that JSON carries them exactly (Signature.to_json)
    return (Signature(np.round(p1, 3), np.round(np.log(l1[keep]), 6)),
            Signature(np.round(p2, 3), np.round(np.log(l2[keep]), 6)))


def scale_link(a_frame2: Signature | None, b_frame1: Signature | None) -> tuple[float, float]:
    """``(log(s_b / s_a), its 1-sigma)`` from the points step ``a``'s frame 2 and step ``b``'s frame 1 share (the
    same frame); ``(nan, nan)`` where they share fewer than :data:`MIN_LINK_POINTS` or the ratio is implausible."""
    nan = (math.nan, math.nan)
    if a_frame2 is None or b_frame1 is None or len(a_frame2.pts_px) < MIN_LINK_POINTS \
            or len(b_frame1.pts_px) < MIN_LINK_POINTS:
        return nan
    dist, j = cKDTree(b_frame1.pts_px).query(a_frame2.pts_px, distance_upper_bound=LINK_TOL_PX)
    ok = np.isfinite(dist)
    n = int(ok.sum())
    if n < MIN_LINK_POINTS:
        return nan
    lr = b_frame1.log_depth[j[ok]] - a_frame2.log_depth[ok]
    med = float(np.median(lr))
    if abs(med) > MAX_LINK_LOG:
        return nan
    mad = 1.4826 * float(np.median(np.abs(lr - med)))
    return med, LINK_SD_MAD_FACTOR * max(mad, LINK_MAD_MIN) / math.sqrt(n) + LINK_SD_FLOOR


def linked(s: StepMotion, a_frame2: Signature | None, b_frame1: Signature | None) -> StepMotion:
    """Step ``s`` with its scale link to the previous step (:func:`scale_link` of the previous step's last-frame
    points and this step's first-frame ones)."""
    link, sd = scale_link(a_frame2, b_frame1)
    return replace(s, scale_link=link, scale_link_sd=sd)


def chain_factors(distance_m: np.ndarray, sigma_m: np.ndarray, link: np.ndarray, link_sd: np.ndarray,
                  member: np.ndarray, radius_m: float) -> np.ndarray:
    """The factor each step's length is multiplied by (module docstring): ``exp(-x)`` of the log scales solved
    from the links and the steps' priors; 1 for steps that take no part. Arrays over consecutive steps:
    ``link[i]`` ties step ``i`` to step ``i - 1``; ``member``: the steps measured from their own pair (``ok``,
    ``wall``). Linear in the steps (a tridiagonal solve)."""
    d = np.asarray(distance_m, float)
    sig = np.asarray(sigma_m, float)
    lk, lsd = np.asarray(link, float), np.asarray(link_sd, float)
    n = len(d)
    on = np.asarray(member, bool) & np.isfinite(d) & (np.abs(d) > MIN_STEP_RADII * radius_m) & np.isfinite(sig)
    out = np.ones(n)
    if not on.any():
        return out
    # normal equations: each step's prior on the diagonal (1 where it takes no part: x = 0), each link of step i
    # (joining i - 1 and i when both take part) on both diagonals and the upper band
    diag, rhs, w = np.ones(n), np.zeros(n), np.zeros(n)
    diag[on] = 1.0 / (STEP_SD_FIT * sig[on] / np.abs(d[on]) + STEP_SD_FLOOR) ** 2
    j = np.nonzero(on[1:] & on[:-1] & np.isfinite(lk[1:]) & np.isfinite(lsd[1:]) & (lsd[1:] > 0))[0] + 1
    w[j] = 1.0 / lsd[j] ** 2
    diag[j] += w[j]
    diag[j - 1] += w[j]  # j - 1 is unique per link: no two links share a left end
    rhs[j] += w[j] * lk[j]
    rhs[j - 1] -= w[j] * lk[j]
    ab = np.zeros((2, n))
    ab[0, 1:] = -w[1:]  # the upper band: element (i - 1, i)
    ab[1] = diag
    x = solveh_banded(ab, rhs) if n > 1 else rhs / diag  # (LAPACK's banded solver refuses a 1 x 1 system)
    out[on] = np.exp(-x[on])
    return out


def chained(steps: list[StepMotion], radius_m: float) -> tuple[list[StepMotion], dict]:
    """The steps with each measured one's length (translation, distance) multiplied by its chain factor
    (:func:`chain_factors`; the 1-sigma is kept), and a summary: steps that took part, links used, the factors'
    spread."""
    d = np.array([s.distance_m for s in steps], float)
    member = np.array([s.status in MEASURED and s.has_estimate for s in steps], bool)
    f = chain_factors(d, np.array([s.sigma_distance_m for s in steps], float),
                      np.array([s.scale_link for s in steps], float),
                      np.array([s.scale_link_sd for s in steps], float), member, radius_m)
    out = [replace(s, distance_m=s.distance_m * fi, t_c1_c2_m=s.t_c1_c2_m * fi, chain_factor=float(fi))
           if fi != 1.0 else s for s, fi in zip(steps, f)]
    return out, chain_summary(f, np.array([math.isfinite(s.scale_link) for s in steps], bool))


def chain_summary(factors: np.ndarray, has_link: np.ndarray) -> dict:
    """What ``summary.json`` and the logs say of the chain."""
    moved = factors != 1.0
    lf = np.log(factors[moved]) if moved.any() else np.zeros(0)
    return {"steps_chained": int(moved.sum()), "links": int(np.sum(has_link)),
            "factor_p10": float(np.exp(np.percentile(lf, 10))) if len(lf) else 1.0,
            "factor_p90": float(np.exp(np.percentile(lf, 90))) if len(lf) else 1.0}

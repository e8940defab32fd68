"""The lumen's scale seen in the images: a tube with one contraction ring, fitted to a sample of the steps.

Why: the tube fit (:func:`bodyslam.vision.motion.fit_tube`) takes its scale from the radius it is told, a
population prior on real exams. Where the gut narrows -- a contraction ring, a collapsed lumen -- the wall the
matches lie on is nearer than that cylinder, and the fit reads it as a cylinder of the prior's radius seen from
farther away: every step comes out too long, by the same factor along a stretch of gut (on the realistic testbed's
reporting seeds 18% long on average, the largest part of its per-step distance error). One cylinder cannot see that. A tube whose
radius narrows in one ring along the axis,

    r(z) = R (1 - A exp(-(z - c)^2 / (2 w^2))),   z the axial distance from the camera, w = RING_WIDTH_RADII R,

(two more unknowns: the ring's depth ``A``, bounded to +-RING_MAX_DEPTH, and its place ``c``; both frames see the
same wall) explains the same matches better (session 37: robust cost lower by 76 at the median on realistic
steps) and reads the step shorter where the lumen narrows. Taken step by step it is noisier than the cylinder
(docs/RESULTS.md, session 37), so it is used only for the *scale*: the ratio of its step length to the cylinder's,
on a sample of the exam's steps, whose median rescales every step of the exam
(:func:`exam_scale`; the fusion, the path travelled and motion.csv then carry the rescaled steps).

On the ideal tube (`thesis`) the ring fits nothing and the median ratio is 0.999-1.000 (tuning seed 566; there the
radius is told exactly, and a known radius is not rescaled: :func:`bodyslam.vision.odometry.lumen_scale_measured`);
on realistic tuning seeds 562-565 the factors are 0.78-0.96 and the per-step distance error falls 0.076 -> 0.059
cm, on reporting seeds 700-709 0.068 -> 0.059 cm (docs/RESULTS.md, "The lumen's scale from a contraction ring").
The ring's width, one lumen radius (session 39; 0.7 before, the testbed's own contraction rings' width), was chosen
on tuning seeds 562-570: wider, the ring also takes in the lumen's other narrowing (folds, a collapsed section), and
the reporting seeds' per-step distance error falls further, 0.059 -> 0.056 cm; a lone ring narrower than that is
over-corrected (docs/RESULTS.md, "The lumen scale: its ring fit compiled, the ring wider").

The ray-wall intersection has no closed form here: each ray is stepped along a grid of :data:`RING_GRID` depths
(denser near the camera) to the first point outside the wall, then refined by two regula-falsi steps. The fit is
started from the cylinder's solution with the ring at each of :data:`RING_STARTS_RADII` and the lowest robust cost
kept (its cost has a minimum per place the ring can sit). The residuals are compiled beside the cylinder's
(``_tube_fit.c``: ~0.07 s a fit instead of numpy's ~0.4 s on realistic tuning steps, ratios equal to ~1e-6).

**A ring must be seen** (session 41, docs/RESULTS.md "The lumen scale only where a ring is seen"). The ring's
depth is started at a narrowing (``a`` = 0.2, a ring closing the lumen by ~19%) and the solution nearest that start
is kept: started also at 0 and at a bulge (-0.2), the fit finds lower costs with rings of either sign, and on
realistic tuning seeds the factor then scatters about 1 (0.71-1.14) with the per-step distance error back at the
prior's (0.068 against 0.056 cm without the scale chain): the ring model does not describe a folded lumen well
enough for its best fit to be the scale. What the ratio measures is "how much shorter the step is if the wall ahead
narrows". Where no ring is to be seen the fit still settles on some narrowing, and the ratio comes out short
whatever the lumen: on the ideal `exam` tube (its first 1,000 frames, fast mode, the radius given only as a prior;
its radius varies by +-8% along the gut) the median ratio was 0.94, on a plain synthetic cylinder with 0.6-mm
steps and 1-px noise 0.76-0.85. So a ratio counts only where the ring is seen: where it lowers the fit's robust cost
(:func:`bodyslam.vision.motion._soft_l1_cost`) from the cylinder's solution by more than
:data:`RING_MIN_COST_DROP` in units of the assumed ray noise (it moves the rays by more than the fits' noise: an
effect, not a few percent of radius) and by more than :data:`RING_MIN_DROP_SIGNIFICANCE` times the step's own
residual scale (a likelihood-ratio test for its two parameters on the matches as noisy as they are); elsewhere it is
NaN. On that `exam` tube 13 of 124 sampled steps pass, too few: the prior's scale stands (factor 1). On realistic
tuning seeds most steps pass (the median drop is 77). Fewer ratios survive, so the sample is denser
(:data:`RING_EVERY_MIN`, :data:`RING_SAMPLES_MAX`).

**An exam that shows rings** (session 42, docs/RESULTS.md "The lumen scale where an exam shows rings"). Even so a
lumen without rings lets a few steps through: 8-10.5% of the sampled fitted steps on the ideal `exam` tube (10 of
124 on seed 1's 2,000 frames, 13 of 124 on its 10,000-frame render's first 1,000), whose ratios read short (median
0.95). Until session 42 a count of 24 kept them out, and cut realistic runs with fewer rings off the scale they show
(reporting seed 709: 23). The factor now applies where the exam shows rings: at least :data:`RING_MIN_SAMPLES`
ratios, and more of them among the fitted steps sampled than a lumen without rings lets through -- a one-sided
binomial test against a share of :data:`RING_NULL_SHARE` at level :data:`RING_SHARE_ALPHA` (:func:`exam_scale`; the
steps the ring was fitted to are counted by :func:`ring_tried`). Realistic tuning runs show rings on 40-75% of them.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from bodyslam.camera import CameraModel
from bodyslam.geometry import rotvec_to_matrix
from bodyslam.steps import StepMotion
# _tube_c: the compiled residuals (None: not built); lm_compiled: the fit's loop in C (None where it is not)
from bodyslam.vision.motion import _lm_soft_l1, _soft_l1_cost, _tube_c, lm_compiled

__all__ = ["RING_EVERY_MIN", "RING_SAMPLES_MAX", "RING_MIN_SAMPLES", "RING_SAMPLE_MIN_STEPS", "RING_NULL_SHARE",
           "RING_SHARE_ALPHA", "RING_MIN_COST_DROP", "RING_MIN_DROP_SIGNIFICANCE", "SCALE_SD_FLOOR_REL",
           "SCALE_LOCAL_SD_REL", "ring_tried", "shows_rings", "ring_every", "ring_distance_ratio", "exam_scale",
           "exam_scale_sd_rel", "scale_of_steps", "binomial_tail", "radius_sd_rel_after", "local_sd_rel_after",
           "rescaled", "lumen_scale_summary", "lumen_scale_text"]

RING_WIDTH_RADII = 1.0  # the ring's width w (Gaussian sigma along the axis), lumen radii (session 39; 0.7 to 38)
RING_MAX_DEPTH = 0.6  # |A| bound: the ring closes the lumen by at most 60% (A = 0.6 tanh(a / 0.6))
RING_DEPTH_SD = 0.3  # the prior on A (about 0): a ring must be seen to be fitted
RING_PLACE_SD_RADII = 2.0  # the prior on the ring's place about its start, lumen radii
RING_STARTS_RADII = (1.0, 2.0, 3.5)  # its places tried, lumen radii ahead of the camera
RING_GRID = 32  # depths per ray for the first wall crossing (32 and 64 gave the same ratios within 1-2%)
# the sample: every RING_EVERY_MIN-th step at most, and at most ~RING_SAMPLES_MAX in an exam (each fit ~0.07 s
# compiled, ~0.2-0.5 s in numpy: a whole exam's 64 cost ~5 s of one core, ~half a minute in numpy). An exam with
# fewer than RING_MIN_SAMPLES measured ratios keeps the prior's scale: on realistic tuning seeds one step's ratio
# scatters by ~0.2 (robust sigma; 0.003 on the ideal tube); 8 on the demo clip gave 0.99 forwards and 0.91 played
# backwards (24 until session 42: the median of 24 is good to ~5%). An exam shorter than RING_SAMPLE_MIN_STEPS steps
# is not sampled at all. Session 41: every step at most, ~128 an exam (every 2nd and 64 before), since a ratio without a
# ring seen is dropped (RING_MIN_COST_DROP, RING_MIN_DROP_SIGNIFICANCE: ~25% of them on realistic tuning seeds,
# ~90% on the ideal `exam` tube); a whole exam's 128 fits cost ~4-7 s of one core (29 ms a fit on `exam` steps, 55 on
# realistic ones, CPU time on this machine, session 41).
RING_EVERY_MIN = 1
RING_SAMPLES_MAX = 128
# Session 42: the least count 24 -> 12, beside the share test below. Ratios drawn at random from realistic tuning
# runs 560-567 (each run's own, 200 draws; per-step distance error with the factor their median gives, against the
# run's whole median): 0.0502 cm from 6, 0.0492 from 8, 0.0478 from 12, 0.0472 from 16, 0.0467 from 24, 0.0462 from
# all (30-52), 0.0641 with no factor: a median of 12 keeps most of the gain (one ratio scatters by ~0.2, so the
# median of 12 is good to ~7%, against the 8-26% the factor corrects there)
RING_MIN_SAMPLES = 12
# an exam of fewer steps than this is not sampled at all (24, as before session 42): a clip's factor from a dozen
# ratios would differ between the clip and the clip reversed by ~10% (the median's scatter, twice), where issue 16
# asks the two paths to agree within 15%
RING_SAMPLE_MIN_STEPS = 24
# the share of the fitted steps sampled whose ring test passes where the lumen has no rings (the ideal `exam` tube,
# radius given as a prior: 10 of 124 and 13 of 124, two renders of seed 1; a plain synthetic cylinder with noisy
# short steps: 0 of 24), and the level at which an exam's share must exceed it (one-sided binomial test)
RING_NULL_SHARE = 0.10
RING_SHARE_ALPHA = 0.01
# a ring counts (module docstring) where it lowers the fit's robust cost (0.5 sum rho) from the cylinder's solution
# by more than RING_MIN_COST_DROP in units of the assumed ray noise -- it moves the rays by more than the noise the
# fits assume: an effect, not a few percent of radius -- and by more than RING_MIN_DROP_SIGNIFICANCE in units of the
# step's own residual scale (2 cost / (residuals - parameters)): a ring fitted to noisier matches than assumed is
# not one (twice the drop over the scale against chi-square with the ring's 2 parameters: 10, p ~ 0.007). Chosen on
# realistic tuning seeds 562-570 (stored matches, the scale chain before the factor; per-step distance error 0.0531
# cm as before, 0.0509 with the denser sample and no test, 0.0508 with the first test alone, 0.0507 with both,
# 0.0504-0.0518 for the second at 3-10), the `exam` tube's first 1,000 frames (factor 0.942 with no test, 1 with the
# first: 13 of 124 steps pass; 0.87 with the second alone at 3) and synthetic cylinders (0.6-mm steps, 1-px
# noise, twice the assumed: 5 of 12 rings pass the first test alone, 3 both at 3, 1 at 5)
RING_MIN_COST_DROP = 10.0
RING_MIN_DROP_SIGNIFICANCE = 5.0
MIN_TUBE_STEP_M = 1e-5  # a step shorter than this has no ratio (0/0)


def ring_every(n_positions: int) -> int:
    """Which steps are sampled: those into positions divisible by this (so the sample is the same whatever the
    chunking): every :data:`RING_EVERY_MIN`-th, thinned so an exam has at most ~:data:`RING_SAMPLES_MAX`; 0 (none)
    where the exam is too short to sample :data:`RING_SAMPLE_MIN_STEPS` steps."""
    n = max(int(n_positions), 1)
    every = max(RING_EVERY_MIN, math.ceil(n / RING_SAMPLES_MAX))
    return every if (n - 1) // every >= RING_SAMPLE_MIN_STEPS else 0


def _ring_points(P: np.ndarray, b1: np.ndarray, radius: float, max_depth: float, grid: np.ndarray):
    """Where frame-1 rays ``b1 (n, 3)`` first leave the ringed tube, in frame 2's axes, for parameter vectors
    ``P (B, 12)`` (the cylinder's 10, then the ring's depth parameter and its place in radii)."""
    R = rotvec_to_matrix(P[:, 0:3])
    ax, ay = P[:, 6:7], P[:, 7:8]
    inv = 1.0 / np.sqrt(ax * ax + ay * ay + 1.0)
    ax, ay, az = ax * inv, ay * inv, inv
    ox, oy = P[:, 8:9], P[:, 9:10]
    A = RING_MAX_DEPTH * np.tanh(P[:, 10:11] / RING_MAX_DEPTH)
    c = P[:, 11:12] * radius
    w = RING_WIDTH_RADII * radius
    bx, by, bz = b1[:, 0], b1[:, 1], b1[:, 2]
    wx, wy, wz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax  # the ray's distance from the axis:
    ux, uy, uz = oy * az, -ox * az, ox * ay - oy * ax  # |lam w - u|, as in the cylinder's closed form
    ww = wx * wx + wy * wy + wz * wz
    wu = wx * ux + wy * uy + wz * uz
    uu = ux * ux + uy * uy + uz * uz
    ba = bx * ax + by * ay + bz * az  # axial distance per unit depth

    def f(lam):  # squared distance from the axis minus the wall's squared radius: < 0 inside
        z = lam * ba[..., None] if lam.ndim == 3 else lam * ba
        Ae, ce = (A[..., None], c[..., None]) if lam.ndim == 3 else (A, c)
        r = radius * (1.0 - Ae * np.exp(-0.5 * ((z - ce) / w) ** 2))
        w2, wu2, uu2 = (ww[..., None], wu[..., None], uu[..., None]) if lam.ndim == 3 else (ww, wu, uu)
        return lam * lam * w2 - 2.0 * lam * wu2 + uu2 - r * r

    lam = max_depth * grid
    F = f(np.broadcast_to(lam, ww.shape + lam.shape))
    outside = F >= 0
    first = np.argmax(outside, axis=-1)
    hit = np.take_along_axis(outside, first[..., None], -1)[..., 0]
    j0 = np.maximum(first - 1, 0)
    f0 = np.take_along_axis(F, j0[..., None], -1)[..., 0]
    f1 = np.take_along_axis(F, first[..., None], -1)[..., 0]
    l0, l1 = lam[j0], lam[first]
    with np.errstate(divide="ignore", invalid="ignore"):
        lh = np.where(f1 != f0, l0 - f0 * (l1 - l0) / (f1 - f0), l1)
        lh = np.where(first == 0, l1, lh)
        for _ in range(2):  # regula falsi inside the bracket
            fh = f(lh)
            inside = fh < 0
            l0, f0 = np.where(inside, lh, l0), np.where(inside, fh, f0)
            l1, f1 = np.where(inside, l1, lh), np.where(inside, f1, fh)
            nl = np.where(f1 != f0, l0 - f0 * (l1 - l0) / (f1 - f0), lh)
            lh = np.where(first == 0, lh, nl)
    lam_hit = np.where(hit, np.clip(lh, 1e-4, max_depth), max_depth)
    Xx, Xy, Xz = lam_hit * bx - P[:, 3:4], lam_hit * by - P[:, 4:5], lam_hit * bz - P[:, 5:6]
    cc = R[:, :, :, None]
    return (cc[:, 0, 0] * Xx + cc[:, 1, 0] * Xy + cc[:, 2, 0] * Xz,
            cc[:, 0, 1] * Xx + cc[:, 1, 1] * Xy + cc[:, 2, 1] * Xz,
            cc[:, 0, 2] * Xx + cc[:, 1, 2] * Xy + cc[:, 2, 2] * Xz)


def _axis_prior(radius: float) -> np.ndarray:
    """The cylinder fit's axis priors (:func:`bodyslam.vision.motion.fit_tube`'s ``prior_sigma``), which the ring fit
    keeps: tilt 0.35 rad, offset half a radius."""
    return np.array([0.35, 0.35, 0.5 * radius, 0.5 * radius])


def _ring_residuals(P, b1, b2, radius, max_depth, noise_rad, grid, c0):
    """The cylinder fit's residuals (ray angles over ``noise_rad``, the axis priors) for the ringed tube, and the
    ring's two priors: ``P (B, 12)`` -> ``(B, 3 n + 6)``. Compiled where ``_tube_fit.c`` was built (the same
    formulas, equal to ~1e-12; a call ~10x faster, a fit ~6x), else :func:`_ring_residuals_numpy`."""
    if _tube_c is None:
        return _ring_residuals_numpy(P, b1, b2, radius, max_depth, noise_rad, grid, c0)
    prior = _axis_prior(radius)
    out = np.empty((len(P), 3 * len(b1) + 6))
    _tube_c.ring_residuals(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(b1, np.float64),
                           np.ascontiguousarray(b2, np.float64), float(radius), float(max_depth), float(noise_rad),
                           prior, np.ascontiguousarray(grid, np.float64),
                           np.array([RING_MAX_DEPTH, RING_WIDTH_RADII, RING_DEPTH_SD, RING_PLACE_SD_RADII, c0],
                                    np.float64), out)
    return out


def _ring_residuals_numpy(P, b1, b2, radius, max_depth, noise_rad, grid, c0):
    """:func:`_ring_residuals` in numpy."""
    x, y, z = _ring_points(P, b1, radius, max_depth, grid)
    inv = 1.0 / (noise_rad * np.sqrt(x * x + y * y + z * z))
    cx, cy, cz = b2[:, 0], b2[:, 1], b2[:, 2]
    r = np.stack([(cy * z - cz * y) * inv, (cz * x - cx * z) * inv, (cx * y - cy * x) * inv], axis=-1)
    prior = _axis_prior(radius)
    return np.concatenate([r.reshape(len(P), -1), P[:, 6:10] / prior, P[:, 10:11] / RING_DEPTH_SD,
                           (P[:, 11:12] - c0) / RING_PLACE_SD_RADII], axis=1)


def ring_distance_ratio(pts1_px: np.ndarray, pts2_px: np.ndarray, camera: CameraModel, radius_m: float,
                        x_tube: np.ndarray, noise_rad: float = 0.003, max_depth_m: float = 0.3,
                        max_points: int = 150, min_cost_drop: float | None = None,
                        min_significance: float | None = None) -> float:
    """The step's length under the ringed tube over its length under the cylinder (``x_tube``: the cylinder fit's
    10-vector on the same matches, :func:`bodyslam.vision.motion.fit_tube`), NaN where there is none (a step of
    no length, a failed fit, or a ring the matches do not show: it lowers the robust cost by less than
    ``min_cost_drop``, or by less than ``min_significance`` times the step's own residual scale; module docstring;
    None: :data:`RING_MIN_COST_DROP`, :data:`RING_MIN_DROP_SIGNIFICANCE`; -inf: every ratio). The rays are the
    cylinder fit's: unprojected, valid in both frames, at most ``max_points`` evenly taken."""
    x_tube = np.asarray(x_tube, float)
    d_tube = float(np.linalg.norm(x_tube[3:6]))
    if not (np.all(np.isfinite(x_tube)) and d_tube > MIN_TUBE_STEP_M):
        return math.nan
    b1, v1 = camera.unproject(np.asarray(pts1_px, float))
    b2, v2 = camera.unproject(np.asarray(pts2_px, float))
    ok = v1 & v2
    b1, b2 = b1[ok], b2[ok]
    if len(b1) < 12:
        return math.nan
    if len(b1) > max_points:
        sel = np.linspace(0, len(b1) - 1, max_points).astype(int)
        b1, b2 = b1[sel], b2[sel]
    ratio, drop, scale = _ring_ratio_rays(b1, b2, radius_m, x_tube, noise_rad, max_depth_m)
    min_drop = RING_MIN_COST_DROP if min_cost_drop is None else min_cost_drop
    min_sig = RING_MIN_DROP_SIGNIFICANCE if min_significance is None else min_significance
    return ratio if drop > min_drop and drop > min_sig * scale else math.nan


def _ring_ratio_rays(b1: np.ndarray, b2: np.ndarray, radius_m: float, x_tube: np.ndarray, noise_rad: float,
                     max_depth_m: float) -> tuple[float, float, float]:
    """``(ratio, cost drop, residual scale)`` of :func:`ring_distance_ratio` on the matches' unit rays ``b1``,
    ``b2 (n, 3)``: the drop is the robust cost of the cylinder's solution (the ring of depth 0) less the ring fit's,
    in the fit's units (ray noise ``noise_rad``); the scale, the ring fit's cost per degree of freedom times 2 (1
    where the rays scatter as much as assumed); ``(nan, nan, nan)`` where the fit fails."""
    d_tube = float(np.linalg.norm(x_tube[3:6]))
    grid = (np.arange(1, RING_GRID + 1) / RING_GRID) ** 2
    x_scale = np.r_[[0.05] * 3, [0.003] * 3, [0.2] * 2, [0.005] * 2, [0.1, 0.5]]
    h = 1e-6 * x_scale
    h[11] = 1e-3  # the ring's place moves the first crossing by grid cells: a finite step
    f_scale = 2.0  # soft-L1's scale, in ray-noise units
    best = None
    for c0 in RING_STARTS_RADII:
        def fun(q, c0=c0):
            return _ring_residuals(q[None], b1, b2, radius_m, max_depth_m, noise_rad, grid, c0)[0]

        def fun_jac(q, c0=c0):
            Q = np.repeat(q[None], 13, axis=0)
            Q[1:] += np.diag(h)
            F = _ring_residuals(Q, b1, b2, radius_m, max_depth_m, noise_rad, grid, c0)
            return F[0], ((F[1:] - F[0]) / h[:, None]).T

        ring = np.array([RING_MAX_DEPTH, RING_WIDTH_RADII, RING_DEPTH_SD, RING_PLACE_SD_RADII, c0], np.float64)
        sol = lm_compiled(1, np.r_[x_tube, 0.2, c0], 12, b1, b2, radius_m, max_depth_m, noise_rad,
                          _axis_prior(radius_m), x_scale, h, f_scale, grid=grid, ring=ring)
        if sol is None:
            with np.errstate(all="ignore"):
                sol = _lm_soft_l1(np.r_[x_tube, 0.2, c0], fun_jac, fun, x_scale, f_scale)
        q, cost = sol[0], sol[3]
        if np.all(np.isfinite(q)) and np.isfinite(cost) and (best is None or cost < best[1]):
            best = (q, cost, c0)
    if best is None:
        return math.nan, math.nan, math.nan
    q, cost, c0 = best
    # the cylinder's own solution in the same cost: no ring (depth 0) at the ring fit's start place (its prior 0)
    f_cyl = _ring_residuals(np.r_[x_tube, 0.0, c0][None], b1, b2, radius_m, max_depth_m, noise_rad, grid, c0)[0]
    dof = max(len(f_cyl) - len(q), 1)
    return float(np.linalg.norm(q[3:6]) / d_tube), _soft_l1_cost(f_cyl, f_scale) - cost, 2.0 * cost / dof


def ring_tried(statuses, every: int) -> int:
    """How many of an exam's steps had the ring fitted (:func:`exam_scale`'s denominator): the steps fitted from their
    own matches (``ok``, ``wall``: :data:`bodyslam.steps.MEASURED`) into positions divisible by ``every``
    (:func:`ring_every`; ``statuses[k]`` is the step into position ``k + 1``). The chunks fit the ring to exactly these
    (:meth:`bodyslam.vision.odometry.VisualOdometry.run`), so the count is the same from motion.csv's statuses."""
    from bodyslam.steps import MEASURED

    if every <= 0:
        return 0
    return sum(1 for k, st in enumerate(statuses) if (k + 1) % every == 0 and st in MEASURED)


def shows_rings(samples: int, tried: int) -> bool:
    """Whether ``samples`` ratios (rings seen) among ``tried`` fitted steps say the exam shows rings: at least
    :data:`RING_MIN_SAMPLES`, and more than a lumen without rings lets through (the binomial tail at
    :data:`RING_NULL_SHARE` below :data:`RING_SHARE_ALPHA`)."""
    if samples < RING_MIN_SAMPLES:
        return False
    return binomial_tail(samples, max(int(tried), samples), RING_NULL_SHARE) < RING_SHARE_ALPHA


def binomial_tail(k: int, n: int, p: float) -> float:
    """``P(X >= k)`` for ``X ~ Binomial(n, p)`` (scipy's ``binom.sf(k - 1, n, p)``), summed term by term from the
    largest, in logs: within 2e-12 of scipy's (relative) wherever the tail is above 1e-100, for ``n`` to 2,000 (tested;
    the test against :data:`RING_SHARE_ALPHA` needs far less), and without importing ``scipy.stats``, which took
    0.26-0.58 s at the serial end of every run that measures the lumen scale."""
    if k <= 0:
        return 1.0
    if k > n:
        return 0.0
    if p <= 0.0 or p >= 1.0:
        return float(p >= 1.0)
    lp, lq = math.log(p), math.log1p(-p)
    logs = [math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * lp + (n - i) * lq
            for i in range(k, n + 1)]
    top = max(logs)
    return float(min(1.0, math.exp(top) * math.fsum(math.exp(v - top) for v in logs)))


def _finite_ratios(ratios) -> np.ndarray:
    """The ratios that were measured (not None, finite, positive), as an array."""
    return np.asarray([x for x in ratios if x is not None and math.isfinite(x) and x > 0], float)


def exam_scale(ratios, tried: int) -> tuple[float, int]:
    """``(factor, samples)``: the median of an exam's finite ring ratios where they say it shows rings
    (:func:`shows_rings`, ``tried`` the steps the ring was fitted to: :func:`ring_tried`), else 1.0 (the prior's
    scale)."""
    r = _finite_ratios(ratios)
    if not shows_rings(len(r), tried):
        return 1.0, int(len(r))
    return float(np.median(r)), int(len(r))


# The measured factor's own error beside its median's scatter (:func:`exam_scale_sd_rel`): the ring model is not the
# folded, peristaltic lumen, and the steps the ring was fitted to are a sample of the exam's. Chosen on tuning renders
# only (session 63, docs/RESULTS.md "The radius a measured lumen scale leaves"): 22 realistic runs (realistic_exam
# 587-594, `bodyslam batch` defaults; realistic 595-598, the same; realistic 540-549, `testbed evaluate`), the factor
# each run's steps still needed after it (testbed.score's distance_scale) against the stated relative 1-sigma: its
# median's scatter alone put 50% of them inside 1-sigma (mean z^2 2.5); with a floor of 0.03 / 0.05 / 0.06 / 0.07 /
# 0.10, 64 / 64 / 77 / 77 / 91% (mean z^2 1.8 / 1.2 / 1.04 / 0.88 / 0.56). 0.06 gives mean z^2 ~1.
SCALE_SD_FLOOR_REL = 0.06
# ... and what the exam's one factor cannot follow from step to step: the lumen's radius over a step's few
# millimetres about the exam's mean (contraction rings ~2 cm long, peristalsis, folds), kept in each step's 1-sigma as
# the lumen shape's share is (white: the fusion and the path do not take it out) wherever a measured factor replaces
# the prior's 1-sigma (which covered it, within its 20%). Chosen on the same 22 tuning runs (session 63): with the
# factor's 1-sigma alone 62% of the estimated steps' distance errors fell inside their stated 1-sigma (88% inside 2;
# the prior's share gave 74% / 95%); with this share 0.10 / 0.11 / 0.115 beside it, 66.6 / 67.5 / 68.0% (91.7 / 92.2 /
# 92.4%)
SCALE_LOCAL_SD_REL = 0.11


def exam_scale_sd_rel(ratios) -> float:
    """The relative 1-sigma of :func:`exam_scale`'s factor where it applies: the median's scatter, ``1.2533 s /
    sqrt(n)`` with ``s`` the robust spread (1.4826 MAD) of ``ln`` of the ``n`` finite ratios (the factor multiplies,
    and one ratio's spread is ~0.15-0.5 in ``ln`` on realistic runs), and :data:`SCALE_SD_FLOOR_REL` in quadrature.
    NaN where there are no ratios."""
    r = _finite_ratios(ratios)
    if not len(r):
        return math.nan
    lr = np.log(r)
    spread = 1.4826 * float(np.median(np.abs(lr - np.median(lr))))
    return math.hypot(1.2533 * spread / math.sqrt(len(r)), SCALE_SD_FLOOR_REL)


def scale_of_steps(steps: list[StepMotion], measured: bool) -> dict:
    """A run's lumen scale from its steps' ring ratios (``motion.csv``: ``bodyslam localize --motion``, `testbed
    evaluate`), as the motion stage found it: ``factor``, ``samples`` (rings seen), ``steps_tried`` (0 where the scale
    is not ``measured``: :func:`bodyslam.vision.odometry.lumen_scale_measured`), ``applied``, ``factor_sd_rel``
    (:func:`exam_scale_sd_rel`; None where not applied) and ``steps_chained``."""
    tried = ring_tried((s.status for s in steps), ring_every(len(steps) + 1)) if measured else 0
    ratios = [s.ring_ratio for s in steps]
    factor, samples = exam_scale(ratios, tried)
    applied = factor != 1.0
    return {"factor": factor, "samples": samples, "steps_tried": tried, "applied": applied,
            "factor_sd_rel": exam_scale_sd_rel(ratios) if applied else None,
            "steps_chained": int(sum(math.isfinite(s.chain_factor) for s in steps))}


def radius_sd_rel_after(sc: dict | None, prior_sd_rel: float) -> float:
    """The relative 1-sigma of the radius an exam's steps amount to: the measured factor's (``factor_sd_rel`` of
    :func:`lumen_scale_summary` or :func:`scale_of_steps`) where the lumen scale was applied, else the radius's own
    (``prior_sd_rel``: the prior's, meta.json's, 0 for a radius given). Both the steps' 1-sigma
    (:func:`bodyslam.vision.odometry.with_lumen_uncertainty`) and the fusion's scale state and the path's variance
    take this one number. A summary written before session 63 has no ``factor_sd_rel``: the prior's then."""
    sd = _factor_sd_rel(sc)
    return float(prior_sd_rel) if sd is None else sd


def _factor_sd_rel(sc: dict | None) -> float | None:
    """The applied factor's relative 1-sigma of a lumen-scale summary; None where none was applied or stated."""
    if sc and sc.get("applied") and sc.get("factor_sd_rel") is not None and math.isfinite(sc["factor_sd_rel"]):
        return float(sc["factor_sd_rel"])
    return None


def local_sd_rel_after(sc: dict | None) -> float:
    """The white share of each step's 1-sigma (relative to its distance) that a measured lumen scale adds beside its
    factor's (:data:`SCALE_LOCAL_SD_REL` where the scale was applied, :func:`radius_sd_rel_after`), 0 elsewhere."""
    return SCALE_LOCAL_SD_REL if _factor_sd_rel(sc) is not None else 0.0


def rescaled(s: StepMotion, factor: float) -> StepMotion:
    """A step with a full pose rescaled by ``factor`` (its translation, distance and their 1-sigma); any other
    step as it is."""
    if factor == 1.0 or not s.has_estimate:
        return s
    return replace(s, distance_m=s.distance_m * factor, t_c1_c2_m=s.t_c1_c2_m * factor,
                   sigma_distance_m=s.sigma_distance_m * factor)


def lumen_scale_summary(factor: float, samples: int, every: int, radius_m: float,
                        scale_chain: dict | None = None, tried: int | None = None,
                        factor_sd_rel: float | None = None) -> dict:
    """What ``summary.json`` and the CLIs say of it: the factor applied, the ratios behind it (``samples`` rings seen
    of ``tried`` fitted steps sampled), its relative 1-sigma (``factor_sd_rel``: :func:`exam_scale_sd_rel`, None where
    not applied), and the radius of the cylinder the rescaled steps amount to, with its 1-sigma."""
    applied = bool(factor != 1.0)
    sd = float(factor_sd_rel) if applied and factor_sd_rel is not None else None
    return {"factor": float(factor), "samples": int(samples), "steps_tried": None if tried is None else int(tried),
            "every_nth_step": int(every), "applied": applied, "min_samples": RING_MIN_SAMPLES,
            "null_share": RING_NULL_SHARE,
            "factor_sd_rel": sd,
            # each step's white share beside it (local_sd_rel_after), relative to its distance
            "local_sd_rel": SCALE_LOCAL_SD_REL if sd is not None else None,
            "effective_radius_m": float(radius_m * factor),
            "effective_radius_sd_m": None if sd is None else float(radius_m * factor * sd),
            # the steps' scales tied to their neighbours' before this factor (bodyslam.vision.scale_chain)
            "scale_chain": scale_chain}


def _ordinal(n: int) -> str:
    """2 -> "2nd", 4 -> "4th", 11 -> "11th", 23 -> "23rd"."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def lumen_scale_text(sc: dict | None) -> str:
    """What the CLIs print and the report says of a run's lumen scale (:func:`lumen_scale_summary`, None where it
    was not measured)."""
    if sc is None:
        from bodyslam.vision.odometry import LUMEN_SCALE_MIN_PRIOR_SD_REL

        return (f"not measured (the radius is known, or known to within {LUMEN_SCALE_MIN_PRIOR_SD_REL:.0%}; the "
                "lumen scale is off; or the thesis estimator): the steps keep the radius's scale")
    tried = sc.get("steps_tried")
    sampled = f" of {tried} sampled" if tried is not None else ""
    if not sc["applied"]:
        hint = ""
        if not sc["every_nth_step"]:
            why = "; too few frames to sample"
            # a clip: how it takes its exam's scale (docs/RESULTS.md, "Short clips: ... their scale", session 61)
            hint = (" (a clip cut from an exam can take the whole exam's measured radius: bodyslam batch "
                    "--radius-from the exam's batch output, or --radius-m its summary.json "
                    "lumen_scale.effective_radius_m)")
        elif sc["samples"] < sc["min_samples"]:
            why = f", {sc['min_samples']} needed"
        else:  # enough rings, but no more of them than a lumen without rings lets through
            why = f", no more than the ~{sc.get('null_share', RING_NULL_SHARE):.0%} a lumen without rings shows"
        return (f"not applied ({sc['samples']}{sampled} step(s) showed a ring{why}): the steps keep the radius "
                "prior's scale" + hint + _chain_text(sc.get("scale_chain")))
    sd = sc.get("factor_sd_rel")
    pm = f" +- {100 * sd:.0f}%" if sd is not None else ""
    radius_sd = sc.get("effective_radius_sd_m")
    rpm = f" +- {radius_sd * 100:.2f}" if radius_sd is not None else ""
    return (f"steps x{sc['factor']:.3f}{pm}, the median over the {sc['samples']}{sampled} steps that showed a ring "
            f"({'every' if sc['every_nth_step'] == 1 else 'every ' + _ordinal(sc['every_nth_step'])} step sampled) "
            "of a tube with one contraction ring against the "
            f"cylinder: a cylinder of {sc['effective_radius_m'] * 100:.2f}{rpm} cm"
            + _chain_text(sc.get("scale_chain")))


def _chain_text(ch: dict | None) -> str:
    """The clause on the steps' scales tied to their neighbours' (:func:`bodyslam.vision.scale_chain.chained`)."""
    if not ch:
        return ""
    if not ch["steps_chained"]:
        return "; no step's scale tied to its neighbours' (no links)"
    return (f"; {ch['steps_chained']} steps' scales tied to their neighbours' by {ch['links']} links (factors "
            f"{ch['factor_p10']:.2f}-{ch['factor_p90']:.2f}, 10th-90th percentile)")

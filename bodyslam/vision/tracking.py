"""Dead reckoning (dissertation Eq. 3.16-3.18) and the path travelled, from per-step motion.

The steps come from :mod:`bodyslam.vision.odometry` (or a ``motion.csv``, :func:`bodyslam.io.read_motion_steps`).

:func:`dead_reckon` accumulates per-step motion into poses ``T_w_c``. The world frame of a dead-reckoned
trajectory is the first frame's camera frame. Composition (written correctly): ``R_w_k = R_w_(k-1) R_(k-1)_k`` and
``p_w_k = p_w_(k-1) + R_w_(k-1) t_(k-1)_k``. The dissertation's Eq. 3.17, ``R = R R_t R^-1``, is a similarity
transform of the previous orientation, not an accumulation: with it the orientation never changes when the step
rotation commutes with it, so it is not used. The thesis estimator gives no translation direction, so its step
is ``d`` along the first frame's optical axis and its rotation ``R_swing(pitch, yaw) R_z(roll)`` (the convention
of :mod:`bodyslam.geometry`, which Eq. 3.18's matrix approximates for small angles). A step with no estimate
(too few matches, a dark frame) contributes no motion and is counted in the summary, never hidden; a
``rotation`` step (only its rotation measured) turns without moving.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.steps import (BESIDE_WALL_LOG_SD, HAMPERED_ENTER_PROB, HAMPERED_STAY_PROB, LOSS_SCALE_GRID,
                            LOSS_SCALE_PRIOR_LOG_SD, LOSS_SLOPE, LOST_STEP_FLOOR_R, LOST_STEP_QUANTILE,
                            MISSING_STEP_REL_SD, SPEED_JUMP_PROB, STEP_MAX_R, WITH_ROTATION, StepMotion,
                            lost_step_floor_m, lost_to_motion)

__all__ = ["dead_reckon", "path_travelled", "path_from_lengths", "missing_step_lengths", "step_length",
           "scale_path_variance", "segment_variance", "fraction_between", "share_without_estimate",
           "share_beside_wall", "path_share_text",
           "SCALE_CORR_M", "LOCAL_SCALE_SD_REL", "LOCAL_SCALE_CORR_M"]

# the distance along the gut over which the lumen radius (the visual scale) changes: the fusion's scale state and
# the path's variance share it (stated choice, as the realistic testbed's 20 cm radius wavelength)
SCALE_CORR_M = 0.2
# how far along the stretch between two landmarks (fraction_between): the exam-wide scale cancels there, and what is
# left is the lumen's local scale, which the steps read in units of the radius they assume. Its 1-sigma and the
# distance over which it changes, for a lumen that is not a cylinder: on the realistic testbed the steps err by
# ~25% of their length at every distance, following the local radius, and a window of 11-21 frames (2.6-5 cm of gut
# at the dissertation's pace) follows it best (session 40, docs/RESULTS.md "Each step's scale tied to its
# neighbours'"). Stated from those measurements, not fitted to the fractions' coverage (session 78)
LOCAL_SCALE_SD_REL = 0.25
LOCAL_SCALE_CORR_M = 0.05


def _step_transform(s: StepMotion) -> tuple[Rotation, np.ndarray]:
    if not (s.ok or s.has_estimate):  # a rotation step turns without moving (its translation is unknown)
        return (Rotation.from_matrix(s.R_c1_c2) if s.has_rotation else Rotation.identity()), np.zeros(3)
    if s.R_c1_c2 is not None and s.t_c1_c2_m is not None:
        return Rotation.from_matrix(s.R_c1_c2), np.asarray(s.t_c1_c2_m, float)
    pitch = 0.0 if np.isnan(s.pitch_rad) else s.pitch_rad
    yaw = 0.0 if np.isnan(s.yaw_rad) else s.yaw_rad
    R = Rotation.from_rotvec([pitch, yaw, 0.0]) * Rotation.from_rotvec([0.0, 0.0, s.roll_rad])
    return R, np.array([0.0, 0.0, s.distance_m])


def dead_reckon(steps: list[StepMotion]) -> tuple[np.ndarray, Rotation]:
    """Poses ``T_w_c`` of frames ``0..n`` from ``n`` steps (module docstring); world = first camera frame."""
    pos = np.zeros((len(steps) + 1, 3))
    quats = np.zeros((len(steps) + 1, 4))
    R = Rotation.identity()
    quats[0] = R.as_quat()
    for k, s in enumerate(steps, start=1):
        dR, dt = _step_transform(s)
        pos[k] = pos[k - 1] + R.apply(dt)
        R = R * dR
        quats[k] = R.as_quat()
    return pos, Rotation.from_quat(quats)


def step_length(s: StepMotion) -> tuple[float, float]:
    """``(length m, variance m^2)`` of a step with an estimate (``ok`` or ``bridged``: the translation's norm; the
    thesis estimator's ``ok`` rows: its distance), ``(nan, 0)`` otherwise."""
    if s.has_estimate:
        return float(np.linalg.norm(s.t_c1_c2_m)), s.sigma_t_m ** 2
    if s.ok and math.isfinite(s.distance_m):
        return abs(s.distance_m), s.sigma_t_m ** 2
    return math.nan, 0.0


def scale_path_variance(length_m, scale_sd_rel: float, corr_m: float = SCALE_CORR_M):
    """Variance (m^2) that a relative scale error adds to a path of length ``length_m`` when the error is a
    Gauss-Markov process along the path (1-sigma ``scale_sd_rel``, correlation distance ``corr_m``): the integral
    of its covariance, ``2 sd^2 l^2 (L/l - 1 + exp(-L/l))`` -- ``(sd L)^2`` for a path much shorter than ``l`` (one
    scale for all of it), ``2 sd^2 l L`` for a much longer one (independent stretches of ``l``)."""
    L = np.abs(np.asarray(length_m, float)) / corr_m
    return 2.0 * scale_sd_rel**2 * corr_m**2 * (L - 1.0 + np.exp(-L))


def segment_variance(path_m: np.ndarray, var_m2: np.ndarray, j: int, k: int, scale_sd_rel: float = 0.0,
                     corr_m: float = SCALE_CORR_M) -> float:
    """Variance of the path travelled between frames ``j`` and ``k`` (:func:`path_travelled`'s outputs): the
    steps' own variances between them, and the scale's over that stretch's length."""
    sv = (lambda L: float(scale_path_variance(L, scale_sd_rel, corr_m))) if scale_sd_rel > 0 else (lambda L: 0.0)
    own = abs((var_m2[k] - sv(path_m[k])) - (var_m2[j] - sv(path_m[j])))
    return own + sv(path_m[k] - path_m[j])


def fraction_between(path_m: np.ndarray, var_m2: np.ndarray, a: int, b: int, k: int,
                     scale_sd_rel: float = 0.0, corr_m: float = SCALE_CORR_M,
                     local_sd_rel: float = 0.0, local_corr_m: float = LOCAL_SCALE_CORR_M) -> tuple[float, float]:
    """``(fraction, 1-sigma)``: how far frame ``k`` lies along the path from frame ``a`` to frame ``b`` (two
    landmarks: the pylorus and the ileocaecal valve, say), ``(path[k] - path[a]) / (path[b] - path[a])``; 0 at
    ``a``, 1 at ``b``, outside [0, 1] for a frame outside them. A scale error common to the whole stretch (the lumen
    radius assumed) cancels; its share in the 1-sigma is what the Gauss-Markov scale model
    (:func:`scale_path_variance`) leaves uncorrelated between the two parts. ``local_sd_rel`` (0: none;
    :data:`LOCAL_SCALE_SD_REL` for a lumen that is not a cylinder) adds the lumen's local scale as a second such
    process over ``local_corr_m``, on top of the steps' own variances (which hold an independent share of it, so
    this errs on the wide side). Delta method on ``A / C``, ``A`` the path from ``a`` to ``k`` and ``C`` from ``a``
    to ``b``, their covariance by polarisation from :func:`segment_variance`. ``(nan, nan)`` when the path from
    ``a`` to ``b`` is zero."""
    C = float(path_m[b] - path_m[a])
    if not C > 0:
        return math.nan, math.nan
    A = float(path_m[k] - path_m[a])

    def local(L: float) -> float:
        return float(scale_path_variance(L, local_sd_rel, local_corr_m)) if local_sd_rel > 0 else 0.0

    va = segment_variance(path_m, var_m2, a, k, scale_sd_rel, corr_m) + local(A)
    vc = segment_variance(path_m, var_m2, a, b, scale_sd_rel, corr_m) + local(C)
    vd = segment_variance(path_m, var_m2, k, b, scale_sd_rel, corr_m) + local(C - A)
    cov = 0.5 * (va + vc - vd)
    var = va / C**2 + A**2 * vc / C**4 - 2.0 * A * cov / C**3
    return A / C, math.sqrt(max(var, 0.0))


# the speed model's grid: step lengths from 1/1000 of the lumen radius to STEP_MAX_R radii, log-spaced
_GRID_BINS = 100
_GRID_LO_R = 1e-3
# a measured length tells the speed to this relative 1-sigma at least (one step's error must not pin the speed)
_MEASURED_REL_SD = 0.1
# estimated steps taken into account on each side of a run of missing steps (the speed model forgets faster:
# SPEED_JUMP_PROB per step)
_CONTEXT_STEPS = 25
# the spread of ln(step) from one step to the next where too few pairs of consecutive estimated steps say it
_DEFAULT_LOG_STEP_SD = 0.5
# emission rows are made in blocks of this many steps on each pass: float64 temporaries of a few MB
_BLOCK_STEPS = 4096


def missing_step_lengths(length_m: np.ndarray, var_m2: np.ndarray, lost: np.ndarray, radius_m: float,
                         beside_wall: np.ndarray | None = None, rotated: np.ndarray | None = None,
                         info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The length (m) and its 1-sigma of every step without an estimate (NaN in ``length_m``) and of every step
    fitted beside its own tube's wall (``beside_wall``; None: none), from the speed around it: ``(mean_m (n,),
    sd_m (n,))``, NaN at the other estimated steps. ``rotated``: the steps without an estimate that carry a rotation
    (guided matching saw the wall in both frames; None: none do).

    The capsule's step length is a hidden state on a log-spaced grid (``_GRID_LO_R`` to :data:`STEP_MAX_R` lumen
    radii ``radius_m``: the radius the steps were fitted with, the prior's where the radius is one, *not* rescaled by
    the lumen scale (:mod:`bodyslam.vision.lumen_scale`): the loss curve below was fitted in its units, and on
    realistic tuning seeds 567-574 the matcher's losses follow d / prior radius better than d / the rescaled radius
    (docs/RESULTS.md, session 39)) that changes little from step to step (a Gaussian in ln
    length whose spread is the exam's own: consecutive estimated steps, robust) and with chance
    :data:`SPEED_JUMP_PROB` jumps to any value. An estimated step observes it (its length, with its 1-sigma and at
    least ``_MEASURED_REL_SD`` of it); a step lost to motion (:func:`~bodyslam.steps.lost_to_motion`) observes that
    matching lost it, which a step of length d is with the chance ``1 / (1 + (d / d50)^-s)``, ``d50`` =
    :data:`~bodyslam.steps.LOST_STEP_FLOOR_R` radii, ``s`` = :data:`~bodyslam.steps.LOSS_SLOPE` (the matcher's
    measured loss curve); any other missing step (a dark, blurred, turbid frame: perhaps at rest) observes nothing.
    Forward-backward on each run of missing steps with ``_CONTEXT_STEPS`` estimated steps on either side gives each
    missing step's posterior mean and 1-sigma, the latter at least :data:`~bodyslam.steps.MISSING_STEP_REL_SD` of
    the mean (the model's own spread was too narrow: it held 47% of the lost steps' true lengths). So a lone lost
    step among slow ones is a little beyond the matcher's reach, and a long run of them a sustained fast phase,
    near the prior's upper end: the rule before (the 90th percentile of the estimated steps) was 35% long on lone
    lost steps and 40% short on runs of nine or more (realistic tuning seeds 503-522; docs/RESULTS.md, "The steps
    matching loses, from the speed around them").
    Since session 49 two more things (docs/RESULTS.md, "Beside the wall and hampered by the world"):

    - the world may hamper matching for a while, a second hidden state
      (:data:`~bodyslam.steps.HAMPERED_ENTER_PROB`, :data:`~bodyslam.steps.HAMPERED_STAY_PROB`) in which a step is
      lost or fitted beside the wall whatever its length: a run of such steps there observes nothing of the speed.
      A step with an ordinary fit or a rotation is never in it;
    - a step fitted beside the wall observes its length only weakly, a Gaussian in ln(length) about the fit's with
      :data:`~bodyslam.steps.BESIDE_WALL_LOG_SD`, and those steps' lengths do not set the speed's spread.

    Since session 50 the loss curve's half-loss length is the exam's own (docs/RESULTS.md, "The loss curve's scale
    is each exam's own"): ``d50`` times each of :data:`~bodyslam.steps.LOSS_SCALE_GRID`, the one under which the
    windows' observations are likeliest (forward passes) times a prior of
    :data:`~bodyslam.steps.LOSS_SCALE_PRIOR_LOG_SD` in ln(scale); an ordinary fit observes that matching did not
    lose it (``1 - p_lost``), without which the shortest curve would always be likeliest. ``info`` (a dict)
    receives the scale chosen as ``loss_scale``.

    The model is symmetric in time: an exam played backwards gets the same lengths."""
    length = np.asarray(length_m, float)
    var = np.asarray(var_m2, float)
    lost = np.asarray(lost, bool)
    n = len(length)
    mean, sd = np.full(n, np.nan), np.full(n, np.nan)
    est = np.isfinite(length)
    wall = np.zeros(n, bool) if beside_wall is None else np.asarray(beside_wall, bool) & est
    model = ~est | wall  # the steps whose length this gives
    if not model.any():
        return mean, sd
    # the steps the world may have hampered: nothing measured, not even a rotation, or fitted beside the wall
    hampered = (~est if rotated is None else ~est & ~np.asarray(rotated, bool)) | wall
    u = np.linspace(math.log(_GRID_LO_R), math.log(STEP_MAX_R), _GRID_BINS)  # ln(length / radius)
    d_grid = radius_m * np.exp(u)
    floor_u = math.log(_GRID_LO_R)
    le = np.where(est & ~wall, np.log(np.maximum(np.abs(length), radius_m * _GRID_LO_R) / radius_m), np.nan)
    dl = np.diff(le)
    dl = dl[np.isfinite(dl) & (le[1:] > floor_u) & (le[:-1] > floor_u)]  # a capsule at rest says nothing of it
    q = 1.4826 * float(np.median(np.abs(dl))) if len(dl) >= 5 else _DEFAULT_LOG_STEP_SD
    q = max(q, 2.0 * (u[1] - u[0]))
    T = np.exp(-0.5 * ((u[:, None] - u[None, :]) / q) ** 2)
    T = (1.0 - SPEED_JUMP_PROB) * T / T.sum(axis=1, keepdims=True) + SPEED_JUMP_PROB / _GRID_BINS
    T = T.astype(np.float32)
    a_in, a_stay = np.float32(HAMPERED_ENTER_PROB), np.float32(HAMPERED_STAY_PROB)
    pi_h = a_in / (a_in + 1 - a_stay)  # the hampered state's stationary share: an exam read backwards is read alike
    # windows: each run of modelled steps with its context, overlapping windows merged
    windows: list[list[int]] = []
    miss = np.flatnonzero(model)
    ctx = np.flatnonzero(~model)
    if len(ctx):  # from the _CONTEXT_STEPS-th estimated step before each modelled one to the one as far after it
        pos = np.searchsorted(ctx, miss)
        lo = np.minimum(ctx[np.maximum(pos - _CONTEXT_STEPS, 0)], miss)
        hi = np.maximum(ctx[np.minimum(pos + _CONTEXT_STEPS - 1, len(ctx) - 1)] + 1, miss + 1)
    else:
        lo, hi = np.zeros_like(miss), np.full_like(miss, n)
    for a, b in zip(lo.tolist(), hi.tolist()):
        if windows and a <= windows[-1][1]:
            windows[-1][1] = max(windows[-1][1], b)
        else:
            windows.append([a, b])
    blk = _BLOCK_STEPS
    p_lost = not_lost = None

    def emissions(a: int, b: int) -> np.ndarray:
        """The unhampered state's likelihood of steps a..b-1's observations over the grid, (b - a, bins) float32."""
        E = np.ones((b - a, _GRID_BINS), np.float32)
        e, w = est[a:b], wall[a:b]
        for kind in (e & ~w, w):
            r = np.flatnonzero(kind)
            if not len(r):
                continue
            d = np.maximum(np.abs(length[a + r]), radius_m * _GRID_LO_R)[:, None]
            if kind is w:  # beside the wall: a weak reading, in ln(length)
                ll = -0.5 * (np.log(d_grid / d) / BESIDE_WALL_LOG_SD) ** 2
            else:
                s2 = (var[a + r][:, None] + (_MEASURED_REL_SD * np.maximum(d, d_grid)) ** 2
                      + (radius_m * _GRID_LO_R) ** 2)
                ll = -0.5 * (d - d_grid) ** 2 / s2 - 0.5 * np.log(s2)
            E[r] = np.exp(ll - ll.max(axis=1, keepdims=True))
            if kind is not w:  # an ordinary fit: matching did not lose it
                E[r] *= not_lost
        E[~e & lost[a:b]] = p_lost
        return E

    def loss_curve(scale: float) -> None:
        nonlocal p_lost, not_lost
        p_lost = (1.0 / (1.0 + np.exp(-LOSS_SLOPE * (u - math.log(scale * LOST_STEP_FLOOR_R))))).astype(np.float32)
        not_lost = np.float32(1.0) - p_lost

    # the loss curve's scale: the exam's likeliest under its prior (LOSS_SCALE_GRID), from forward passes alone
    score = []
    for scale in LOSS_SCALE_GRID:
        loss_curve(scale)
        score.append(_forward(windows, emissions, hampered, T, pi_h, a_in, a_stay, keep=False)[2]
                     - 0.5 * (math.log(scale) / LOSS_SCALE_PRIOR_LOG_SD) ** 2)
    chosen = LOSS_SCALE_GRID[int(np.argmax(score))]
    loss_curve(chosen)
    if info is not None:
        info["loss_scale"] = chosen

    zero = np.zeros(_GRID_BINS, np.float32)
    for a, b in windows:
        m = b - a
        H = hampered[a:b]  # the hampered state's likelihood of each step's observation: 1 or 0
        slot = np.cumsum(H) - 1  # its forward pass is kept only where it can be non-zero
        fwd, fwd1, _ = _forward([(a, b)], emissions, hampered, T, pi_h, a_in, a_stay, keep=True)
        # backward, the posterior (the speed's marginal over both states) written over the forward pass
        g0, g1 = np.ones(_GRID_BINS, np.float32), np.ones(_GRID_BINS, np.float32)
        if H[m - 1]:
            fwd[m - 1] += fwd1[slot[m - 1]]
        for c in range(((m - 1) // blk) * blk, -1, -blk):
            E = emissions(a + c, a + min(c + blk, m))
            for j in range(min(c + blk, m) - 1, max(c, 1) - 1, -1):  # the message from step j to step j - 1
                h0 = T @ (E[j - c] * g0)
                h1 = T @ g1 if H[j] else zero
                g0, g1 = (1 - a_in) * h0 + a_in * h1, (1 - a_stay) * h0 + a_stay * h1
                z = g0.sum() + g1.sum()
                g0, g1 = g0 / z, g1 / z
                fwd[j - 1] *= g0
                if H[j - 1]:
                    fwd[j - 1] += fwd1[slot[j - 1]] * g1
        del fwd1
        post = fwd
        w = np.flatnonzero(model[a:b])
        for c in range(0, len(w), 4096):
            r = w[c:c + 4096]
            p = post[r].astype(float)
            p /= p.sum(axis=1, keepdims=True)
            mu, m2 = p @ d_grid, p @ d_grid**2
            mean[a + r] = mu
            sd[a + r] = np.maximum(np.sqrt(np.maximum(m2 - mu * mu, 0.0)), MISSING_STEP_REL_SD * mu)
    return mean, sd


def _forward(windows, emissions, hampered, T, pi_h, a_in, a_stay, keep: bool):
    """The forward pass of :func:`missing_step_lengths`' two chains over ``windows``: ``p0`` the speed with
    matching unhampered, ``p1`` hampered, each step normalised over both. Returns ``(fwd, fwd1, loglik)``: with
    ``keep`` (one window) the unhampered state's filtered distribution at every step ``(m, bins)`` and the hampered
    one's where it can be non-zero; and the log-likelihood of the windows' observations (the sum of the
    normalisers: emissions are scaled per step, by amounts that do not depend on the loss curve)."""
    blk = _BLOCK_STEPS
    zero = np.zeros(_GRID_BINS, np.float32)
    loglik = 0.0
    fwd = fwd1 = None
    for a, b in windows:
        m = b - a
        H = hampered[a:b]
        slot = np.cumsum(H) - 1
        if keep:
            fwd = np.empty((m, _GRID_BINS), np.float32)  # float32: a whole exam can be one window
            fwd1 = np.empty((int(H.sum()), _GRID_BINS), np.float32)
        p0 = np.full(_GRID_BINS, (1 - pi_h) / _GRID_BINS, np.float32)
        p1 = np.full(_GRID_BINS, pi_h / _GRID_BINS, np.float32)
        for c in range(0, m, blk):
            E = emissions(a + c, a + min(c + blk, m))
            zs = np.empty(min(c + blk, m) - c)
            for k in range(c, min(c + blk, m)):
                f0 = (((1 - a_in) * p0 + (1 - a_stay) * p1) @ T) * E[k - c]
                f1 = ((a_in * p0 + a_stay * p1) @ T) if H[k] else zero
                z = f0.sum() + f1.sum()
                zs[k - c] = z
                p0, p1 = f0 / z, f1 / z
                if keep:
                    fwd[k] = p0
                    if H[k]:
                        fwd1[slot[k]] = p1
            loglik += float(np.sum(np.log(np.maximum(zs, 1e-300))))
    return fwd, fwd1, loglik


def path_travelled(steps: list[StepMotion], scale_sd_rel: float = 0.0,
                   radius_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Path travelled from the first frame to each frame, and its variance: ``(path_m (n+1,), var_m2 (n+1,))``.

    The length of an estimated step is :func:`step_length`, with its own 1-sigma. A step without an estimate is a
    capsule that may still have moved. With the radius the steps assumed (``radius_m``) and which steps were lost
    to motion, its length and 1-sigma come from the speed around it (:func:`missing_step_lengths`), and so do those
    of a step fitted beside the wall (its fit observes its length weakly); the steps of one run of such steps share
    one speed, so their 1-sigmas add (not their variances). With nothing estimated
    and nothing lost to motion, as below. The rest of this docstring is the rule without ``radius_m`` (and, with
    it, the rule before session 30): each step of a run without an estimate takes the mean length of the
    estimated steps that border the run (both sides inside the exam, the one side at its start or end). A step
    lost to motion
    (:func:`~bodyslam.steps.lost_to_motion`) takes at least the :data:`~bodyslam.steps.LOST_STEP_QUANTILE`
    percentile of the exam's estimated lengths instead: matching fails on the steps longer than it measures, so
    the neighbours' mean is biased low (realistic tuning seeds 503-509: the path's end -11% on average, 27% at
    worst; with the percentile -3% and 19%). Every missing step's 1-sigma is its length, and at least that
    percentile (a step lost for another reason may have been as fast). That percentile is taken at least
    :data:`~bodyslam.steps.LOST_STEP_FLOOR_R` lumen radii (``radius_m``, the radius the steps assumed; None: no
    floor), the length at which matching loses about half of the steps: an exam whose estimated steps are few and
    short (a rest after a fast phase) would otherwise fill its lost steps with nearly nothing, and state that
    nothing as sure. The rule is the same forwards and backwards, so an exam's path does not depend on its frame
    order beyond the steps' own errors (tested on a clip played backwards); with no estimated step at all the path
    is the lost steps at the floor, each step with the floor as 1-sigma (zero with zero variance without a floor:
    nothing is known).
    """
    lv = np.array([step_length(s) for s in steps], float).reshape(-1, 2)
    return path_from_lengths(lv[:, 0], lv[:, 1], scale_sd_rel, lost=np.array([lost_to_motion(s) for s in steps]),
                             radius_m=radius_m, beside_wall=np.array([s.beside_wall for s in steps], bool),
                             rotated=np.array([s.status in WITH_ROTATION for s in steps], bool))


def share_without_estimate(path_m: np.ndarray, length_m: np.ndarray) -> float:
    """The share of the path travelled to the end (``path_m``: :func:`path_from_lengths`'s, ``n + 1`` values) that
    lies in the steps without an estimate (NaN in ``length_m``, ``n`` values): lengths the missing-step model gave,
    not the frames. 0 for a path of length 0. Where it is large the path is mostly the model's (session 47: a
    realistic exam in turbid fluid had 82 steps lost to matching filled as a fast phase, its path four times the
    truth); the reports say so beside the path."""
    return _path_share(path_m, ~np.isfinite(np.asarray(length_m, float)))


def share_beside_wall(path_m: np.ndarray, length_m: np.ndarray, beside_wall: np.ndarray) -> float:
    """The share of the path travelled to the end that lies in the estimated steps fitted beside the wall
    (``beside_wall``): since session 49 their lengths are the speed model's, the fit only a weak reading of them
    (:func:`missing_step_lengths`), so the reports give it beside :func:`share_without_estimate`'s."""
    return _path_share(path_m, np.isfinite(np.asarray(length_m, float)) & np.asarray(beside_wall, bool))


def _path_share(path_m: np.ndarray, steps: np.ndarray) -> float:
    path = np.asarray(path_m, float)
    total = float(path[-1]) if len(path) else 0.0
    if not total > 0:
        return 0.0
    return float(np.sum(np.diff(path)[steps]) / total)


def path_share_text(share: float, beside_wall_share: float = 0.0) -> str:
    """The path's share in steps without an estimate (and in fits beside the wall), as the report and the CLI say
    it beside the path travelled: ``"85% of it in steps without an estimate: the missing-step model's lengths, not
    the frames'"``, ``"... and 20% in fits beside the wall: the speed model's lengths more than the frames'"`` (such
    a fit is a weak reading of its length), or ``""`` where neither holds any of it."""

    def pct(x: float) -> str:
        return f"{100 * x:.0f}%" if x >= 0.005 else "<1%"

    if not beside_wall_share > 0:
        return (f"{pct(share)} of it in steps without an estimate: the missing-step model's lengths, not the frames'"
                if share > 0 else "")
    return (f"{pct(share)} of it in steps without an estimate and {pct(beside_wall_share)} in fits beside the wall: "
            "the speed model's lengths more than the frames'")


def path_from_lengths(length_m: np.ndarray, var_m2: np.ndarray, scale_sd_rel: float = 0.0,
                      corr_m: float = SCALE_CORR_M, lost: np.ndarray | None = None,
                      radius_m: float | None = None, beside_wall: np.ndarray | None = None,
                      rotated: np.ndarray | None = None, info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`path_travelled` from per-step lengths (NaN: no estimate) and variances (streamed callers keep
    only these two numbers per step, and ``lost``: which steps were lost to motion,
    :func:`~bodyslam.steps.lost_to_motion`; None: every missing step takes its neighbours' mean at a 1-sigma as
    large, the rule before session 22; ``radius_m``: the radius the steps assumed, for the missing steps' model,
    :func:`missing_step_lengths`; None: the rule before session 30 without its floor,
    :func:`~bodyslam.steps.lost_step_floor_m`; with them, ``beside_wall`` and ``rotated``, which
    :func:`missing_step_lengths` takes: the steps fitted beside the wall, whose lengths it gives too, and the
    steps with a rotation but no estimate; None: none; ``info``: receives the loss curve's scale the model chose,
    ``loss_scale``, where it ran).
    ``scale_sd_rel``: the relative 1-sigma of the lumen radius the steps
    assumed (:func:`bodyslam.vision.odometry.with_lumen_uncertainty` put its share into each step's variance):
    that share is taken out of the steps and added back as one error correlated along the path
    (:func:`scale_path_variance`), which neighbouring steps share instead of averaging it out."""
    length = np.array(length_m, float)
    var = np.array(var_m2, float)
    if scale_sd_rel > 0:
        ok = np.isfinite(length)
        var[ok] = np.maximum(var[ok] - (scale_sd_rel * length[ok]) ** 2, 0.0)
    n = len(length)
    est = np.isfinite(length)
    if lost is not None and radius_m is not None and radius_m > 0 and (est.any() or np.any(lost)):
        fill, fill_sd = missing_step_lengths(length, var, lost, radius_m, beside_wall, rotated, info)
        given = est & ~np.isfinite(fill)  # the steps whose own length counts (not the model's)
        path = np.r_[0.0, np.cumsum(np.where(given, length, fill))]
        cum = np.zeros(n + 1)
        base = run_sd = 0.0
        for k in range(n):  # a run of modelled steps: one speed, so their 1-sigmas add
            if given[k]:
                base += var[k] + run_sd**2
                run_sd = 0.0
                cum[k + 1] = base
            else:
                run_sd += fill_sd[k]
                cum[k + 1] = base + run_sd**2
        if scale_sd_rel > 0:
            cum = cum + scale_path_variance(path, scale_sd_rel, corr_m)
        return path, cum
    floor = lost_step_floor_m(radius_m) if lost is not None else 0.0
    if not est.any():  # nothing measured: a lost step still moved at least the floor, the others are unknown
        if floor > 0:
            length, var = np.where(lost, floor, 0.0), np.full(n, floor**2)
            return np.r_[0.0, np.cumsum(length)], np.r_[0.0, np.cumsum(var)]
        return np.zeros(n + 1), np.zeros(n + 1)
    q_hi = max(float(np.percentile(length[est], LOST_STEP_QUANTILE)), floor) if lost is not None else 0.0
    i = 0
    while i < n:
        if est[i]:
            i += 1
            continue
        j = i
        while j < n and not est[j]:
            j += 1
        fill = float(np.mean([length[k] for k in (i - 1, j) if 0 <= k < n and est[k]]))
        if lost is None:
            length[i:j], var[i:j] = fill, fill**2
        else:  # the reason a step has no estimate says how long it likely was
            length[i:j] = np.where(lost[i:j], max(fill, q_hi), fill)
            var[i:j] = np.maximum(length[i:j], q_hi) ** 2
        i = j
    path, cum = np.r_[0.0, np.cumsum(length)], np.r_[0.0, np.cumsum(var)]
    if scale_sd_rel > 0:
        cum = cum + scale_path_variance(path, scale_sd_rel, corr_m)
    return path, cum

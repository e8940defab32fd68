"""How far the RF readings' errors are from independent, measured on the exam itself, and the covariance that
follows (issue 15: an honest 1-sigma).

The filter (:mod:`bodyslam.fusion.ekf`) counts every RSS reading as independent, as the calibration (Eq. 2.1, one
log-normal shadowing per reading) says. Real channels are not: shadowing is correlated along the path (Gudmundson's
exponential model) and each sensor departs from the calibration for the whole exam. Averaging ``N`` readings
whose errors are correlated leaves ``kappa`` times the variance the independent count promises, with
``kappa = 1 + 2 sum_l rho_l`` the variance inflation factor of a stationary series (the effective sample size
is ``N / kappa``; e.g. Geyer, "Practical Markov chain Monte Carlo", Statistical Science 7, 1992, whose
initial-sequence rule the truncation below follows).

:func:`residual_correlation` measures ``rho_l`` on the exam's own normalised residuals
``z = (RSS - mean(p_hat)) / sigma`` (pooled over sensors, lags ``1 .. max_lag`` frames) and sums it up to the first
lag that is not significant (``rho_l < 2 / sqrt(pairs)``, or fewer than ``MIN_PAIRS`` pairs). :func:`causal_inflation` does the same with the
readings of frames ``0 .. k`` only, for the online filter's frame ``k``. :func:`inflate` scales a run's covariance
by it. The positions are not changed: the inflation is what the stated 1-sigma must admit, not a re-weighting
(measured on tuning seeds: re-running the filter with the readings down-weighted by ``kappa`` made it *less*
accurate on the realistic testbed's tuning seeds 500-502, 6.6 -> 9.6 cm online, because its vision heading is the weaker half there).

The online filter does not average the whole exam: each frame it keeps a fraction ``a_k`` of its position
information and adds the new readings' (:func:`filter_memory`: ``a_k = tr(J_prior) / tr(J_post)`` of the position
block, read off the run's own covariances). For an exponentially weighted mean with weights ``a^i`` the variance
inflation is ``1 + 2 sum_l rho_l a^l`` (the double sum ``sum_ij a^i a^j rho_|i-j|`` over ``sum_i a^2i``), so
:func:`causal_inflation` tapers each lag by ``a_k^l`` when given the memory. Measured on realistic tuning seeds
503-509 (session 12's motion): online NEES 1.76 -> 3.16 and frames inside their 68% ellipsoid 0.88 -> 0.72 (the
strictly causal filter 1.54 -> 2.98, 0.89 -> 0.72), with no parameter chosen. The smoother's estimate is, in
steady state, a two-sided exponential average of the readings (weights ``a^|i|``, ``a`` the forward filter's
memory), so :func:`smoother_inflation` weights lag ``l`` by :func:`two_sided_lag_weights` (session 22; tried in
session 16, when it under-covered, 57% inside the 68% ellipsoid on tuning seeds 503-509, because the process
noise understated the steps lost to motion; with them stated, 70% against 83% untapered, docs/RESULTS.md).

What the estimate takes up (``fitted_dof``, session 64). The residuals are read at the estimated positions, and a
position moves to fit part of each slow error: of a persistent offset on ``m`` sensors, a fit with ``p`` position
parameters leaves ``m - p`` of its ``m`` dimensions in the residuals (the projection onto the orthogonal
complement of the readings' position Jacobian, as a least-squares fit's residual sum of squares has ``n - p`` degrees
of freedom). The slow errors' autocovariances measured there are therefore low by ``(m - p) / m``, and the position's
error is the part they do not show. ``fitted_dof = 3`` (:data:`POSITION_DOF`, the position's three coordinates)
scales the summed correlations by ``m / (m - 3)``, ``m`` the sensors that gave a reading so far: 32 / 29 = 1.10 on
the testbed's 32 sensors, 1.6 on an 8-antenna belt. Measured on tuning runs (the per-sensor mean residual's energy at
the true positions over that at the estimated ones, readings beyond 4 sigma left out): 1.11 on ``realistic`` 540-549
and 1.13 on ``realistic_exam`` 587-594, i.e. 3.2 and 3.6 dimensions taken up of 32. Where the slow errors are most of
the residuals' mean square (a strongly correlated channel), that mean square, rho's normaliser, shrinks with them,
and rho itself is low by less (1.03-1.06 on those runs); but kappa also leaves out the mean square itself, 1.10-1.12
of the calibration's sigma^2 there, which the variance of a mean carries. The factor was kept for the stated
1-sigma it gives, chosen by the tuning runs' mean z^2 (3.28 -> 2.98 over 22 runs; docs/RESULTS.md, "What the fit
takes up"). The start's search windows (:mod:`bodyslam.fusion.body_slam`) read the correlations as measured.

What it does not see: the vision's heading error. On the ideal ``thesis`` channel ``kappa`` is 1.0 (no lag is
significant, so nothing is scaled).

Units: dB for readings, frames for lags.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from bodyslam.fusion.body_slam import FusionResult
from bodyslam.fusion.rf import PathLossModel

__all__ = ["ResidualCorrelation", "normalised_residuals", "residual_correlation", "causal_inflation", "filter_memory",
           "smoother_inflation", "two_sided_lag_weights", "inflate", "MAX_LAG_FRAMES", "STATED_MAX_LAG_FRAMES",
           "POSITION_DOF"]

# lags looked at by default: 30 frames (15 s at the PillCam SB's 2 fps). A sensor's constant departure from the
# calibration correlates at every lag; the cap is where this estimate stops counting it (a stated choice). The start
# search's windows use it (bodyslam.fusion.body_slam: their positions depend on it).
MAX_LAG_FRAMES = 30
# lags behind the covariances localize states (bodyslam.fusion.localize; the estimates do not depend on it): 120
# frames (60 s at 2 fps). Shadowing correlated along the path stays correlated for as many frames as the capsule
# takes to cross its correlation distance: at a real exam's pace (~0.06 cm a frame, the `exam` scenario's) the
# realistic testbed's 3 cm take 50 frames, and 30 lags left the smoothed run inside its 68% ellipsoid on 32% of
# the frames. The filter's memory tapers the lags (causal_inflation, smoother_inflation), so on fast exams the
# longer cap adds almost nothing. Chosen on slow realistic tuning seeds 591-594 among 30, 60, 120 and 240
# (smoothed 32 / 43 / 49 / 49% inside; online 50 / 56 / 57 / 57%); fast realistic tuning seeds 560-567: 79 -> 81%
# smoothed, online 75% either way (docs/RESULTS.md, "Slow motion, as most of a real exam moves")
STATED_MAX_LAG_FRAMES = 120
# a lag counts once it has this many reading pairs (a few frames of a sensor array): with 16 pairs white noise
# passes the significance test 2.5% of the time at a correlation of 0.5 and more (measured: kappa 2.1 at frame 1)
MIN_PAIRS = 100
# the estimate's parameters per frame that fit the readings' slow errors (module docstring): its position's three
POSITION_DOF = 3
# frames per block of :func:`normalised_residuals` (~1 MB per intermediate at 32 sensors)
RESIDUAL_BLOCK_FRAMES = 4096


def _frame_blocks(n: int):
    """Slices of :data:`RESIDUAL_BLOCK_FRAMES` frames over ``n``: the stages below work on each frame's own numbers,
    a block at a time, so their temporaries stay a few MB whatever the exam's length (issue 17)."""
    return (slice(a, a + RESIDUAL_BLOCK_FRAMES) for a in range(0, n, RESIDUAL_BLOCK_FRAMES))


@dataclass(frozen=True)
class ResidualCorrelation:
    """Pooled autocorrelation ``rho (L,)`` of the normalised RSS residuals at lags ``1 .. L`` frames (as measured),
    the pairs behind each, the lags summed (``n_lags``), the factor the summed correlations were scaled by for what
    the estimate took up (``fitted_gain``, ``m / (m - p)``; 1 where none, module docstring) and the variance
    inflation factor ``kappa = max(1, 1 + 2 fitted_gain sum rho) >= 1``."""

    rho: np.ndarray
    n_pairs: np.ndarray
    n_lags: int
    kappa: float
    fitted_gain: float = 1.0

    def as_dict(self) -> dict:
        return {"kappa": round(self.kappa, 3), "lags_summed": self.n_lags,
                "rho_lag1": None if not len(self.rho) else round(float(self.rho[0]), 3),
                "fitted_gain": round(self.fitted_gain, 3)}


def normalised_residuals(rss_dbm: np.ndarray, positions_w_m: np.ndarray, sensors_w_m: np.ndarray,
                         normals_w: np.ndarray, pl: PathLossModel) -> np.ndarray:
    """``(RSS - mean(p)) / sigma`` per frame and sensor ``(n, m)`` at the estimated positions (NaN: no reading).
    In blocks of frames (:func:`_frame_blocks`): at once its intermediates took ~3 kB a frame (161 MiB at 55,000
    frames, the fusion's peak; docs/RESULTS.md)."""
    rss_dbm = np.asarray(rss_dbm, float)
    positions_w_m = np.asarray(positions_w_m, float)
    out = np.empty(rss_dbm.shape)
    for rows in _frame_blocks(len(out)):
        diff = sensors_w_m[None] - positions_w_m[rows, None, :]
        d = np.linalg.norm(diff, axis=2)
        depth = np.maximum(np.einsum("kji,ji->kj", diff, normals_w), 0.0)
        out[rows] = (rss_dbm[rows] - pl.mean_rss_dbm(d, depth)) / pl.params(depth)[2]
    return out


def _lag_sums(z: np.ndarray, max_lag: int, rows: slice = slice(None)):
    """Per frame ``k`` of ``rows`` (a slice of frames): the sum of ``z_k,j z_(k-l),j`` over sensors and its count, for
    each lag ``(f, L)`` (the lags reach back before the slice), and the frame's sum of squares and count ``(f,)``.
    NaN readings count as missing. Each frame's sums are its own: the same numbers whatever the slice. Each frame's
    lags at once, as one product of its readings with the window of the ``max_lag`` frames before it (3x faster
    than a pass per lag at 120 lags), :data:`_LAG_SUB_FRAMES` frames at a time (the windows' copies stay a few MB)."""
    a, b, _ = rows.indices(len(z))
    m = z.shape[1]
    prod, cnt = np.zeros((b - a, max_lag)), np.zeros((b - a, max_lag))
    sq, n_sq = np.zeros(b - a), np.zeros(b - a, int)
    for c in range(a, b, _LAG_SUB_FRAMES):
        d = min(c + _LAG_SUB_FRAMES, b)
        lo = max(c - max_lag, 0)  # the frames this part's lags reach back to
        ok = np.isfinite(z[lo:d])
        pad = max_lag - (c - lo)  # frames before the exam's first: no pair
        zw = np.concatenate([np.zeros((pad, m)), np.where(ok, z[lo:d], 0.0)])
        ow = np.concatenate([np.zeros((pad, m)), ok.astype(float)])
        # window of frame k: frames k - max_lag .. k - 1, lag 1 first
        wz = sliding_window_view(zw[:-1], max_lag, axis=0)[:, :, ::-1]
        wo = sliding_window_view(ow[:-1], max_lag, axis=0)[:, :, ::-1]
        cz, co = zw[max_lag:], ow[max_lag:]
        prod[c - a:d - a] = np.matmul(cz[:, None, :], wz)[:, 0, :]
        cnt[c - a:d - a] = np.matmul(co[:, None, :], wo)[:, 0, :]
        sq[c - a:d - a] = np.sum(cz * cz, axis=1)
        n_sq[c - a:d - a] = ok[c - lo:].sum(axis=1)
    return prod, cnt, sq, n_sq


# frames per part of :func:`_lag_sums` (its windows' copies: 512 x sensors x lags x 8 bytes, 8 MB at 16 sensors and
# 120 lags)
_LAG_SUB_FRAMES = 512


def _running(total: np.ndarray | None, x: np.ndarray) -> np.ndarray:
    """The cumulative sums of ``x`` along its first axis continued from ``total`` (the sums of the blocks before;
    None: the first block): the numbers of one cumulative sum over all the blocks at once (each is the one before
    plus this frame's)."""
    return np.cumsum(x, 0) if total is None else np.cumsum(np.concatenate([total[None], x]), 0)[1:]


def _fitted_gain(n_sensors, fitted_dof: int):
    """``m / (m - p)`` for ``m`` sensors (a number or per frame) and ``p`` = ``fitted_dof`` parameters fitted
    (module docstring); 1 for ``p = 0``. At most ``m`` (one sensor's worth of residual left) where ``m <= p + 1``."""
    m = np.asarray(n_sensors, float)
    if fitted_dof <= 0:
        return np.ones_like(m)
    return m / np.maximum(m - fitted_dof, 1.0)


def _kappa(prod: np.ndarray, cnt: np.ndarray, sq: np.ndarray, n_sq: np.ndarray, gain=1.0):
    """``(rho, n_lags, kappa)`` along the last axis (works per frame on cumulative sums); ``gain`` (a number, or
    per frame) scales the summed correlations (:func:`_fitted_gain`), not ``rho``."""
    var = sq / np.maximum(n_sq, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = (prod / np.maximum(cnt, 1)) / var[..., None]
    rho = np.where((cnt > 0) & (var[..., None] > 0), rho, 0.0)
    insignificant = (rho < 2.0 / np.sqrt(np.maximum(cnt, 1))) | (cnt < MIN_PAIRS)
    # initial sequence: lags before the first insignificant one
    first = np.where(insignificant.any(axis=-1), insignificant.argmax(axis=-1), rho.shape[-1])
    keep = np.arange(rho.shape[-1]) < first[..., None]
    kappa = np.maximum(1.0, 1.0 + 2.0 * np.asarray(gain) * np.sum(np.where(keep, rho, 0.0), axis=-1))
    return rho, first, kappa


def residual_correlation(z: np.ndarray, max_lag: int = MAX_LAG_FRAMES, fitted_dof: int = 0) -> ResidualCorrelation:
    """The correlation of a whole run's normalised residuals ``z (n, m)`` (module docstring); ``fitted_dof``: the
    parameters per frame of the estimate the residuals were read at (:data:`POSITION_DOF`; 0: the correlations as
    measured). The lag sums in blocks of frames (:func:`_frame_blocks`), added frame after frame as one sum over the
    frames adds them: at once their ``(n, L)`` arrays took ~1 kB a frame (issue 17)."""
    z = np.asarray(z, float)
    prod = cnt = None
    sq, n_sq = np.empty(len(z)), np.empty(len(z))
    for rows in _frame_blocks(len(z)):
        p, c, sq[rows], n_sq[rows] = _lag_sums(z, max_lag, rows)
        prod, cnt = _running(prod, p)[-1], _running(cnt, c)[-1]
    if prod is None:
        prod, cnt = np.zeros(max_lag), np.zeros(max_lag)
    gain = float(_fitted_gain(np.isfinite(z).any(axis=0).sum(), fitted_dof))
    rho, first, kappa = _kappa(prod, cnt, sq.sum(), n_sq.sum(), gain)
    return ResidualCorrelation(rho, cnt.astype(int), int(first), float(kappa), gain)


def causal_inflation(z: np.ndarray, max_lag: int = MAX_LAG_FRAMES, memory: np.ndarray | None = None,
                     fitted_dof: int = 0) -> np.ndarray:
    """``kappa (n,)``: frame ``k``'s from the residuals of frames ``0 .. k`` only (1 until any lag is
    significant). ``memory (n,)``: the filter's per-frame memory ``a_k`` (:func:`filter_memory`), lag ``l``
    weighted by ``a_k^l`` (module docstring); None: every lag in full, as for an average over the whole run.
    ``fitted_dof``: as :func:`residual_correlation`'s, ``m`` the sensors that gave a reading in frames ``0 .. k``.
    A block of frames at a time, the running sums carried from block to block (at once: ~10 arrays of ``(n, L)``)."""
    z = np.asarray(z, float)
    lags = np.arange(1, max_lag + 1)
    mem = None if memory is None else np.asarray(memory, float)
    kappa = np.empty(len(z))
    prod = cnt = sq = n_sq = None
    seen = np.zeros(z.shape[1], bool)  # the sensors with a reading so far
    for rows in _frame_blocks(len(kappa)):
        p, c, s, ns = _lag_sums(z, max_lag, rows)
        prod, cnt, sq, n_sq = _running(prod, p), _running(cnt, c), _running(sq, s), _running(n_sq, ns)
        seen_k = np.logical_or.accumulate(np.vstack([seen, np.isfinite(z[rows])]), axis=0)[1:]
        gain = _fitted_gain(seen_k.sum(axis=1), fitted_dof)
        rho, first, kappa[rows] = _kappa(prod, cnt, sq, n_sq, gain)
        if mem is not None:
            kappa[rows] = _weighted_kappa(rho, first, mem[rows, None] ** lags[None], gain)
        prod, cnt, sq, n_sq, seen = prod[-1], cnt[-1], sq[-1], n_sq[-1], seen_k[-1]
    return kappa


def _weighted_kappa(rho: np.ndarray, n_lags, w: np.ndarray, gain=1.0) -> np.ndarray:
    """``kappa (n,)`` from the correlations ``rho`` (``(L,)`` or ``(n, L)``) of their first ``n_lags`` lags (a number
    or ``(n,)``), lag ``l`` weighted per frame by ``w (n, L)``: ``max(1, 1 + 2 gain sum_l w_l rho_l)`` (``gain``: a
    number or per frame, :func:`_fitted_gain`)."""
    keep = np.arange(1, w.shape[1] + 1)[None] <= np.reshape(n_lags, (-1, 1))
    return np.maximum(1.0, 1.0 + 2.0 * np.asarray(gain) * np.sum(np.where(keep, np.atleast_2d(rho) * w, 0.0), axis=1))


def two_sided_lag_weights(memory: np.ndarray, max_lag: int) -> np.ndarray:
    """``c (n, L)``: the weight of lag ``l`` in the variance inflation of a two-sided exponential average with
    weights ``a^|i|`` (``a``: each frame's ``memory``), ``sum_i w_i w_(i+l) / sum_i w_i^2 =
    a^l (2 + (l - 1)(1 - a^2)) / (1 + a^2)``: 1 at every lag for ``a = 1`` (the whole run), 0 for ``a = 0``."""
    a = np.clip(np.asarray(memory, float), 0.0, 1.0)[:, None]
    lags = np.arange(1, max_lag + 1)[None]
    return a**lags * (2.0 + (lags - 1) * (1.0 - a * a)) / (1.0 + a * a)


def smoother_inflation(corr: ResidualCorrelation, memory: np.ndarray | None) -> np.ndarray | float:
    """The smoother's ``kappa`` per frame: the whole run's correlation ``corr`` (its initial sequence of lags),
    each lag weighted by :func:`two_sided_lag_weights` of the forward filter's ``memory`` (module docstring);
    ``corr.kappa`` (every lag in full) without it."""
    if memory is None or not len(corr.rho):
        return corr.kappa
    memory = np.asarray(memory, float)
    kappa = np.empty(len(memory))
    for rows in _frame_blocks(len(kappa)):  # (the (n, L) lag weights a block at a time)
        kappa[rows] = _weighted_kappa(corr.rho, corr.n_lags, two_sided_lag_weights(memory[rows], len(corr.rho)),
                                      corr.fitted_gain)
    return kappa


def filter_memory(res: FusionResult) -> np.ndarray | None:
    """``a (n,)``: per frame, the share of the filter's position information it carried over from the frames
    before (``tr`` of the prior's position information over the posterior's; 1 where no reading updated it); None
    for a run without its stored passes."""
    ps = res.passes
    if ps is None:
        return None
    if ps.is_released:
        raise ValueError("filter_memory needs the run's priors and posteriors: take it before the passes are released")
    j_post = np.trace(np.linalg.inv(ps.post_P[:, :3, :3]), axis1=1, axis2=2)
    j_prior = np.trace(np.linalg.inv(ps.prior_P[:, :3, :3]), axis1=1, axis2=2)
    return np.clip(j_prior / j_post, 0.0, 1.0)


def inflate(res: FusionResult, kappa) -> FusionResult:
    """A copy of ``res`` whose covariance (position and orientation) is scaled by ``kappa`` (a number, or one
    per frame); positions, rotations and the stored filter passes are the same objects."""
    out = copy.copy(res)
    k = np.broadcast_to(np.asarray(kappa, float), (len(res.cov),))
    out.cov = res.cov * k[:, None, None]
    return out

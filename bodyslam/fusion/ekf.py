"""The error-state EKF of Body-SLAM fusion, as one object over a candidate axis (dissertation Sec. 3.3).

State per candidate ``c``: the pose ``T_w_c`` -- position ``p[c]`` (world/body frame, m) and orientation
``R[c]`` (3x3, ``R_w_c``) -- and the covariance ``P[c]`` over the error ``[dp, dtheta]`` with
``R = R_hat exp([dtheta]x)``. ``C`` candidates run side by side with the same inputs (the orientation search
runs 60-90 starts at once, :mod:`bodyslam.fusion.orientation_search`); the plain filter is one candidate. Keeping
``keep=True`` stores every frame's prior and posterior (``x_prior`` / ``x_post``, FilterPy's habit), which the
RTS smoother (:func:`bodyslam.fusion.body_slam.rts_smooth`) needs.

- :func:`process_model` (``F``, ``Q`` of one step; also what :mod:`testbed.bound` uses for the PCRB, so the
  bound models exactly the filter's process): the visual step ``T_c1_c2 = (R_s, t_s)`` is the input,
  ``p <- p + R t_s``, ``R <- R R_s``; Jacobian ``dp' = dp - R [t_s]x dtheta``, ``dtheta' = R_s^T dtheta``; noise
  ``R diag(sig_t^2) R^T`` on the position and ``sig_r^2 I`` on the orientation.
- :meth:`ErrorStateEkf.update`: an RF position fix with its covariance (``mode="fix"``) or the raw RSS
  readings linearised at the predicted position (``mode="rss"``). Fixes beyond the 99.9% chi-square gate, and
  RSS readings beyond a per-reading 99.9% gate, are not used and counted. Divergence guard: after
  ``max_rejections`` gated measurements in a row the covariance is inflated and the next one accepted (a filter
  that rejects everything can never recover). The negative log-likelihood of the readings (each term capped at
  the gate, so one outlier cannot decide) is summed per candidate: it ranks starts.
- The covariance update of a fix is in Joseph form (it stays symmetric positive semi-definite under rounding);
  RSS readings, independent given the state, update in information form, ``P' = (P^-1 + H^T W H)^-1``
  symmetrised: the same posterior with D x D inverses instead of an m x m one (equal to the Kalman form to
  1e-15 m over a 10,000-frame exam; ``localize`` there 4.75 -> 4.17 s).
- Optional RSS bias states (``bias_corr_m > 0``, ``mode="rss"``): one per sensor, ``b_j`` (dB), the part of a
  reading the path-loss model does not explain and that persists -- shadowing correlated along the path and the
  sensor's own departure from the calibration. A first-order Gauss-Markov process in the distance travelled
  (``b' = rho b + w``, ``rho = exp(-|t_s| / bias_corr_m)``, stationary 1-sigma ``bias_sd_db``, the discrete form of
  Gudmundson's exponential correlation); a reading is ``mean(p) + b_j + v`` with white ``v`` of the rest of the
  model's variance (at least 1 dB). The state becomes ``[dp, dtheta, b]`` (``6 + m``); without them it is 6 and
  every number is as before.
- Optional visual scale state (``scale_sd_rel > 0``): ``s``, the relative error of the lumen radius the vision
  assumed (its translations scale with it). The applied translation is ``(1 + s) t_s`` (``dp' = ... + R t_s ds``);
  ``s`` is a first-order Gauss-Markov process in the distance travelled (correlation distance ``scale_corr_m``,
  stationary 1-sigma ``scale_sd_rel``: the radius changes over centimetres, so neighbouring steps share their
  error) that the RF readings observe through the path's length. It comes first after the pose:
  ``[dp, dtheta, s, b]``. Measured on realistic tuning seeds 500-506 (radius prior 1.25 +- 0.25 cm, true radius
  1.2 +- 0.3 cm with contractions): online filter 5.31 -> 5.10 cm, smoother 4.36 -> 4.31.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.choices import FUSION_MODES
from bodyslam.errors import InputError
from bodyslam.fusion.rf import Fix, PathLossModel
from bodyslam.geometry import rotvec_to_matrix
from bodyslam.steps import StepLengths, StepMotion, lost_to_motion
from bodyslam.vision.tracking import SCALE_CORR_M

try:  # the one-candidate RSS filter compiled (setup.py builds it where a C compiler is at hand); else numpy's
    from bodyslam.fusion import _ekf_rss as _ekf_c
except ImportError:
    _ekf_c = None
_warned = False
log = logging.getLogger(__name__)

__all__ = ["process_model", "step_pose", "process_noise", "ErrorStateEkf", "FilterPasses", "with_orientation_sigma",
           "CHI2_3_999", "Z_GATE_999"]

CHI2_3_999 = 16.27
Z_GATE_999 = 3.29  # per-reading two-sided 99.9% gate on a normalised RSS innovation
# frames per call of the compiled filter (_ekf_rss.c): its per-frame record (~1.4 kB) is stored block by block
COMPILED_BLOCK_FRAMES = 4096
# divergence guard's covariance inflation: position (fixes: 4x their covariance; RSS: 5 cm), orientation 10 deg
GUARD_FIX_COV_SCALE, GUARD_RSS_SIGMA_M, GUARD_THETA_RAD = 4.0, 0.05, np.radians(10.0)
# process-noise floors of an estimated step (the fit's own 1-sigma can be optimistic) and the rule for a step
# without an estimate: the last estimated translation again (constant velocity), 1-sigma its own size (>= 3 mm);
# a step lost to motion at least as long as the steps so far at their LOST_STEP_QUANTILE and the radius's floor
# (step_noise)
SIGMA_T_FLOOR_M, SIGMA_R_FLOOR_RAD = 3e-4, np.radians(0.2)
MISSING_SIGMA_T_MIN_M, MISSING_SIGMA_R_RAD = 3e-3, np.radians(5.0)


_I3, _I6 = np.eye(3), np.eye(6)


def _skew(v):
    """``[v]x`` of a vector (3,), or of many (..., 3) at once."""
    v = np.asarray(v, float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return S - np.swapaxes(S, -1, -2)


def process_model(R_w_c: np.ndarray, t_s_m: np.ndarray, R_s: np.ndarray, sigma_t_m: float,
                  sigma_r_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """``(F, Q)`` of one step (module docstring) for orientations ``R_w_c (C, 3, 3)``: ``(C, 6, 6)`` each."""
    R_w_c = np.asarray(R_w_c, float).reshape(-1, 3, 3)
    C = len(R_w_c)
    F = np.broadcast_to(_I6, (C, 6, 6)).copy()
    F[:, :3, 3:] = -R_w_c @ _skew(np.asarray(t_s_m, float))
    F[:, 3:, 3:] = np.asarray(R_s, float).T
    Q = np.zeros((C, 6, 6))
    Q[:, :3, :3] = _I3 * sigma_t_m**2  # R (s^2 I) R^T: isotropic, the same in any axes
    Q[:, 3:, 3:] = _I3 * sigma_r_rad**2
    return F, Q


def step_pose(s: StepMotion) -> tuple[Rotation, np.ndarray]:
    """``(R_c1_c2, t_c1_c2_m)`` of a step with an estimate (ok, wall or bridged); a ``rotation`` step's rotation
    and zero; identity and zero otherwise."""
    if s.has_estimate:
        return Rotation.from_matrix(s.R_c1_c2), np.asarray(s.t_c1_c2_m, float)
    if s.has_rotation:
        return Rotation.from_matrix(s.R_c1_c2), np.zeros(3)
    return Rotation.identity(), np.zeros(3)


def step_rotation_matrices(steps: list[StepMotion]) -> np.ndarray:
    """``R_c1_c2 (n, 3, 3)`` of every step, orthonormalised in one vectorised call; identity without a
    rotation (as :func:`step_pose`, without a Rotation per step: this is on the whole-exam path)."""
    mats = np.repeat(np.eye(3)[None], len(steps), axis=0)
    has = [k for k, s in enumerate(steps) if s.has_rotation]
    if has:
        mats[has] = Rotation.from_matrix(np.array([steps[k].R_c1_c2 for k in has])).as_matrix()
    return mats


def step_noise(s: StepMotion, last_t: np.ndarray, scale_sd_rel: float = 0.0,
               long_m: float = 0.0) -> tuple[np.ndarray, float, float]:
    """The process rule for one step: ``(translation applied, 1-sigma translation m, 1-sigma rotation rad)``;
    a step without an estimate repeats ``last_t`` (the last estimated step: constant velocity), and so does a
    ``rotation`` step, with its own rotation 1-sigma (its translation is unknown). ``long_m``: the estimated steps
    so far at their :data:`~bodyslam.steps.LOST_STEP_QUANTILE`, at least the lumen radius's floor
    (:meth:`~bodyslam.steps.StepLengths.lost_length_m`; 0: not used). A step lost to motion
    (:func:`~bodyslam.steps.lost_to_motion`: matching loses the long steps) is ``last_t`` stretched to at least
    that length, and every step without an estimate has at least that 1-sigma (the path travelled's rule,
    :func:`bodyslam.vision.tracking.path_from_lengths`, made causal). With a scale state (``scale_sd_rel > 0``)
    the radius's part of the step's 1-sigma (:func:`bodyslam.vision.odometry.with_lumen_uncertainty`) is taken
    out: the state carries it."""
    if s.has_estimate:
        t = np.asarray(s.t_c1_c2_m, float)
        sig = s.sigma_t_m
        if scale_sd_rel > 0:
            sig = math.sqrt(max(sig**2 - (scale_sd_rel * float(np.linalg.norm(t))) ** 2, 0.0))
        return t, max(sig, SIGMA_T_FLOOR_M), max(s.sigma_r_rad, SIGMA_R_FLOOR_RAD)
    n = float(np.linalg.norm(last_t))
    t = last_t
    if long_m > n and lost_to_motion(s):  # along the last step's direction (forward when there is none)
        t = last_t * (long_m / n) if n > 1e-9 else np.array([0.0, 0.0, long_m])
    sig_t = max(n, long_m, MISSING_SIGMA_T_MIN_M)
    if s.has_rotation:
        return t, sig_t, max(s.sigma_r_rad, SIGMA_R_FLOOR_RAD)
    return t, sig_t, MISSING_SIGMA_R_RAD


def process_noise(steps: list[StepMotion], scale_sd_rel: float = 0.0,
                  lost_floor_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step: the translation the filter applies (:func:`step_noise`) and its 1-sigmas (m, rad).
    ``lost_floor_m``: the least length of a step lost to motion (:func:`bodyslam.steps.lost_step_floor_m` of the
    radius the steps assumed; the path travelled's floor, :func:`bodyslam.vision.tracking.path_from_lengths`)."""
    t_out = np.zeros((len(steps), 3))
    sig_t = np.zeros(len(steps))
    sig_r = np.zeros(len(steps))
    last_t = np.zeros(3)
    lengths = StepLengths()
    for k, s in enumerate(steps):
        long_m = 0.0 if s.has_estimate else lengths.lost_length_m(lost_floor_m)
        t_out[k], sig_t[k], sig_r[k] = step_noise(s, last_t, scale_sd_rel, long_m)
        if s.has_estimate:
            last_t = t_out[k]
            lengths.add(float(np.linalg.norm(last_t)))
    return t_out, sig_t, sig_r


def with_orientation_sigma(P: np.ndarray, sig_rad: float) -> np.ndarray:
    """A copy of ``P`` (``(..., D, D)``) whose orientation block is ``sig_rad^2 I``, uncorrelated with the rest
    of the state (a re-start)."""
    P = np.array(P, float, copy=True)
    P[..., 3:6, :] = 0.0
    P[..., :, 3:6] = 0.0
    P[..., 3:6, 3:6] = np.eye(3) * sig_rad**2
    return P


@dataclass
class FilterPasses:
    """Every frame's prior and posterior of a one-candidate run (what the RTS smoother needs):
    ``p (n, 3)``, ``R (n, 3, 3)``, ``P (n, 6, 6)``; ``F[k]`` takes the posterior of frame ``k`` to the prior of
    ``k + 1`` (``(n - 1, 6, 6)``). After the smoother has run they may be :meth:`released` (None)."""

    prior_p: np.ndarray | None
    prior_R: np.ndarray | None
    prior_P: np.ndarray | None  # (n, D, D): D = 6, or 7 with the scale state (the RSS bias states marginalised)
    F: np.ndarray | None
    post_p: np.ndarray | None
    post_R: np.ndarray | None
    post_P: np.ndarray | None
    prior_b: np.ndarray | None = None  # (n, e) the states kept after the pose: the scale state (e = 0 without it)
    post_b: np.ndarray | None = None
    # (n, m) the RSS bias states after each update (dB; None without them). They are not in the stored P, F and
    # prior/post_b: the passes keep the pose and scale block, the biases marginalised (ErrorStateEkf.run)
    post_bias_db: np.ndarray | None = None
    post_bias_var_db2: np.ndarray | None = None  # (n, m) their variances (the diagonal of their covariance block)

    def released(self) -> FilterPasses:
        """These passes without what only the RTS smoother reads: every frame's priors, posteriors and ``F`` (~1 kB
        a frame, 100 MB over a 100,000-frame exam), held until the exam's outputs are written unless released
        (issue 17); the RSS bias states' rows, which the whole-exam solve and the readings' correlation read after
        the smoother, kept."""
        return FilterPasses(None, None, None, None, None, None, None, post_bias_db=self.post_bias_db,
                            post_bias_var_db2=self.post_bias_var_db2)

    @property
    def is_released(self) -> bool:
        return self.post_P is None


class ErrorStateEkf:
    """The filter (module docstring) over frames ``0 .. n-1`` of one exam.

    Inputs fixed at construction: ``steps`` (``n - 1``), ``fixes`` (``n``), ``rss (n, m)`` with the sensors and
    the path-loss model (``mode="rss"``). State after :meth:`start`: ``p (C, 3)``, ``R (C, 3, 3)``, ``P (C, D,
    D)`` (``D = 6``, or ``6 + m`` with the bias states ``b (C, m)``), ``nll (C,)`` (summed), ``streak (C,)``
    (gated measurements in a row), ``n_rejected``/``n_updates (C,)``.
    """

    def __init__(self, steps: list[StepMotion], fixes: list[Fix] | None, rss: np.ndarray | None,
                 sensors_w_m: np.ndarray | None, normals_w: np.ndarray | None, pl: PathLossModel | None,
                 mode: str = "rss", max_rejections: int = 5, bias_corr_m: float = 0.0, bias_sd_db: float = 4.0,
                 scale_sd_rel: float = 0.0, scale_corr_m: float = SCALE_CORR_M, lost_floor_m: float = 0.0):
        if mode not in FUSION_MODES:
            raise InputError(f"fusion mode must be one of {', '.join(FUSION_MODES)}, got {mode!r}")
        if mode == "rss" and (rss is None or sensors_w_m is None or pl is None):
            raise InputError("RSS fusion needs the readings, the sensor positions and the path-loss model")
        self.fixes, self.rss, self.pos, self.nrm, self.pl = fixes, rss, sensors_w_m, normals_w, pl
        self.mode, self.max_rejections = mode, max_rejections
        self.t_applied, self.sig_t, self.sig_r = process_noise(steps, scale_sd_rel, lost_floor_m)
        self.R_steps = step_rotation_matrices(steps)
        self.m_bias = len(sensors_w_m) if (mode == "rss" and bias_corr_m > 0) else 0
        self.n_scale = 1 if scale_sd_rel > 0 else 0
        self.m_extra = self.n_scale + self.m_bias  # the states after the pose: [scale], [biases]
        self.D = 6 + self.m_extra
        # the RSS update's form (ErrorStateEkf.update): the Kalman form's m x m solve where the bias states make the
        # state outnumber the readings, the information form's D x D inverses otherwise (the same posterior)
        self.kalman_form = self.m_bias > 0
        self.bias_sd_db = float(bias_sd_db)
        self.scale_sd_rel = float(scale_sd_rel)
        step_len = np.linalg.norm(self.t_applied, axis=1)
        if self.m_bias:
            self.rho = np.exp(-step_len / bias_corr_m)
        if self.n_scale:
            self.rho_s = np.exp(-step_len / scale_corr_m)

    # -- the state --------------------------------------------------------------------------------------------
    def start(self, p: np.ndarray, R: np.ndarray, P: np.ndarray, b: np.ndarray | None = None) -> None:
        """Candidates' start at the first frame of a run (before its update): ``p (C, 3)``, ``R (C, 3, 3)`` (or
        Rotations), ``P (C, 6, 6)`` or ``(C, D, D)``; ``b (C, m)`` the bias states (default zero, with their
        stationary covariance)."""
        if isinstance(R, Rotation):
            R = R.as_matrix()
        self.p = np.array(p, float).reshape(-1, 3)
        self.R = np.array(R, float).reshape(-1, 3, 3)
        C = len(self.p)
        P = np.array(P, float)
        P = P.reshape(-1, P.shape[-1], P.shape[-1])
        if P.shape[-1] != self.D:
            full = np.zeros((len(P), self.D, self.D))
            full[:, :6, :6] = P[:, :6, :6]
            full[:, 6:, 6:] = np.diag(self._extra_var())
            P = full
        self.P = np.broadcast_to(P, (C, self.D, self.D)).copy() if len(P) == 1 and C > 1 else P
        self.b = np.zeros((C, self.m_extra)) if b is None else np.array(b, float).reshape(C, self.m_extra)
        self.nll = np.zeros(C)
        self.streak = np.zeros(C, int)
        self.n_rejected = np.zeros(C, int)
        self.n_updates = np.zeros(C, int)

    def _extra_var(self) -> np.ndarray:
        """Stationary variances of the states after the pose: the scale's, then each bias's."""
        return np.r_[[self.scale_sd_rel**2] * self.n_scale, [self.bias_sd_db**2] * self.m_bias]

    def predict(self, k: int) -> np.ndarray:
        """Into frame ``k`` with step ``k - 1``; returns ``F (C, D, D)``."""
        ts, Rs = self.t_applied[k - 1], self.R_steps[k - 1]
        C = len(self.p)
        # the translation applied: the step's, scaled by (1 + s) with the scale state (one per candidate)
        ts_c = np.repeat(ts[None], C, axis=0) * (1.0 + self.b[:, :1]) if self.n_scale else ts
        F, Q = process_model(self.R, ts, Rs, self.sig_t[k - 1], self.sig_r[k - 1])
        if self.n_scale:
            F[:, :3, 3:] = -self.R @ _skew(ts_c)
        if self.m_extra:  # Gauss-Markov steps of the scale and the biases, driven by the distance travelled
            D = self.D
            rho = np.r_[self.rho_s[k - 1:k] if self.n_scale else [],
                        np.repeat(self.rho[k - 1], self.m_bias) if self.m_bias else []]
            F6, Q6 = F, Q
            F, Q = np.zeros((C, D, D)), np.zeros((C, D, D))
            F[:, :6, :6], Q[:, :6, :6] = F6, Q6
            F[:, 6:, 6:] = np.diag(rho)
            Q[:, 6:, 6:] = np.diag((1.0 - rho**2) * self._extra_var())
            if self.n_scale:
                F[:, :3, 6] = self.R @ ts  # dp' / ds
            self.b = self.b * rho
        if self.n_scale:
            self.p = self.p + np.einsum("cij,cj->ci", self.R, ts_c)
        else:
            self.p = self.p + self.R @ ts
        self.R = self.R @ Rs
        self.P = F @ self.P @ F.transpose(0, 2, 1) + Q
        return F

    def update(self, k: int) -> None:
        """The readings of frame ``k`` (none, or none that passes the gate: no change but the counters)."""
        C = len(self.p)
        p, R, P, nll, streak = self.p, self.R, self.P, self.nll, self.streak
        if self.mode == "fix":
            f = self.fixes[k]
            if f.status != "ok":
                return
            y = f.position_w_m[None] - p  # (C, 3)
            S = P[:, :3, :3] + f.cov_m2
            d2 = np.einsum("ci,ci->c", y, np.linalg.solve(S, y[..., None])[..., 0])
            nll = nll + 0.5 * (np.minimum(d2, CHI2_3_999) + np.linalg.slogdet(S)[1])
            gated = d2 > CHI2_3_999
            self.n_rejected = self.n_rejected + gated
            streak = np.where(gated, streak + 1, streak)
            guard = gated & (streak >= self.max_rejections)
            do = ~gated | guard
            P = P.copy()
            P[guard, :3, :3] += GUARD_FIX_COV_SCALE * f.cov_m2
            P[guard, 3:6, 3:6] += np.eye(3) * GUARD_THETA_RAD**2
            streak = np.where(do, 0, streak)
            H = np.repeat(np.hstack([np.eye(3), np.zeros((3, self.D - 3))])[None], C, axis=0)
            Rm = np.repeat(f.cov_m2[None], C, axis=0)
            S = H @ P @ H.transpose(0, 2, 1) + Rm
            K = P @ H.transpose(0, 2, 1) @ np.linalg.inv(S)
            dx = (K @ y[..., None])[..., 0]
            IKH = np.eye(self.D) - K @ H
            P_new = IKH @ P @ IKH.transpose(0, 2, 1) + K @ Rm @ K.transpose(0, 2, 1)  # Joseph form
        else:
            r = self.rss[k]
            ok = np.isfinite(r)
            if ok.sum() < 1:
                return
            sens, nrm = self.pos[ok], self.nrm[ok]
            diff = sens[None] - p[:, None, :]  # (C, m, 3)
            d = np.sqrt(np.add.reduce(diff * diff, axis=2))  # np.linalg.norm's own sum, without its checks
            depth = np.maximum(np.einsum("cij,ij->ci", diff, nrm), 0.0)
            pl0, alpha, sigma = self.pl.params(depth)
            Hp = (10.0 * alpha / np.log(10.0))[..., None] * diff / (d**2)[..., None]
            y = r[ok][None] - self.pl.mean_from_params(d, pl0, alpha)
            # H is zero outside the columns J the readings touch: the position, and with the bias states each
            # reading's own bias. Everything below works on those columns: HJ = H[:, :, J] (C, m, j)
            if self.m_bias:  # reading j = mean(p) + b_j + white noise of the model's remaining variance
                idx = np.nonzero(ok)[0]
                J = np.r_[0:3, 6 + self.n_scale + idx]
                HJ = np.concatenate([Hp, np.broadcast_to(np.eye(len(idx)), (C, len(idx), len(idx)))], axis=2)
                y = y - self.b[:, self.n_scale + idx]
                sigma = np.sqrt(np.maximum(sigma**2 - self.bias_sd_db**2, 1.0))
                PJJ = P[:, J][:, :, J]
            else:
                J = slice(0, 3)
                HJ = Hp
                PJJ = P[:, :3, :3]
            dS = np.sum((HJ @ PJJ) * HJ, axis=2) + sigma**2  # the innovations' variances (the diagonal of S)
            z2 = y * y / dS
            nll = nll + 0.5 * np.sum(np.minimum(z2, Z_GATE_999**2) + np.log(dS), axis=1)
            keep = z2 < Z_GATE_999**2  # per-reading 99.9% gate
            self.n_rejected = self.n_rejected + (~keep).sum(axis=1)
            bad = keep.mean(axis=1) < 0.5  # most readings disagree with the prediction
            streak = np.where(bad, streak + 1, 0)
            guard = bad & (streak >= self.max_rejections)
            if guard.any():
                P = P.copy()
                P[guard, :3, :3] += _I3 * GUARD_RSS_SIGMA_M**2
                P[guard, 3:6, 3:6] += _I3 * GUARD_THETA_RAD**2
                PJJ = P[:, J][:, :, J] if self.m_bias else P[:, :3, :3]
            keep[guard] = True
            streak = np.where(guard, 0, streak)
            do = keep.sum(axis=1) >= 1
            PJ = P[:, :, J]  # (C, D, j): P H^T = PJ HJ^T
            if not self.kalman_form:
                # Information form: the readings are independent given the state (diagonal noise), so the update
                # is P' = (P^-1 + H^T W H)^-1, dx = P' H^T W y with W = 1 / sigma^2 -- 0 for a reading outside the
                # gate, exactly the update without it. H^T W H = A is nonzero only on J, so by Woodbury
                # P' = P - PJ A (I + PJJ A)^-1 PJ^T: one j x j solve (j = 3 without the bias states) instead of two
                # D x D inverses; I + PJJ A is never singular (PJJ A, a product of two PSD matrices, has no negative
                # eigenvalue). The same posterior (tested against the Kalman form and the two inverses).
                HJW = HJ * np.where(keep, 1.0 / sigma**2, 0.0)[..., None]
                A = HJW.transpose(0, 2, 1) @ HJ
                X = np.linalg.solve(np.eye(A.shape[-1]) + PJJ @ A, PJ.transpose(0, 2, 1))  # (C, j, D)
                P_new = P - PJ @ (A @ X)
                P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
                dx = np.einsum("cdj,cj->cd", P_new[:, :, J], np.einsum("cmj,cm->cj", HJW, y))
            else:
                # Kalman form with the bias states, where the state outnumbers the readings (D = 6 + m): one solve
                # with the m x m innovation covariance S = H P H^T + diag(sigma^2) instead of two D x D inverses
                # (the same posterior; localize on a 200-frame realistic run 2.66 -> 1.8 s). A reading outside the
                # gate gets no row of H and a zero innovation: exactly the update without it.
                HJk = np.where(keep[..., None], HJ, 0.0)
                HPk = HJk @ PJ.transpose(0, 2, 1)  # (C, m, D): H P = (P H^T)^T, P symmetric
                S = HJk @ (HJk @ PJJ).transpose(0, 2, 1)
                S[:, np.arange(S.shape[1]), np.arange(S.shape[1])] += np.where(keep, sigma**2, 1.0)
                KT = np.linalg.solve(S, HPk)  # K^T = S^-1 H P, S symmetric
                dx = np.einsum("cm,cmd->cd", np.where(keep, y, 0.0), KT)
                P_new = P - HPk.transpose(0, 2, 1) @ KT
                P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
        # commit the correction and covariance for the candidates that updated; the others keep theirs
        R_new = R @ rotvec_to_matrix(dx[:, 3:6])
        if self.m_extra:
            self.b = np.where(do[:, None], self.b + dx[:, 6:], self.b)
        self.p = np.where(do[:, None], p + dx[:, :3], p)
        self.R = np.where(do[:, None, None], R_new, R)
        self.P = np.where(do[:, None, None], P_new, P)
        self.nll, self.streak = nll, streak
        self.n_updates = self.n_updates + do

    # -- a run ------------------------------------------------------------------------------------------------
    def run(self, p, R, P, k0: int, k1: int, keep: bool = False, resets: dict | None = None, decide=None,
            b=None, decide_at=None):
        """Frames ``k0 .. k1-1`` from the candidates' state at ``k0`` (before its update).

        ``resets`` ``{frame: (R (3, 3) or Rotation, sigma_rad)}``: after the prediction into that frame every
        candidate's orientation is replaced and its orientation covariance set to ``sigma_rad^2 I``
        (uncorrelated with the position). ``decide(k, p (3,), R (3, 3), P (D, D), b (m,))`` (one candidate): called
        after each prediction into a frame without a given reset; a ``(R, sigma_rad)`` it returns is applied the
        same way and recorded in ``resets``. ``decide_at``: the frames where ``decide`` may act (a set; None: any
        frame); elsewhere it is not called. ``keep``: store the priors and posteriors (one candidate).

        One candidate in ``rss`` mode without the bias states runs compiled between those frames where the
        extension is built (``_ekf_rss.c``: the same arithmetic, to rounding), else in numpy.

        Returns ``(positions (C, f, 3), rotations (C, f, 3, 3), covariances (C, f, 6, 6), cumulative nll (C,
        f), passes or None)`` with ``f = k1 - k0``. One pass: the cost is linear in the frames.
        """
        self.start(p, R, P, b)
        C, f = len(self.p), k1 - k0
        if (keep or decide is not None) and C != 1:
            raise ValueError("keep and decide are for one candidate")
        resets = {} if resets is None else resets
        pos, rot, covs, nll_k = np.zeros((C, f, 3)), np.zeros((C, f, 3, 3)), np.zeros((C, f, 6, 6)), np.zeros((C, f))
        # the stored passes keep the pose and the scale state, and marginalise the bias states: memory stays that
        # of a 6-7 dimensional state whatever the number of sensors (32 biases would be ~35 kB a frame, 1.9 GB over
        # a 55,000-frame exam), and the smoother over that block is within 0.02 cm of the full one (realistic
        # tuning seeds 503-509: 3.34 against 3.32 cm; docs/RESULTS.md)
        D = 6 + self.n_scale
        out = {"pos": pos, "rot": rot, "covs": covs, "nll_k": nll_k}
        if keep:
            out.update(prior_p=np.zeros((f, 3)), prior_R=np.zeros((f, 3, 3)), prior_P=np.zeros((f, D, D)),
                       Fs=np.zeros((max(f - 1, 0), D, D)), prior_b=np.zeros((f, self.n_scale)),
                       post_b=np.zeros((f, self.n_scale)), post_P=np.zeros((f, D, D)),
                       post_bias=np.zeros((f, self.m_bias)) if self.m_bias else None,
                       post_bias_var=np.zeros((f, self.m_bias)) if self.m_bias else None)
        compiled = _ekf_c is not None and C == 1 and self.mode == "rss" and not self.m_bias and (
            decide is None or decide_at is not None)
        global _warned
        if _ekf_c is None and keep and self.mode == "rss" and not self.m_bias and not _warned:
            _warned = True
            log.info("RSS filter: the compiled frames (bodyslam/fusion/_ekf_rss.c) are not built here; using numpy's, "
                     "~0.4 ms a frame instead of ~0.01 (reinstall with a C compiler: pip install -e .)")
        # the frames Python must take: a reset's, or where decide may act
        stops = sorted(k for k in set(resets) | (set(decide_at) if decide is not None else set()) if k0 < k < k1) \
            if compiled else []
        k = k0
        while k < k1:
            if compiled and (k == k0 or k not in resets and not (decide is not None and k in decide_at)):
                nxt = next((s for s in stops if s > k), k1)
                self._run_compiled(k, nxt, k0, keep, out)
                k = nxt
                continue
            self._frame(k, k0, keep, resets, decide if decide_at is None or k in decide_at else None, out)
            k += 1
        pos, rot, covs, nll_k = out["pos"], out["rot"], out["covs"], out["nll_k"]
        if keep:
            prior_p, prior_R, prior_P, Fs = out["prior_p"], out["prior_R"], out["prior_P"], out["Fs"]
            prior_b, post_b, post_P = out["prior_b"], out["post_b"], out["post_P"]
            post_bias, post_bias_var = out["post_bias"], out["post_bias_var"]
        passes = None
        if keep:
            passes = FilterPasses(prior_p, prior_R, prior_P, Fs, pos[0].copy(), rot[0].copy(), post_P, prior_b, post_b,
                                  post_bias, post_bias_var)
        return pos, rot, covs, nll_k, passes

    def _frame(self, k: int, k0: int, keep: bool, resets: dict, decide, out: dict) -> None:
        """One frame of :meth:`run` in numpy: the prediction into it (after the run's first), a reset or
        ``decide``'s, the update; its outputs into ``out``."""
        i = k - k0
        D = 6 + self.n_scale
        if k > k0:
            F = self.predict(k)
            if k not in resets and decide is not None:
                d = decide(k, self.p[0].copy(), self.R[0].copy(), self.P[0].copy(), self.b[0].copy())
                if d is not None:
                    resets[k] = d
            if k in resets:
                Rr, sig = resets[k]
                self.R[:] = Rr.as_matrix() if isinstance(Rr, Rotation) else Rr
                self.P = with_orientation_sigma(self.P, sig)
            if keep:
                out["Fs"][i - 1] = F[0, :D, :D]
                if k in resets:  # the new orientation does not depend on the old one: the prior stored
                    out["Fs"][i - 1, 3:6, :] = 0.0  # below is F' P F'^T + Q' with these rows zero (RTS needs that)
        if keep:
            out["prior_p"][i], out["prior_R"][i], out["prior_P"][i] = self.p[0], self.R[0], self.P[0, :D, :D]
            out["prior_b"][i] = self.b[0, :self.n_scale]
        self.update(k)
        out["pos"][:, i], out["rot"][:, i], out["covs"][:, i] = self.p, self.R, self.P[:, :6, :6]
        out["nll_k"][:, i] = self.nll
        if keep:
            out["post_P"][i], out["post_b"][i] = self.P[0, :D, :D], self.b[0, :self.n_scale]
            if out["post_bias"] is not None:
                out["post_bias"][i] = self.b[0, self.n_scale:]
                out["post_bias_var"][i] = np.diagonal(self.P[0])[D:]

    def _run_compiled(self, a: int, b: int, k0: int, keep: bool, out: dict) -> None:
        """Frames ``a .. b-1`` of :meth:`run` (one candidate, ``rss`` mode, no bias states) in ``_ekf_rss.c``:
        no reset or decision among them; frame ``a`` predicted unless it is the run's first."""
        D, ns = 6 + self.n_scale, self.n_scale
        self.compiled_inputs()
        state = np.concatenate([self.p[0], self.R[0].ravel(), self.P[0].ravel(), self.b[0, :ns],
                                [self.nll[0], self.streak[0], self.n_rejected[0], self.n_updates[0]]]).astype(float)
        W = 49 + (12 + 3 * D * D + 2 * ns if keep else 0)
        for a1 in range(a, b, COMPILED_BLOCK_FRAMES):  # in blocks: the record stays ~5 MB, not ~1.4 kB a frame
            b1 = min(a1 + COMPILED_BLOCK_FRAMES, b)  # (the state carries everything from one block to the next)
            rec = np.empty((b1 - a1, W))
            _ekf_c.run(state, self._c_steps, self._c_rss, self._c_pos, self._c_nrm, self._c_params, rec, a1, b1,
                       int(a1 > k0), ns, int(keep))
            self._store_compiled(rec, a1, b1, k0, keep, out)
        e = 12 + D * D
        self.p, self.R, self.P = state[None, :3].copy(), state[3:12].reshape(1, 3, 3).copy(), \
            state[12:e].reshape(1, D, D).copy()
        if ns:
            self.b = state[None, e:e + 1].copy()
        self.nll = state[e + ns:e + ns + 1].copy()
        self.streak, self.n_rejected, self.n_updates = (state[e + ns + j:e + ns + j + 1].astype(int) for j in (1, 2, 3))

    def compiled_inputs(self) -> None:
        """The compiled filter's inputs, made once: per step its translation, rotation, 1-sigmas and the scale's
        rho (``(n - 1, 15)``, 120 bytes a frame), the parameters, contiguous readings and sensors. Made before a
        ``copy.copy`` of the filter (:func:`bodyslam.fusion.body_slam.fuse`'s searcher), the copies share them."""
        if getattr(self, "_c_steps", None) is not None:
            return
        n1, ns = len(self.t_applied), self.n_scale
        tab = np.zeros((n1, 15))
        tab[:, :3], tab[:, 3:12] = self.t_applied, self.R_steps.reshape(n1, 9)
        tab[:, 12], tab[:, 13] = self.sig_t, self.sig_r
        if ns:
            tab[:, 14] = self.rho_s
        pl = self.pl
        self._c_steps = tab
        self._c_params = np.array([pl.pt_dbm, pl.d0_m, pl.near_surface_depth_m, *pl.near, *pl.deep,
                                   self.max_rejections, Z_GATE_999, GUARD_RSS_SIGMA_M, GUARD_THETA_RAD,
                                   self.scale_sd_rel**2], float)
        self._c_rss = np.ascontiguousarray(self.rss, np.float64)
        self._c_pos = np.ascontiguousarray(self.pos, np.float64)
        self._c_nrm = np.ascontiguousarray(self.nrm, np.float64)

    def _store_compiled(self, rec: np.ndarray, a: int, b: int, k0: int, keep: bool, out: dict) -> None:
        """The compiled frames ``a .. b-1``'s record ``rec`` into :meth:`run`'s outputs ``out``."""
        D, ns = 6 + self.n_scale, self.n_scale
        i0, i1 = a - k0, b - k0
        out["pos"][0, i0:i1], out["rot"][0, i0:i1] = rec[:, :3], rec[:, 3:12].reshape(-1, 3, 3)
        out["covs"][0, i0:i1], out["nll_k"][0, i0:i1] = rec[:, 12:48].reshape(-1, 6, 6), rec[:, 48]
        if keep:
            q = rec[:, 49:]
            out["prior_p"][i0:i1], out["prior_R"][i0:i1] = q[:, :3], q[:, 3:12].reshape(-1, 3, 3)
            out["prior_P"][i0:i1] = q[:, 12:12 + D * D].reshape(-1, D, D)
            j0 = 1 if a == k0 else 0  # the run's first frame has no F
            out["Fs"][i0 + j0 - 1:i1 - 1] = q[j0:, 12 + D * D:12 + 2 * D * D].reshape(-1, D, D)
            out["post_P"][i0:i1] = q[:, 12 + 2 * D * D:12 + 3 * D * D].reshape(-1, D, D)
            if ns:
                out["prior_b"][i0:i1, 0], out["post_b"][i0:i1, 0] = q[:, 12 + 3 * D * D], q[:, 13 + 3 * D * D]

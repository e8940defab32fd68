"""Body-SLAM fusion of visual motion and RF localization (dissertation Sec. 3.3), with covariances.

State: the capsule pose ``T_w_c`` -- position ``p`` (world/body frame, m) and orientation ``R_w_c`` -- as an
error-state EKF: the covariance is over ``[dp, dtheta]`` (6x6) with ``R = R_hat exp([dtheta]x)``.

- Process (the visual step ``T_c1_c2 = (R_s, t_s)`` of :mod:`bodyslam.motion` as input):
  ``p <- p + R t_s``, ``R <- R R_s``; Jacobian ``dp' = dp - R [t_s]x dtheta``, ``dtheta' = R_s^T dtheta``;
  noise from the step's own 1-sigma (floors 0.3 mm, 0.2 deg). A step without an estimate (facing the wall, too
  few matches after a big jump) repeats the last estimated step (constant velocity) with a 1-sigma as large as
  that step (at least 3 mm) and 5 deg: handled, not skipped (measured: such steps moved 0.55-0.95 cm on average
  on thesis seeds, so assuming a stop biased the path).
- Measurements: an RF position fix with its covariance (:mod:`bodyslam.rf`, ``mode="fix"``), or the raw RSS
  readings with the path-loss model (``mode="rss"``: the EKF linearises Eq. 2.1 at the predicted position; no
  intermediate trilateration). Innovations beyond the 99.9% chi-square gate are rejected and counted.
- Initialisation: the dead-reckoned path over the first ``init_frames`` frames (more, until it bends: 1.5 cm RMS
  spread along its second principal direction) is aligned to the RF fixes by a weighted Procrustes fit
  (rotation + translation), which gives ``p_0`` and ``R_w_c0``: vision alone has no world frame, RF alone no
  orientation. The fit is then checked against other orientations (:func:`_search_orientation`): the filter is
  run from the fit turned by each of the 60 rotations of the icosahedral group, from the fit of the frames
  before the first step without an estimate, and from refinements, and the start whose filter explains the
  readings of the first ``search_frames`` (80) frames best is kept, with a 30 deg orientation 1-sigma. Why: dead
  reckoning across steps without an estimate bends the path, and the fit was 166, 150, 127 and 79 deg off on
  four of 30 seeds; a linearised filter does not recover from that.
- Re-start after long gaps: after ``regap_steps`` (5) or more steps in a row without a visual estimate the
  capsule may have turned any way (a 2 cm jump, a roll of tens of degrees), so the orientation is searched
  again the same way from the filter's predicted pose (position and its covariance kept). Measured on seeds
  300-309, which had two runs diverging after such gaps: EKF 2.09 -> 1.28 cm, smoother 1.57 -> 0.73.
- Online output while a search is open (the start's and each re-start's window): the likelihood-weighted mixture
  of the candidates, each on the readings up to that frame (a Gaussian-sum filter; refinements join at a quarter
  and at half of the window, around the candidate leading then), so no estimate uses later readings except
  through the start's alignment window. The committed run (one candidate per decision, the one that explains
  the whole window best) is what the RTS smoother smooths.
- Divergence guard: after ``max_rejections`` gated measurements in a row the covariance is inflated and the next
  measurement accepted (a filter that rejects everything can never recover).
- :func:`rts_smooth`: Rauch-Tung-Striebel smoothing of the stored filter passes (a whole exam is reviewed after
  the fact, so the future is available).

Units: metres, radians; covariances m^2 / rad^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.errors import InputError
from bodyslam.rf import Fix, PathLossModel

__all__ = ["Step", "FusionResult", "process_noise", "predict", "DeadReckoner", "fuse", "rts_smooth", "align_to_fixes", "steps_from_motion_rows", "kf_thesis"]

CHI2_3_999 = 16.27
Z_GATE_999 = 3.29  # per-reading two-sided 99.9% gate on a normalised RSS innovation
# divergence guard's covariance inflation: position (fixes: 4x their covariance; RSS: 5 cm), orientation 10 deg
GUARD_FIX_COV_SCALE, GUARD_RSS_SIGMA_M, GUARD_THETA_RAD = 4.0, 0.05, np.radians(10.0)


@dataclass(frozen=True)
class Step:
    """One visual step: ``R_c1_c2`` (Rotation), ``t_c1_c2_m`` (3,), 1-sigma distance and rotation; ``ok``."""

    R: Rotation
    t: np.ndarray
    sigma_t_m: float
    sigma_r_rad: float
    ok: bool
    bridged: bool = False  # a share of a gap's end-to-end motion (bodyslam.tracking.split_motion)


@dataclass
class FusionResult:
    positions_w_m: np.ndarray  # (n, 3)
    rotations_w_c: Rotation
    cov: np.ndarray  # (n, 6, 6) over [p, theta]
    n_rejected: int = 0
    n_updates: int = 0
    passes: dict = field(default_factory=dict, repr=False)  # for the smoother


def _bridge(s: Step, last_t: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The process rule for one step: ``(translation applied, 1-sigma translation m, 1-sigma rotation rad)``;
    a step without an estimate repeats ``last_t`` (the last estimated step: constant velocity)."""
    if s.ok:
        return s.t, max(s.sigma_t_m, 3e-4), max(s.sigma_r_rad, np.radians(0.2))
    return last_t, max(float(np.linalg.norm(last_t)), 3e-3), np.radians(5.0)


def process_noise(steps: list[Step]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step: the translation the filter applies (the estimate, or for a step without one the last
    estimated step: constant velocity), and the 1-sigma of translation (m) and rotation (rad) it assumes."""
    t_out = np.zeros((len(steps), 3))
    sig_t = np.zeros(len(steps))
    sig_r = np.zeros(len(steps))
    last_t = np.zeros(3)
    for k, s in enumerate(steps):
        t_out[k], sig_t[k], sig_r[k] = _bridge(s, last_t)
        if s.ok:
            last_t = s.t
    return t_out, sig_t, sig_r


def predict(p: np.ndarray, R: Rotation, P: np.ndarray, t_s: np.ndarray, R_s: Rotation, sig_t: float,
            sig_r: float) -> tuple[np.ndarray, Rotation, np.ndarray, np.ndarray]:
    """One process step of the error-state model (module docstring): ``(p', R', P', F)``."""
    Rm = R.as_matrix()
    F = np.eye(6)
    F[:3, 3:] = -Rm @ _skew(t_s)
    F[3:, 3:] = R_s.as_matrix().T
    Q = np.zeros((6, 6))
    Q[:3, :3] = Rm @ (np.eye(3) * sig_t**2) @ Rm.T
    Q[3:, 3:] = np.eye(3) * sig_r**2
    return p + R.apply(t_s), R * R_s, F @ P @ F.T + Q, F


class DeadReckoner:
    """Streaming dead reckoning with the filter's process model and its covariance (no measurements).

    World frame: the first camera frame, known exactly (``P = 0`` at frame 0). Per :meth:`step`: the pose
    ``p_w_m``, ``R_w_c``, the 6x6 covariance ``P`` over ``[p, theta]``, and the path travelled ``path_m`` (sum of
    the applied step lengths) with its variance ``path_var_m2`` (steps independent). Memory is constant.
    """

    def __init__(self) -> None:
        self.p_w_m = np.zeros(3)
        self.R_w_c = Rotation.identity()
        self.P = np.zeros((6, 6))
        self.path_m = 0.0
        self.path_var_m2 = 0.0
        self._last_t = np.zeros(3)

    def step(self, s: Step) -> None:
        t_s, sig_t, sig_r = _bridge(s, self._last_t)
        if s.ok:
            self._last_t = s.t
        R_s = s.R if s.ok else Rotation.identity()
        self.p_w_m, self.R_w_c, self.P, _ = predict(self.p_w_m, self.R_w_c, self.P, t_s, R_s, sig_t, sig_r)
        self.path_m += float(np.linalg.norm(t_s))
        self.path_var_m2 += sig_t**2


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _second_spread(q: np.ndarray) -> float:
    """RMS spread of points along their second principal direction (m)."""
    if len(q) < 3:
        return 0.0
    sv = np.linalg.svd(q - q.mean(axis=0), compute_uv=False)
    return float(sv[1] / np.sqrt(len(q)))


def _paired_fixes(dr_positions: np.ndarray, fixes: list[Fix]):
    """Dead-reckoned points ``q`` and the RF fixes ``z`` of the same frames (fixes that are ``ok``), the weights
    ``w = 1 / tr(cov)`` and the weighted means ``qm``, ``zm``: the data of :func:`align_to_fixes`."""
    ok = [k for k, f in enumerate(fixes) if f.status == "ok" and k < len(dr_positions)]
    if len(ok) < 3:
        raise InputError("need at least 3 RF fixes to align the visual trajectory to the body frame")
    q = dr_positions[ok]
    z = np.array([fixes[k].position_w_m for k in ok])
    w = np.array([1.0 / max(np.trace(fixes[k].cov_m2), 1e-8) for k in ok])
    return q, z, w, (w[:, None] * q).sum(0) / w.sum(), (w[:, None] * z).sum(0) / w.sum()


def align_to_fixes(dr_positions: np.ndarray, fixes: list[Fix]) -> tuple[Rotation, np.ndarray, float]:
    """Weighted Procrustes: ``R, p0`` with ``p0 + R q_k ~= z_k``; returns also the rms residual (m)."""
    q, z, w, qm, zm = _paired_fixes(dr_positions, fixes)
    H = ((q - qm) * w[:, None]).T @ (z - zm)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    p0 = zm - R @ qm
    res = z - (p0 + q @ R.T)
    return Rotation.from_matrix(R), p0, float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


class _Ekf:
    """The filter loop of :func:`fuse` over frames ``0 .. n-1`` from a given start ``(p, R, P)``; it also sums
    the negative log-likelihood of the readings (per reading for RSS, per fix for fixes; each term capped at
    the gate so one outlier cannot decide), which ranks initial orientations."""

    def __init__(self, steps, fixes, rss, sensors_w_m, normals_w, pl, mode, max_rejections):
        self.steps, self.fixes, self.rss, self.pos, self.nrm, self.pl = steps, fixes, rss, sensors_w_m, normals_w, pl
        self.mode, self.max_rejections = mode, max_rejections
        self.bridged_t, self.sig_t, self.sig_r = process_noise(steps)

    def run(self, p, R, P, k1: int, keep: bool = True, k0: int = 0, resets: dict | None = None,
            decide=None) -> tuple[FusionResult, float]:
        """Frames ``k0 .. k1-1`` from the state ``(p, R, P)`` at ``k0`` (before its update). ``resets``:
        ``{frame: (R, sigma_rad)}`` -- after the prediction into that frame its orientation is replaced and
        its orientation covariance set to ``sigma_rad^2 I`` (uncorrelated with the position). ``decide(k, p, R,
        P)``: called after each prediction (frames without a given reset); a ``(R, sigma_rad)`` it returns is
        applied the same way and recorded in ``resets``. One pass: the cost is linear in the frames."""
        self.rejected = self.updates = self.streak = 0
        self.nll = 0.0
        self.nll_k = np.zeros(k1 - k0)  # cumulative, after each frame's update
        resets = {} if resets is None else resets
        p = np.asarray(p, float).copy()
        n = k1 - k0
        pos = np.zeros((n, 3))
        quats = np.zeros((n, 4))
        covs = np.zeros((n, 6, 6))
        prior = {"p": [], "R": [], "P": [], "F": []}
        post = {"p": [], "R": [], "P": []}
        for k in range(k0, k1):
            if k > k0:
                s = self.steps[k - 1]
                ts, Rs = self.bridged_t[k - 1], (s.R if s.ok else Rotation.identity())
                p, R, P, F = predict(p, R, P, ts, Rs, self.sig_t[k - 1], self.sig_r[k - 1])
                if k not in resets and decide is not None:
                    d = decide(k, p, R, P)
                    if d is not None:
                        resets[k] = d
                if k in resets:
                    R, sig = resets[k]
                    P = _with_orientation_sigma(P, sig)
                if keep:
                    prior["F"].append(F)
            if keep:
                prior["p"].append(p.copy())
                prior["R"].append(R)
                prior["P"].append(P.copy())
            p, R, P = self.update(p, R, P, k)
            if keep:
                post["p"].append(p.copy())
                post["R"].append(R)
                post["P"].append(P.copy())
            pos[k - k0], quats[k - k0], covs[k - k0] = p, R.as_quat(), P
            self.nll_k[k - k0] = self.nll
        res = FusionResult(pos, Rotation.from_quat(quats), covs, self.rejected, self.updates,
                           {"prior": prior, "post": post})
        return res, self.nll

    def update(self, p, R, P, k):
        if self.mode == "fix":
            f = self.fixes[k]
            if f.status != "ok":
                return p, R, P
            H = np.hstack([np.eye(3), np.zeros((3, 3))])
            y = f.position_w_m - p
            S = P[:3, :3] + f.cov_m2
            d2 = float(y @ np.linalg.solve(S, y))
            self.nll += 0.5 * (min(d2, CHI2_3_999) + np.linalg.slogdet(S)[1])
            if d2 > CHI2_3_999:
                self.rejected += 1
                self.streak += 1
                if self.streak < self.max_rejections:
                    return p, R, P
                # divergence guard: after max_rejections gated fixes in a row the filter, not RF, is wrong
                P = P.copy()
                P[:3, :3] += GUARD_FIX_COV_SCALE * f.cov_m2
                P[3:, 3:] += np.eye(3) * GUARD_THETA_RAD**2
            self.streak = 0
            Rm = f.cov_m2
        else:
            r = self.rss[k]
            ok = np.isfinite(r)
            if ok.sum() < 1:
                return p, R, P
            mean, sigma, Hp = self.pl.predict(p, self.pos[ok], self.nrm[ok])
            y = r[ok] - mean
            H = np.hstack([Hp, np.zeros((len(y), 3))])
            Rm = np.diag(sigma**2)
            S = H @ P @ H.T + Rm
            z2 = y * y / np.diag(S)
            self.nll += 0.5 * float(np.sum(np.minimum(z2, Z_GATE_999**2) + np.log(np.diag(S))))
            keep = z2 < Z_GATE_999**2  # per-reading 99.9% gate
            self.rejected += int((~keep).sum())
            if keep.mean() < 0.5:  # most readings disagree with the prediction
                self.streak += 1
                if self.streak >= self.max_rejections:  # divergence guard (see the fix branch)
                    P = P.copy()
                    P[:3, :3] += np.eye(3) * GUARD_RSS_SIGMA_M**2
                    P[3:, 3:] += np.eye(3) * GUARD_THETA_RAD**2
                    keep[:] = True
                    self.streak = 0
            else:
                self.streak = 0
            if keep.sum() < 1:
                return p, R, P
            H, y, Rm = H[keep], y[keep], Rm[np.ix_(keep, keep)]
        S = H @ P @ H.T + Rm
        K = P @ H.T @ np.linalg.inv(S)
        dx = K @ y
        p = p + dx[:3]
        R = R * Rotation.from_rotvec(dx[3:])
        IKH = np.eye(6) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T  # Joseph form
        self.updates += 1
        return p, R, P


    def run_batch(self, p: np.ndarray, R: np.ndarray, P: np.ndarray, k0: int, k1: int):
        """:meth:`run` for ``C`` starts at once (no resets): ``p (C, 3)``, ``R (C, 3, 3)`` rotation matrices,
        ``P (C, 6, 6)``. Returns the cumulative negative log-likelihood ``(C, k1-k0)``, positions
        ``(C, k1-k0, 3)`` and covariances ``(C, k1-k0, 6, 6)``; the same numbers as :meth:`run` per candidate
        (tested), ~40x faster for the 60-90 candidates of an orientation search."""
        C = len(p)
        p, R, P = p.astype(float).copy(), R.astype(float).copy(), P.astype(float).copy()
        f = k1 - k0
        nll = np.zeros(C)
        streak = np.zeros(C, int)
        nll_k = np.zeros((C, f))
        pos = np.zeros((C, f, 3))
        covs = np.zeros((C, f, 6, 6))
        eye6 = np.eye(6)
        for k in range(k0, k1):
            if k > k0:
                s = self.steps[k - 1]
                ts = self.bridged_t[k - 1]
                Rs = (s.R if s.ok else Rotation.identity()).as_matrix()
                F = np.repeat(eye6[None], C, axis=0)
                F[:, :3, 3:] = -R @ _skew(ts)
                F[:, 3:, 3:] = Rs.T
                Q = np.zeros((C, 6, 6))
                Q[:, :3, :3] = R @ (np.eye(3) * self.sig_t[k - 1] ** 2) @ R.transpose(0, 2, 1)
                Q[:, 3:, 3:] = np.eye(3) * self.sig_r[k - 1] ** 2
                p = p + R @ ts
                R = R @ Rs
                P = F @ P @ F.transpose(0, 2, 1) + Q
            p, R, P, nll, streak = self._update_batch(p, R, P, k, nll, streak)
            nll_k[:, k - k0], pos[:, k - k0], covs[:, k - k0] = nll, p, P
        return nll_k, pos, covs

    def _update_batch(self, p, R, P, k, nll, streak):
        C = len(p)
        if self.mode == "fix":
            f = self.fixes[k]
            if f.status != "ok":
                return p, R, P, nll, streak
            y = f.position_w_m[None] - p  # (C, 3)
            S = P[:, :3, :3] + f.cov_m2
            d2 = np.einsum("ci,ci->c", y, np.linalg.solve(S, y[..., None])[..., 0])
            nll = nll + 0.5 * (np.minimum(d2, CHI2_3_999) + np.linalg.slogdet(S)[1])
            gated = d2 > CHI2_3_999
            streak = np.where(gated, streak + 1, streak)
            guard = gated & (streak >= self.max_rejections)
            do = ~gated | guard
            P = P.copy()
            P[guard, :3, :3] += GUARD_FIX_COV_SCALE * f.cov_m2
            P[guard, 3:, 3:] += np.eye(3) * GUARD_THETA_RAD**2
            streak = np.where(do, 0, streak)
            H = np.repeat(np.hstack([np.eye(3), np.zeros((3, 3))])[None], C, axis=0)
            Rm = np.repeat(f.cov_m2[None], C, axis=0)
        else:
            r = self.rss[k]
            ok = np.isfinite(r)
            if ok.sum() < 1:
                return p, R, P, nll, streak
            sens, nrm = self.pos[ok], self.nrm[ok]
            diff = sens[None] - p[:, None, :]  # (C, m, 3)
            d = np.linalg.norm(diff, axis=2)
            depth = np.maximum(np.einsum("cij,ij->ci", diff, nrm), 0.0)
            _, alpha, sigma = self.pl.params(depth)
            Hp = (10.0 * alpha / np.log(10.0))[..., None] * diff / (d**2)[..., None]
            y = r[ok][None] - self.pl.mean_rss_dbm(d, depth)
            H = np.concatenate([Hp, np.zeros_like(Hp)], axis=2)  # (C, m, 6)
            S = H @ P @ H.transpose(0, 2, 1) + sigma[:, :, None] ** 2 * np.eye(len(y[0]))[None]
            dS = np.diagonal(S, axis1=1, axis2=2)
            z2 = y * y / dS
            nll = nll + 0.5 * np.sum(np.minimum(z2, Z_GATE_999**2) + np.log(dS), axis=1)
            keep = z2 < Z_GATE_999**2
            bad = keep.mean(axis=1) < 0.5
            streak = np.where(bad, streak + 1, 0)
            guard = bad & (streak >= self.max_rejections)
            P = P.copy()
            P[guard, :3, :3] += np.eye(3) * GUARD_RSS_SIGMA_M**2
            P[guard, 3:, 3:] += np.eye(3) * GUARD_THETA_RAD**2
            keep[guard] = True
            streak = np.where(guard, 0, streak)
            do = keep.sum(axis=1) >= 1
            # readings outside the gate: rows of H and y zeroed and unit variance -- exactly the update without them
            H = H * keep[..., None]
            y = y * keep
            Rm = np.where(keep, sigma**2, 1.0)[:, :, None] * np.eye(len(y[0]))[None]
        S = H @ P @ H.transpose(0, 2, 1) + Rm
        K = P @ H.transpose(0, 2, 1) @ np.linalg.inv(S)
        dx = (K @ y[..., None])[..., 0]
        IKH = np.eye(6)[None] - K @ H
        P_new = IKH @ P @ IKH.transpose(0, 2, 1) + K @ Rm @ K.transpose(0, 2, 1)
        R_new = R @ Rotation.from_rotvec(dx[:, 3:]).as_matrix()
        p = np.where(do[:, None], p + dx[:, :3], p)
        R = np.where(do[:, None, None], R_new, R)
        P = np.where(do[:, None, None], P_new, P)
        return p, R, P, nll, streak

def fuse(steps: list[Step], fixes: list[Fix] | None = None, rss: np.ndarray | None = None,
         sensors_w_m: np.ndarray | None = None, normals_w: np.ndarray | None = None,
         pl: PathLossModel | None = None, mode: str = "fix", init_frames: int = 40,
         init: tuple[Rotation, np.ndarray] | None = None, init_spread_m: float = 0.015,
         max_rejections: int = 5, init_search: bool = True, search_frames: int = 80,
         regap_steps: int | None = 5) -> FusionResult:
    """EKF over ``len(steps) + 1`` frames. ``fixes[k]`` / ``rss[k]`` are the RF readings at frame ``k``.

    ``init``: a known start ``(R_w_c0, p_w0)``; ``None``: aligned to the fixes (module docstring), and with
    ``init_search`` checked against other orientations (:func:`_search_orientation`) over ``search_frames``.
    ``regap_steps``: after a run of at least that many steps without a visual estimate the orientation is
    searched again the same way (``None``: never)."""
    n = len(steps) + 1
    if mode not in ("fix", "rss"):
        raise InputError(f"fusion mode must be 'fix' or 'rss', got {mode!r}")
    if fixes is None or len(fixes) != n:
        raise InputError(f"need one RF fix per frame for initialisation ({n}), got "
                         f"{0 if fixes is None else len(fixes)}")
    if mode == "rss" and (rss is None or sensors_w_m is None or pl is None):
        raise InputError("RSS fusion needs the readings, the sensor positions and the path-loss model")
    # dead reckoning in the first camera frame, for the initial alignment
    dr = np.zeros((n, 3))
    Rdr = Rotation.identity()
    for k, s in enumerate(steps, start=1):
        dr[k] = dr[k - 1] + Rdr.apply(s.t if s.ok else np.zeros(3))
        Rdr = Rdr * (s.R if s.ok else Rotation.identity())
    ekf = _Ekf(steps, fixes, rss, sensors_w_m, normals_w, pl, mode, max_rejections)
    search = []
    if init is None:
        # The window grows until the dead-reckoned path bends: its second principal RMS spread must reach
        # init_spread_m. Along a straight path the rotation about the path's direction is unobservable
        # (measured: a 40-frame straight start aligned 155 deg off about its axis).
        m = min(n, max(init_frames, 3))
        while m < n and _second_spread(dr[:m]) < init_spread_m:
            m += 1
        R0, p0, rms = align_to_fixes(dr[:m], fixes[:m])
        alignment = (R0, p0)
        s2 = max(_second_spread(dr[:m]), 1e-3)
        sig_theta = min(max(rms / (np.sqrt(m) * s2), np.radians(5.0)), np.radians(45.0))
        P = np.diag([rms**2 / m + 1e-4] * 3 + [sig_theta**2] * 3)
        if init_search and n > 3:
            *_, qm, zm = _paired_fixes(dr[:m], fixes[:m])

            def start_of(R):  # the weighted least-squares translation that goes with orientation R
                return zm - R.apply(qm)

            extra = []
            ok = np.array([s.ok for s in steps[: m - 1]])
            first_gap = int(np.argmin(ok)) + 1 if not ok.all() else m
            if 10 <= first_gap < m:  # dead reckoning across a gap bends the path: align the part before it
                extra.append(align_to_fixes(dr[:first_gap], fixes[:first_gap])[0])
            sig = max(sig_theta, np.radians(30.0))
            P[3:, 3:] = np.eye(3) * sig**2
            R0, p0, info = _search_orientation(ekf, 0, min(n, search_frames), R0, start_of, P, extra)
            search.append(info)
    else:
        R0, p0 = init
        alignment = init
        P = np.diag([1e-4] * 3 + [np.radians(5.0) ** 2] * 3)
    gap_ends = set(_gap_ends(steps, regap_steps)) if regap_steps else set()

    def decide(b, p_b, R_b, P_b):
        """At the end of a long gap: search the orientation from the predicted pose (position kept)."""
        if b not in gap_ends:
            return None
        sig = max(float(np.sqrt(np.trace(P_b[3:, 3:]) / 3)), np.radians(30.0))
        p_b = p_b.copy()
        R_new, _, info = _search_orientation(ekf, b, min(n, b + search_frames), R_b, lambda R: p_b,
                                             _with_orientation_sigma(P_b, sig), [])
        info["frame"] = b
        search.append(info)
        return R_new, sig

    resets: dict = {}
    res, _ = ekf.run(p0, R0, P.copy(), n, resets=resets, decide=decide)
    # Online output: inside each decision window (start, after a long gap) the candidates' mixture on the readings
    # so far, so that no estimate uses later readings (except the start's alignment window); the smoother uses
    # the committed chain (passes), which is one filter run with the decisions taken.
    committed = res.positions_w_m.copy()
    for info in search:
        k0, k1 = info["frames"]
        res.positions_w_m[k0:k1] = info.pop("leader_positions_w_m")
        res.cov[k0:k1] = info.pop("leader_cov")
    res.passes.update({"init": (R0, np.asarray(p0, float)), "P0": P, "dead_reckoning": dr, "search": search,
                       "alignment": alignment,  # the rigid fit of the first window, before any search
                       "committed_positions_w_m": committed, "resets": {k: v[0] for k, v in resets.items()}})
    return res


def _with_orientation_sigma(P: np.ndarray, sig_rad: float) -> np.ndarray:
    """A copy of ``P`` whose orientation block is ``sig_rad^2 I``, uncorrelated with the position (a re-start)."""
    P = P.copy()
    P[3:, :3] = P[:3, 3:] = 0.0
    P[3:, 3:] = np.eye(3) * sig_rad**2
    return P


def _gap_ends(steps: list[Step], min_len: int) -> list[int]:
    """Frames reached by the last step of each run of at least ``min_len`` steps without an estimate."""
    out, run = [], 0
    for k, s in enumerate(steps, start=1):
        run = 0 if s.ok else run + 1
        if run >= min_len and (k == len(steps) or steps[k].ok):
            out.append(k)
    return out


def _search_orientation(ekf: _Ekf, k0: int, k1: int, R_centre: Rotation, position_of, P: np.ndarray,
                        extra: list[Rotation]) -> tuple[Rotation, np.ndarray, dict]:
    """The orientation at frame ``k0`` under which the filter best explains the readings of frames
    ``k0 .. k1-1`` (negative log-likelihood, :class:`_Ekf`): ``(R, p, summary)``.

    Used at the start (vision has no world frame; RF no orientation) and after long runs of steps without a
    visual estimate (the capsule may have turned any way meanwhile, and a linearised filter does not recover
    from errors of tens of degrees: measured on seeds 301, 306, 308). Candidates: ``R_centre`` (the alignment,
    or the filter's own prediction), ``R_centre`` turned by each of the 59 other rotations of the icosahedral
    group (no orientation is more than 44 deg from one of the 60), and ``extra``; at a quarter and at half of
    the window, turns of 20 and 10 deg about 14 axes of the candidate leading then join. ``position_of(R)``: the
    start position that goes with ``R``; every candidate starts from the covariance ``P``. The committed
    candidate explains the whole window best (a decision with a ``k1 - k0`` frame lag); the summary carries
    the candidates' mixture per frame on the readings so far (``leader_positions_w_m``, ``leader_cov``), the
    causal output while the decision is open."""
    group = Rotation.create_group("I")
    cands = [R_centre] + [R_centre * g for g in group if g.magnitude() > 1e-6] + list(extra)
    pool = []  # (R, p, cumulative nll per frame, positions, covariances, first frame it may be used)

    def add(Rs, first):
        ps = np.array([position_of(R) for R in Rs])
        nll_k, pos, covs = ekf.run_batch(ps, np.array([R.as_matrix() for R in Rs]),
                                         np.repeat(P[None], len(Rs), axis=0), k0, k1)
        pool.extend((R, pr, nk, x, c, first) for R, pr, nk, x, c in zip(Rs, ps, nll_k, pos, covs))

    add(cands, k0)
    # Refinement without looking ahead: at a quarter and at half of the window, turns of 20 and 10 deg about 14
    # axes (faces and corners of a cube) of the candidate leading on the readings up to then, run from k0.
    axes = np.array([v for v in np.ndindex(3, 3, 3) if sum(abs(np.array(v) - 1)) in (1, 3)], float) - 1.0
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for frac, step_deg in ((0.25, 20.0), (0.5, 10.0)):
        kc = k0 + max(1, int((k1 - k0) * frac))
        if kc >= k1:
            break
        lead = pool[int(np.argmin([c[2][kc - 1 - k0] for c in pool]))][0]
        add([lead * Rotation.from_rotvec(np.radians(step_deg) * a) for a in axes], kc)
    # Online output while the decision is open: the mixture of the candidates available at each frame, each
    # weighted by the likelihood of the readings so far (a Gaussian-sum filter; its covariance includes their
    # spread). The committed candidate is the one that explains the whole window best.
    nll_k = np.array([c[2] for c in pool])  # (candidates, frames)
    frames = np.arange(k0, k1)
    avail = np.array([c[5] for c in pool])[:, None] <= frames[None, :]
    nll_k = np.where(avail, nll_k, np.inf)
    wgt = np.exp(-(nll_k - nll_k.min(axis=0)))
    wgt /= wgt.sum(axis=0)
    X = np.array([c[3] for c in pool])  # (c, f, 3)
    mix_pos = np.einsum("cf,cfi->fi", wgt, X)
    mix_cov = np.einsum("cf,cfij->fij", wgt, np.array([c[4] for c in pool]))
    d = X - mix_pos[None]
    mix_cov[:, :3, :3] += np.einsum("cf,cfi,cfj->fij", wgt, d, d)
    best = int(np.argmin(nll_k[:, -1]))
    R, p = pool[best][0], pool[best][1]
    return R, p, {"n_candidates": len(pool), "frames": [k0, k1],
                  "turn_from_centre_deg": float(np.degrees((R_centre.inv() * R).magnitude())),
                  "nll_centre": float(nll_k[0, -1]), "nll_best": float(nll_k[best, -1]),
                  "leader_positions_w_m": mix_pos, "leader_cov": mix_cov}


def rts_smooth(res: FusionResult) -> FusionResult:
    """Rauch-Tung-Striebel smoother over an EKF pass (error-state, rotations composed on the right)."""
    pr, po = res.passes["prior"], res.passes["post"]
    n = len(po["p"])
    ps = [None] * n
    Rs = [None] * n
    Ps = [None] * n
    ps[-1], Rs[-1], Ps[-1] = po["p"][-1], po["R"][-1], po["P"][-1]
    for k in range(n - 2, -1, -1):
        F = pr["F"][k]  # prior of k+1 came from post of k through F
        Pp = pr["P"][k + 1]
        C = po["P"][k] @ F.T @ np.linalg.inv(Pp)
        dx = np.r_[ps[k + 1] - pr["p"][k + 1], (pr["R"][k + 1].inv() * Rs[k + 1]).as_rotvec()]
        corr = C @ dx
        ps[k] = po["p"][k] + corr[:3]
        Rs[k] = po["R"][k] * Rotation.from_rotvec(corr[3:])
        Ps[k] = po["P"][k] + C @ (Ps[k + 1] - Pp) @ C.T
    return FusionResult(np.array(ps), Rotation.from_quat([r.as_quat() for r in Rs]), np.array(Ps),
                        res.n_rejected, res.n_updates, res.passes)


def steps_from_motion_rows(rows: dict[int, dict], n_frames: int) -> list[Step]:
    """Steps ``1..n-1`` from ``motion.csv`` rows (:func:`bodyslam.io.read_motion_csv`); missing rows, rows
    without an estimate or without the full-step columns become steps without an estimate."""
    out = []
    for k in range(1, n_frames):
        r = rows.get(k)
        vals = None
        if r is not None and r.get("status") in ("ok", "bridged"):  # bridged: a share of a gap's motion
            try:
                vals = [float(r[c]) for c in ("tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad",
                                                 "sigma_distance_m", "sigma_rotation_rad")]
            except (KeyError, TypeError, ValueError):
                vals = None
        if vals is None or not np.all(np.isfinite(vals[:6])):
            out.append(Step(Rotation.identity(), np.zeros(3), 0.0, 0.0, False))
        else:
            sig_t = vals[6] if np.isfinite(vals[6]) else 1e-3
            sig_r = vals[7] if np.isfinite(vals[7]) else np.radians(1.0)
            out.append(Step(Rotation.from_rotvec(vals[3:6]), np.array(vals[:3]), sig_t, sig_r, True,
                            r.get("status") == "bridged"))
    return out


def kf_thesis(steps: list[Step], fixes: list[Fix], init: tuple[Rotation, np.ndarray], sigma_p_m: float = 0.002,
              sigma_n: float = 0.05, resets: dict | None = None) -> np.ndarray:
    """The dissertation's Kalman filter (Eq. 3.26-3.33), written so that it runs: state ``[x, y, z, nx, ny, nz]``
    (position and unit heading in the world frame), transition ``p <- p + v dt n`` and ``n <- dR_w n``, RF fixes
    as position measurements (``H = [I 0]``). The printed transition matrix is garbled; ``v dt`` is the visual
    step's signed distance and ``dR_w = R_w_c R_step R_w_c^T`` the step's rotation in the world frame, with
    ``R_w_c`` accumulated from ``init`` (the thesis assumes the camera starts aligned with the world axes, which
    no real or testbed capsule is; the same initial alignment as :func:`fuse` is used) and turned after each
    update so that its optical axis is the updated heading. ``fixes``: Sec. 3.3 feeds it the NLS fixes of Eq.
    3.36; any RF localizer's fixes with covariances can be given. Returns positions (n, 3).
    """
    R_wc, p0 = init
    n = len(steps) + 1
    last_d = 0.0
    x = np.r_[np.asarray(p0, float), R_wc.apply([0.0, 0.0, 1.0])]
    P = np.diag([0.02**2] * 3 + [0.2**2] * 3)
    out = np.zeros((n, 3))
    for k in range(n):
        if k > 0:
            s = steps[k - 1]
            Rs = s.R if s.ok else Rotation.identity()
            if s.ok:
                d = float(np.linalg.norm(s.t)) * (1.0 if s.t[2] >= 0 else -1.0)
                last_d = d
            else:
                d = last_d  # no visual estimate: the last step again (constant speed), as the EKF does
            dRw = (R_wc * Rs * R_wc.inv()).as_matrix()
            A = np.eye(6)
            A[:3, 3:] = d * np.eye(3)
            A[3:, 3:] = dRw
            R_wc = R_wc * Rs
            x = A @ x
            q_p = sigma_p_m if s.ok else max(abs(d), 5e-3)
            P = A @ P @ A.T + np.diag([q_p**2] * 3 + [sigma_n**2] * 3)
            if resets and k in resets:
                R_wc = resets[k]
                x[3:] = R_wc.apply([0.0, 0.0, 1.0])
                P[3:, :3] = P[:3, 3:] = 0.0
                P[3:, 3:] = np.eye(3) * 0.5**2  # the unit heading vector: 0.5 ~ 30 deg, the EKF's re-start sigma
        f = fixes[k]
        if f.status == "ok":
            H = np.hstack([np.eye(3), np.zeros((3, 3))])
            S = H @ P @ H.T + f.cov_m2
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ (f.position_w_m - H @ x)
            P = (np.eye(6) - K @ H) @ P
            # The update corrected the heading state: turn R_w_c (which carries the steps into the world frame)
            # by the smallest rotation that puts its optical axis on the new heading, so the two stay one. Left
            # out, R_w_c is dead reckoning's forever (measured on seeds 200-209: 2.38 -> 2.29 cm with ML fixes).
            nh = x[3:] / max(np.linalg.norm(x[3:]), 1e-12)
            z = R_wc.apply([0.0, 0.0, 1.0])
            axis = np.cross(z, nh)
            sn = float(np.linalg.norm(axis))
            if sn > 1e-12:
                R_wc = Rotation.from_rotvec(axis / sn * math.atan2(sn, float(z @ nh))) * R_wc
            x[3:] = nh
        out[k] = x[:3]
    return out

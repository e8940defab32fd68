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
  spread along its second principal direction) is aligned to the RF fixes by a weighted Procrustes fit (rotation + translation), which gives ``p_0`` and
  ``R_w_c0``: vision alone has no world frame, RF alone no orientation. The orientation's initial uncertainty
  follows from the fit (5-30 deg).
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


def align_to_fixes(dr_positions: np.ndarray, fixes: list[Fix]) -> tuple[Rotation, np.ndarray, float]:
    """Weighted Procrustes: ``R, p0`` with ``p0 + R q_k ~= z_k``; returns also the rms residual (m)."""
    ok = [k for k, f in enumerate(fixes) if f.status == "ok" and k < len(dr_positions)]
    if len(ok) < 3:
        raise InputError("need at least 3 RF fixes to align the visual trajectory to the body frame")
    q = dr_positions[ok]
    z = np.array([fixes[k].position_w_m for k in ok])
    w = np.array([1.0 / max(np.trace(fixes[k].cov_m2), 1e-8) for k in ok])
    qm = (w[:, None] * q).sum(0) / w.sum()
    zm = (w[:, None] * z).sum(0) / w.sum()
    H = ((q - qm) * w[:, None]).T @ (z - zm)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    p0 = zm - R @ qm
    res = z - (p0 + q @ R.T)
    return Rotation.from_matrix(R), p0, float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


def fuse(steps: list[Step], fixes: list[Fix] | None = None, rss: np.ndarray | None = None,
         sensors_w_m: np.ndarray | None = None, normals_w: np.ndarray | None = None,
         pl: PathLossModel | None = None, mode: str = "fix", init_frames: int = 40,
         init: tuple[Rotation, np.ndarray] | None = None, init_spread_m: float = 0.015,
         max_rejections: int = 5) -> FusionResult:
    """EKF over ``len(steps) + 1`` frames. ``fixes[k]`` / ``rss[k]`` are the RF readings at frame ``k``."""
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
    if init is None:
        # The window grows until the dead-reckoned path bends: its second principal RMS spread must reach
        # init_spread_m. Along a straight path the rotation about the path's direction is unobservable
        # (measured: a 40-frame straight start aligned 155 deg off about its axis).
        m = min(n, max(init_frames, 3))
        while m < n and _second_spread(dr[:m]) < init_spread_m:
            m += 1
        R0, p0, rms = align_to_fixes(dr[:m], fixes[:m])
        s2 = max(_second_spread(dr[:m]), 1e-3)
        sig_theta = min(max(rms / (np.sqrt(m) * s2), np.radians(5.0)), np.radians(45.0))
        P = np.diag([rms**2 / m + 1e-4] * 3 + [sig_theta**2] * 3)
    else:
        R0, p0 = init
        P = np.diag([1e-4] * 3 + [np.radians(5.0) ** 2] * 3)
    p, R = np.asarray(p0, float).copy(), R0
    pos = np.zeros((n, 3))
    quats = np.zeros((n, 4))
    covs = np.zeros((n, 6, 6))
    prior = {"p": [], "R": [], "P": [], "F": []}
    post = {"p": [], "R": [], "P": []}
    rejected = updates = streak = 0
    bridged_t, sig_t_all, sig_r_all = process_noise(steps)
    P_init = P.copy()

    def update(p, R, P, k):
        nonlocal rejected, updates, streak
        if mode == "fix":
            f = fixes[k]
            if f.status != "ok":
                return p, R, P
            H = np.hstack([np.eye(3), np.zeros((3, 3))])
            y = f.position_w_m - p
            S = P[:3, :3] + f.cov_m2
            if y @ np.linalg.solve(S, y) > CHI2_3_999:
                rejected += 1
                streak += 1
                if streak < max_rejections:
                    return p, R, P
                # divergence guard: after max_rejections gated fixes in a row the filter, not RF, is wrong
                P = P.copy()
                P[:3, :3] += 4.0 * f.cov_m2
                P[3:, 3:] += np.eye(3) * np.radians(10.0) ** 2
            streak = 0
            Rm = f.cov_m2
        else:
            r = rss[k]
            ok = np.isfinite(r)
            if ok.sum() < 1:
                return p, R, P
            mean, sigma, Hp = pl.predict(p, sensors_w_m[ok], normals_w[ok])
            y = r[ok] - mean
            H = np.hstack([Hp, np.zeros((len(y), 3))])
            Rm = np.diag(sigma**2)
            S = H @ P @ H.T + Rm
            keep = np.abs(y) / np.sqrt(np.diag(S)) < 3.29  # per-reading 99.9% gate
            rejected += int((~keep).sum())
            if keep.mean() < 0.5:  # most readings disagree with the prediction
                streak += 1
                if streak >= max_rejections:  # divergence guard (see the fix branch)
                    P = P.copy()
                    P[:3, :3] += np.eye(3) * 0.05**2
                    P[3:, 3:] += np.eye(3) * np.radians(10.0) ** 2
                    keep[:] = True
                    streak = 0
            else:
                streak = 0
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
        updates += 1
        return p, R, P

    for k in range(n):
        if k > 0:
            s = steps[k - 1]
            ts, Rs = bridged_t[k - 1], (s.R if s.ok else Rotation.identity())
            p, R, P, F = predict(p, R, P, ts, Rs, sig_t_all[k - 1], sig_r_all[k - 1])
            prior["F"].append(F)
        prior["p"].append(p.copy())
        prior["R"].append(R)
        prior["P"].append(P.copy())
        p, R, P = update(p, R, P, k)
        post["p"].append(p.copy())
        post["R"].append(R)
        post["P"].append(P.copy())
        pos[k], quats[k], covs[k] = p, R.as_quat(), P
    return FusionResult(pos, Rotation.from_quat(quats), covs, rejected, updates,
                        {"prior": prior, "post": post, "init": (R0, np.asarray(p0, float)), "P0": P_init,
                         "dead_reckoning": dr})


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
              sigma_n: float = 0.05) -> np.ndarray:
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
    x = np.r_[np.asarray(p0, float), R_wc.apply([0.0, 0.0, 1.0])]
    P = np.diag([0.02**2] * 3 + [0.2**2] * 3)
    out = np.zeros((n, 3))
    for k in range(n):
        if k > 0:
            s = steps[k - 1]
            Rs = s.R if s.ok else Rotation.identity()
            d = (float(np.linalg.norm(s.t)) * (1.0 if s.t[2] >= 0 else -1.0)) if s.ok else 0.0
            dRw = (R_wc * Rs * R_wc.inv()).as_matrix()
            A = np.eye(6)
            A[:3, 3:] = d * np.eye(3)
            A[3:, 3:] = dRw
            R_wc = R_wc * Rs
            x = A @ x
            q_p = sigma_p_m if s.ok else 5e-3
            P = A @ P @ A.T + np.diag([q_p**2] * 3 + [sigma_n**2] * 3)
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

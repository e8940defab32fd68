"""Magnetic localization of a screw-type capsule propelled by a single rotating actuator magnet (paper 001:
Popek, Hermans, Abbott).

What runs here is what the paper's PC runs: the dipole field and Hall-sensor model (Eq. 1-4), the magnetic torque
and force on the capsule (Eq. 16-17), the 2-DOF process model (Eq. 15-22: forward motion along and rotation about
the capsule's principal axis ``x_c``), the EKF on the 7-state ``[p, Q]`` (Eq. 8-14) with the closed-form
Jacobians of Appendix B (checked against finite differences in the tests), the synchronous-rotation detector
(Sec. VII, from the lead angle) and the actuator update of Algorithm I (Eq. 5; 80% then 50% speed to re-engage a
capsule that stepped out).

Frames and conventions: positions are relative to the actuator magnet's centre (the robot's tool frame ``r``;
the paper's ``p = p_c``), in metres, the actuator's moment ``m_a`` in that frame (A m^2). Quaternions are
``[q0, q]`` (scalar first) rotating capsule-frame vectors into the tool frame: ``r = Q c Q*`` (Eq. 27). The
capsule's dipole ``m_c`` is fixed in its frame, perpendicular to ``x_c`` (a screw capsule rolls with the field).

Corrections to the paper as printed (each checked numerically in the tests):

- Eq. 17 (force) as printed, ``(m_a p^T + p m_a^T + (p^T Z m_a) I) m_c``, is not the gradient of ``m_c . b``; the
  force of a dipole on a dipole is ``3 mu0 / (4 pi |p|^4) (m_a m_c^T + m_c m_a^T + (m_c^T Z m_a) I) p_hat``
  (Mahoney and Abbott, the paper's [9]), which is used.
- The Jacobians are written from the chain rule with the paper's building blocks (``Pi``, ``Pi*``, ``Upsilon*``
  of Eq. 34-35; Eq. 41, 46, 47), the pieces whose printed form is garbled (Eq. 36, 39, 45, 55, 59) re-derived.
- Quaternions are renormalised after each update (the paper does not say).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bodyslam.errors import ConfigError
from bodyslam.systems import runs_of

__all__ = ["MU0", "skew", "rotate", "rotate_inv", "Pi", "Pi_star", "Upsilon", "Upsilon_star", "quat_mul",
           "quat_from_rotvec", "dquat_drotvec", "field_at", "field_gradient", "torque_force", "HallArray",
           "Propulsion", "process", "process_jacobian", "process_and_jacobian", "measure", "measure_jacobian",
           "measure_and_jacobian", "MagneticEkf",
           "cross", "field_in_capsule", "lead_angle", "RotationMonitor", "rotation_axis", "ActuatorController",
           "load_recording", "replay"]

MU0 = 4e-7 * math.pi
_K = MU0 / (4 * math.pi)


def cross(a, b) -> np.ndarray:
    """``a x b`` for 3-vectors (``np.cross`` costs ~10 us of axis handling per call; this runs per sample)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def skew(a) -> np.ndarray:
    """``S[a]``: ``S[a] b = a x b``."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def Upsilon(Q) -> np.ndarray:
    """``d(Q r Q*)/dr``: the rotation matrix of Q as a function of the (not necessarily unit) quaternion (Eq. 41)."""
    q0, q = Q[0], Q[1:]
    return (q0 * q0 - q @ q) * np.eye(3) + 2 * q0 * skew(q) + 2 * np.outer(q, q)


def Upsilon_star(Q) -> np.ndarray:
    """``d(Q* r Q)/dr`` (Eq. 35)."""
    return Upsilon(Q).T


def rotate(Q, r) -> np.ndarray:
    """``Q r Q*`` (Eq. 27)."""
    return Upsilon(Q) @ r


def rotate_inv(Q, r) -> np.ndarray:
    """``Q* r Q`` (Eq. 28)."""
    return Upsilon(Q).T @ r


def Pi(r, Q) -> np.ndarray:
    """``d(Q r Q*)/dQ`` (3 x 4, Eq. 34)."""
    q0, q = Q[0], Q[1:]
    return np.hstack([(2 * q0 * r + 2 * cross(q, r))[:, None],
                      2 * (q0 * skew(r).T + np.outer(q, r) + (q @ r) * np.eye(3) - np.outer(r, q))])


def Pi_star(r, Q) -> np.ndarray:
    """``d(Q* r Q)/dQ`` (3 x 4, Eq. 35)."""
    q0, q = Q[0], Q[1:]
    return np.hstack([(2 * q0 * r + 2 * cross(r, q))[:, None],
                      2 * (q0 * skew(r) + np.outer(q, r) + (q @ r) * np.eye(3) - np.outer(r, q))])


def _left(Q) -> np.ndarray:
    """``Q . K = L(Q) K`` (Eq. 26, 46)."""
    q0, q = Q[0], Q[1:]
    M = np.empty((4, 4))
    M[0, 0], M[0, 1:], M[1:, 0], M[1:, 1:] = q0, -q, q, q0 * np.eye(3) + skew(q)
    return M


def _right(K) -> np.ndarray:
    """``Q . K = R(K) Q`` (Eq. 47)."""
    k0, k = K[0], K[1:]
    M = np.empty((4, 4))
    M[0, 0], M[0, 1:], M[1:, 0], M[1:, 1:] = k0, -k, k, k0 * np.eye(3) - skew(k)
    return M


def quat_mul(Q, K) -> np.ndarray:
    return _left(Q) @ K


def quat_from_rotvec(v) -> np.ndarray:
    """Eq. 22: the unit quaternion of rotation vector ``v`` (rad)."""
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        return np.array([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]])
    return np.concatenate([[math.cos(n / 2)], np.asarray(v) / n * math.sin(n / 2)])


def dquat_drotvec(v) -> np.ndarray:
    """``dQ/dv`` (4 x 3) of :func:`quat_from_rotvec` (Eq. 45, re-derived)."""
    v = np.asarray(v, float)
    n = float(np.linalg.norm(v))
    if n < 1e-8:
        return np.vstack([-v / 4, 0.5 * np.eye(3)])
    c, s = math.cos(n / 2), math.sin(n / 2)
    return np.vstack([-s / (2 * n) * v, s / n * np.eye(3) + np.outer(v, v) * (c / (2 * n * n) - s / n**3)])


# ------------------------------------------------------------------------------------------------- field model


def field_at(p, m_a) -> np.ndarray:
    """Eq. 1-2: the actuator dipole's field (T) at ``p`` (m, relative to the actuator)."""
    p = np.asarray(p, float)
    r2 = p @ p
    return _K / r2**2.5 * (3 * p * (p @ m_a) - r2 * np.asarray(m_a, float))


def field_gradient(p, m_a) -> np.ndarray:
    """``db/dp`` (3 x 3, symmetric: the field is curl-free)."""
    p, m = np.asarray(p, float), np.asarray(m_a, float)
    r2 = p @ p
    pm = p @ m
    return 3 * _K / r2**2.5 * (pm * np.eye(3) + np.outer(p, m) + np.outer(m, p) - 5 * pm * np.outer(p, p) / r2)


def _force(p, m_a, m_c) -> np.ndarray:
    p, ma, mc = np.asarray(p, float), np.asarray(m_a, float), np.asarray(m_c, float)
    r2 = p @ p
    a, b, g = p @ ma, p @ mc, ma @ mc
    return 3 * _K / r2**2.5 * (a * mc + g * p + b * ma - 5 * a * b * p / r2)


def _force_gradient(p, m_a, m_c) -> np.ndarray:
    """``df/dp`` (the Hessian of ``m_c . b``; Eq. 39 re-derived)."""
    p, ma, mc = np.asarray(p, float), np.asarray(m_a, float), np.asarray(m_c, float)
    r2 = p @ p
    a, b, g = p @ ma, p @ mc, ma @ mc
    gv = a * mc + g * p + b * ma - 5 * a * b * p / r2
    dg = (np.outer(mc, ma) + g * np.eye(3) + np.outer(ma, mc)
          - 5 * ((b * np.outer(p, ma) + a * np.outer(p, mc) + a * b * np.eye(3)) / r2 - 2 * a * b * np.outer(p, p) / r2**2))
    return 3 * _K * (dg / r2**2.5 - 5 * np.outer(gv, p) / r2**3.5)


def torque_force(p, Q, m_a, m_c_capsule):
    """Eq. 16-17 (force corrected, module docstring): torque (N m) and force (N) on the capsule, tool frame."""
    mc = rotate(Q, m_c_capsule)
    return cross(mc, field_at(p, m_a)), _force(p, m_a, mc)


# -------------------------------------------------------------------------------------- sensors and process


@dataclass(frozen=True)
class HallArray:
    """Hall-effect sensors inside the capsule: offsets ``delta`` (n x 3, m) from the magnet's centre and unit
    measuring axes ``alpha`` (n x 3), both in the capsule frame."""

    delta_m: np.ndarray
    alpha: np.ndarray

    def __post_init__(self):
        d, a = np.asarray(self.delta_m, float), np.asarray(self.alpha, float)
        if d.shape != a.shape or d.ndim != 2 or d.shape[1] != 3:
            raise ConfigError(f"sensor offsets {d.shape} and axes {a.shape} must both be (n, 3)")
        object.__setattr__(self, "delta_m", d)
        object.__setattr__(self, "alpha", a / np.linalg.norm(a, axis=1, keepdims=True))


@dataclass(frozen=True)
class Propulsion:
    """The helical thread's map from torque and force to angular and forward velocity along ``x_c`` (Eq. 15,
    18): ``omega_x = a tau_x + e f_x``, ``v_x = e tau_x + l f_x`` (capsule frame), and the capsule's dipole."""

    a: float
    e: float
    l: float
    m_c_capsule: tuple[float, float, float]

    def velocities(self, tau_c, f_c) -> tuple[float, float]:
        return self.a * tau_c[0] + self.e * f_c[0], self.e * tau_c[0] + self.l * f_c[0]


def process(s, o_a, m_a, prop: Propulsion, dt: float) -> np.ndarray:
    """Eq. 19-22: the state after ``dt`` s under the input ``u = [o_a, m_a]`` (the actuator's centre and moment;
    ``s = [p (m), Q]`` in the same frame, so the paper's tool-frame position is ``p - o_a``)."""
    return process_and_jacobian(s, o_a, m_a, prop, dt)[0]


def process_jacobian(s, o_a, m_a, prop: Propulsion, dt: float) -> np.ndarray:
    """``G = dg/ds`` (7 x 7, Eq. 29-48)."""
    return process_and_jacobian(s, o_a, m_a, prop, dt)[1]


def process_and_jacobian(s, o_a, m_a, prop: Propulsion, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`process` and :func:`process_jacobian` from one evaluation of the field, torque and force (the EKF
    needs both every sample)."""
    p, Q = np.asarray(s[:3], float) - np.asarray(o_a, float), s[3:]
    mcc = np.asarray(prop.m_c_capsule, float)
    mc = rotate(Q, mcc)
    b = field_at(p, m_a)
    Gb = field_gradient(p, m_a)
    tau, f = cross(mc, b), _force(p, m_a, mc)
    U_s = Upsilon_star(Q)
    dtau_dp, dtau_dQ = skew(mc) @ Gb, -skew(b) @ Pi(mcc, Q)
    df_dp, df_dQ = _force_gradient(p, m_a, mc), Gb @ Pi(mcc, Q)
    dct_dp, dct_dQ = U_s @ dtau_dp, U_s @ dtau_dQ + Pi_star(tau, Q)
    dcf_dp, dcf_dQ = U_s @ df_dp, U_s @ df_dQ + Pi_star(f, Q)
    ex = np.array([1.0, 0.0, 0.0])
    dv_dp = np.outer(ex, prop.e * dct_dp[0] + prop.l * dcf_dp[0])
    dv_dQ = np.outer(ex, prop.e * dct_dQ[0] + prop.l * dcf_dQ[0])
    dw_dp = np.outer(ex, prop.a * dct_dp[0] + prop.e * dcf_dp[0])
    dw_dQ = np.outer(ex, prop.a * dct_dQ[0] + prop.e * dcf_dQ[0])
    w, v = prop.velocities(U_s @ tau, U_s @ f)
    Qd = quat_from_rotvec(np.array([w * dt, 0.0, 0.0]))
    dQd = _left(Q) @ dquat_drotvec(np.array([w * dt, 0.0, 0.0])) * dt  # d g_Q / d omega
    R = Upsilon(Q)
    G = np.zeros((7, 7))
    G[:3, :3] = np.eye(3) + dt * R @ dv_dp
    G[:3, 3:] = dt * (Pi(np.array([v, 0.0, 0.0]), Q) + R @ dv_dQ)
    G[3:, :3] = dQd @ dw_dp
    G[3:, 3:] = _right(Qd) + dQd @ dw_dQ
    s_new = np.concatenate([s[:3] + dt * R[:, 0] * v, quat_mul(Q, Qd)])
    return s_new, G


def measure(s, o_a, m_a, sensors: HallArray) -> np.ndarray:
    """Eq. 3-4, 23: each sensor's reading (T), the actuator's field at the sensor projected on its axis."""
    p, Q = np.asarray(s[:3], float) - np.asarray(o_a, float), s[3:]
    R = Upsilon(Q)
    out = np.empty(len(sensors.alpha))
    for i, (d, a) in enumerate(zip(sensors.delta_m, sensors.alpha)):
        out[i] = a @ (R.T @ field_at(p + R @ d, m_a))
    return out


def measure_jacobian(s, o_a, m_a, sensors: HallArray) -> np.ndarray:
    """``H = dh/ds`` (n x 7, Eq. 49-60)."""
    return measure_and_jacobian(s, o_a, m_a, sensors)[1]


def measure_and_jacobian(s, o_a, m_a, sensors: HallArray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`measure` and :func:`measure_jacobian` from one evaluation of the field at each sensor."""
    p, Q = np.asarray(s[:3], float) - np.asarray(o_a, float), s[3:]
    R = Upsilon(Q)
    h = np.empty(len(sensors.alpha))
    H = np.empty((len(sensors.alpha), 7))
    for i, (d, a) in enumerate(zip(sensors.delta_m, sensors.alpha)):
        pi = p + R @ d
        b = field_at(pi, m_a)
        Gb = field_gradient(pi, m_a)
        h[i] = a @ (R.T @ b)
        H[i, :3] = a @ (R.T @ Gb)
        H[i, 3:] = a @ (R.T @ Gb @ Pi(d, Q) + Pi_star(b, Q))
    return h, H


@dataclass
class MagneticEkf:
    """Eq. 8-14 on ``s = [p, Q]``: predict with the actuator's pose ``(o_a, m_a)``, update with the Hall readings.
    ``s`` is in the frame ``o_a`` is given in (the robot's base: the actuator moves, the capsule's estimate stays)."""

    s: np.ndarray
    P: np.ndarray
    prop: Propulsion
    sensors: HallArray
    Q_proc: np.ndarray
    N_meas: np.ndarray
    body_sd_rad: tuple[float, float, float] | None = None

    def _q(self) -> np.ndarray:
        """The process noise: the paper's fixed diagonal, or with ``body_sd_rad = (roll, pitch, yaw)`` per step the
        orientation's noise as small rotations in the capsule frame mapped to the quaternion (``Q dq``: the
        capsule rolls with the field far more than the lumen turns it), the position block kept."""
        if self.body_sd_rad is None:
            return self.Q_proc
        J = 0.5 * _left(self.s[3:])[:, 1:]
        Qp = self.Q_proc.copy()
        Qp[3:, 3:] = J @ np.diag(np.square(self.body_sd_rad)) @ J.T + 1e-12 * np.eye(4)
        return Qp

    def predict(self, o_a, m_a, dt: float) -> None:
        self.s, G = process_and_jacobian(self.s, o_a, m_a, self.prop, dt)
        self.P = G @ self.P @ G.T + self._q()

    def update(self, z, o_a, m_a) -> None:
        z = np.asarray(z, float)
        ok = np.isfinite(z)
        if not ok.any():
            return
        h, H = measure_and_jacobian(self.s, o_a, m_a, self.sensors)
        H, r, N = H[ok], (z - h)[ok], self.N_meas[np.ix_(ok, ok)]
        S = H @ self.P @ H.T + N
        K = np.linalg.solve(S, H @ self.P).T
        self.s = self.s + K @ r
        self.P = (np.eye(7) - K @ H) @ self.P  # Eq. 13
        self.P = 0.5 * (self.P + self.P.T)
        self.s[3:] /= np.linalg.norm(self.s[3:])

    @property
    def position(self) -> np.ndarray:
        return self.s[:3]

    @property
    def heading(self) -> np.ndarray:
        """The principal axis ``x_c`` in the tool frame."""
        return Upsilon(self.s[3:])[:, 0] / np.linalg.norm(self.s[3:]) ** 2


# ------------------------------------------------------------------------------- regime and actuator (Sec. VII)


def field_in_capsule(z, sensors: HallArray) -> np.ndarray:
    """The applied field in the capsule frame from the Hall readings alone (least squares over the sensors' axes,
    the field taken as uniform across the sensors)."""
    z = np.asarray(z, float)
    ok = np.isfinite(z)
    return np.linalg.lstsq(sensors.alpha[ok], z[ok], rcond=None)[0]


def lead_angle(b_capsule, m_c_capsule) -> float:
    """Sec. VII: the signed angle (rad) about ``x_c`` from the capsule's dipole to the applied field."""
    m, b = np.asarray(m_c_capsule, float), np.asarray(b_capsule, float)
    return math.atan2(m[1] * b[2] - m[2] * b[1], m[1] * b[1] + m[2] * b[2])


@dataclass
class RotationMonitor:
    """Sec. VII: over the last full rotation of the field (``window`` samples) the capsule rotates synchronously
    unless the lead angle changed sign *and* exceeded pi/2 in magnitude at least once.

    The lead angle is taken from the capsule-frame field averaged over the last ``smooth`` samples: with the
    paper's sensor noise (N: 2.2-2.4 mT per sensor against a ~10 mT field) the per-sample angle scatters by ~17
    deg and the criterion calls steps-out that do not happen (README). While the capsule rotates synchronously
    that field is constant in its frame, so averaging loses nothing; in step-out it turns at the slip rate.
    """

    window: int
    m_c_capsule: tuple[float, float, float]
    smooth: int = 1
    history: list = field(default_factory=list)
    fields: list = field(default_factory=list)

    def push(self, b_capsule) -> bool:
        self.fields.append(np.asarray(b_capsule, float))
        if len(self.fields) > self.smooth:
            del self.fields[0]
        self.history.append(lead_angle(np.mean(self.fields, axis=0), self.m_c_capsule))
        if len(self.history) > self.window:
            del self.history[0]
        h = np.asarray(self.history)
        if len(h) < 2:
            return True
        sign_change = np.any(np.sign(h[1:]) != np.sign(h[:-1]))
        return not (sign_change and np.any(np.abs(h) > math.pi / 2))


def rotation_axis(p, omega_hat) -> np.ndarray:
    """Eq. 5: the actuator's rotation axis that makes the field at ``p`` rotate about ``omega_hat``."""
    p_hat = np.asarray(p, float) / np.linalg.norm(p)
    B = 3 * np.outer(p_hat, p_hat) - np.eye(3)
    w = B @ np.asarray(omega_hat, float)
    return w / np.linalg.norm(w)


@dataclass
class ActuatorController:
    """Algorithm I: the actuator keeps the desired offset from the estimated capsule, rotates about Eq. 5's axis
    at the desired rate while the capsule rotates synchronously, else at 80% for two rotations, then 50%."""

    rate_des_rad_s: float
    p_des_m: np.ndarray
    timer_s: float | None = None

    def command(self, p_est_world, heading_world, rotating: bool, dt: float) -> tuple[np.ndarray, np.ndarray, float]:
        """``(actuator position (world), rotation axis, rate rad/s)`` for the next interval."""
        o_a = np.asarray(p_est_world, float) - self.p_des_m
        axis = rotation_axis(self.p_des_m, heading_world)
        if rotating:
            self.timer_s = None
            return o_a, axis, self.rate_des_rad_s
        self.timer_s = 0.0 if self.timer_s is None else self.timer_s + dt
        t_r = 2 * 2 * math.pi / self.rate_des_rad_s
        return o_a, axis, (0.8 if self.timer_s < t_r else 0.5) * self.rate_des_rad_s


def load_recording(seq_dir) -> dict:
    """A recorded run: ``meta.json`` (sensors, magnets, the filter's calibration and initial localization),
    ``hall.csv`` (``t,b0_t..``) and ``actuator.csv`` (the actuator's pose at each reading and the pose commanded
    for the next interval). Malformed lines are skipped and listed in ``problems`` as ``(file, line, reason)``."""
    from pathlib import Path

    from bodyslam.errors import InputError
    from bodyslam.io import read_json, read_text

    d = Path(seq_dir)
    meta = read_json(d / "meta.json")
    try:
        sen, fl = meta["sensors"], meta["filter"]
        sensors = HallArray(np.asarray(sen["offsets_mm"], float) * 1e-3, np.asarray(sen["axes"], float))
        prop = Propulsion(float(fl["a"]), float(fl["e"]), float(fl["l"]), tuple(fl["m_c_capsule_am2"]))
        # the filter's arrays sized for its state [p (3), Q (4)] and for the sensors, and numbers throughout (a
        # mismatch was a numpy broadcast error in the first step of the replay)
        n = len(sensors.alpha)
        arrays = {"initial_state": (7,), "P0": (7, 7), "q_diag": (7,), "noise_var_t2": (n,), "m_c_capsule_am2": (3,)}
        v = {k: np.asarray(fl[k], float) for k in arrays}
        for k, shape in arrays.items():
            if v[k].shape != shape:
                raise ValueError(f"filter.{k} has shape {v[k].shape}, the 7-element state and {n} sensors need {shape}")
        body = np.asarray(fl["body_sd_rad"], float) if fl.get("body_sd_rad") else None
        if body is not None and body.shape != (3,):
            raise ValueError(f"filter.body_sd_rad has shape {body.shape}, it needs (roll, pitch, yaw)")
        if not all(np.all(np.isfinite(x)) for x in (*v.values(), sensors.delta_m, sensors.alpha, [prop.a, prop.e, prop.l],
                                                     [] if body is None else body)):
            raise ValueError("the filter's numbers or the sensors' offsets and axes hold a value that is not a number")
        ekf_args = {"s": v["initial_state"], "P": v["P0"], "Q_proc": np.diag(v["q_diag"]),
                    "N_meas": np.diag(v["noise_var_t2"]), "body_sd_rad": None if body is None else tuple(body)}
        dt = 1.0 / float(fl["rate_hz"])
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError("rate_hz must be a positive number")
    except (KeyError, TypeError, ValueError, AttributeError, ZeroDivisionError, OverflowError) as exc:
        raise InputError(f"{d / 'meta.json'}: not a magnetic-capsule recording ({exc!r} missing or malformed)") from None
    problems = []

    def table(name, n_cols, nan_ok):
        rows = {}
        path = d / name
        lines = read_text(path).splitlines()
        if not lines or not lines[0].strip():
            raise InputError(f"{path}: empty file: no header line (it needs t and {n_cols} more columns)")
        if len(lines[0].split(",")) != n_cols + 1:
            raise InputError(f"{path}: the header has {len(lines[0].split(','))} columns, a recording of these "
                             f"sensors needs {n_cols + 1} (t and {n_cols} more): {lines[0][:80]!r}")
        for ln, line in enumerate(lines[1:], start=2):
            try:
                v = [float(x) for x in line.split(",")]
                if len(v) != n_cols + 1:
                    raise ValueError(f"{len(v)} fields, expected {n_cols + 1}")
                if not (math.isfinite(v[0]) and 0.0 <= v[0] <= 1e6):
                    raise ValueError(f"time {v[0]:g} s outside 0-1e6 s")
                # a value that is not a number is not a reading (an actuator pose not yet reached is NaN: its first
                # line's); an infinite one never is
                bad = [x for x in v[1:] if math.isinf(x) or (math.isnan(x) and not nan_ok)]
                if bad:
                    raise ValueError(f"not a finite value: {bad[0]}")
            except ValueError as exc:
                problems.append((name, ln, f"malformed line ({exc})"))
                continue
            rows[int(round(v[0] / dt))] = np.asarray(v[1:])
        return rows

    hall = table("hall.csv", len(sensors.alpha), nan_ok=False)
    act = table("actuator.csv", 12, nan_ok=True)
    for name, rows in (("hall.csv", hall), ("actuator.csv", act)):
        if not rows:
            raise InputError(f"{d / name}: no reading in it (every line is malformed or there is none)")
    return {"sensors": sensors, "prop": prop, "ekf": ekf_args, "dt": dt, "hall": hall, "actuator": act,
            "problems": problems}


def replay(rec: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the EKF over a recording: ``(t (K+1,), states (K+1, 7), position covariances (K+1, 3, 3))``. A slot
    without a reading is predicted only. A slot without its actuator pose (a malformed line) takes the last pose
    before it (the first one after, at the start), and each such run of slots is listed in ``rec["problems"]``:
    the filter cannot predict without the field the actuator made. Where the actuator's record ends before the
    readings do, the replay ends there, and that is listed too."""
    ekf = MagneticEkf(prop=rec["prop"], sensors=rec["sensors"], **rec["ekf"])
    K = max(rec["hall"]) if rec["hall"] else 0
    act, dt = rec["actuator"], rec["dt"]
    last = max(act) if act else -1
    held = []  # slots whose actuator pose was held
    nearest = act[min(act)] if act else None  # the last pose seen so far (before any: the first one recorded)

    def pose(k):
        nonlocal nearest
        if k in act:
            nearest = act[k]
        else:
            held.append(k)
        return nearest

    states, covs = [ekf.s.copy()], [ekf.P[:3, :3].copy()]
    now = pose(0)
    for k in range(1, K + 1):
        if k > last:
            rec["problems"].append(("actuator.csv", "-", f"the actuator's poses end at t = {last * dt:g} s: the "
                                    f"replay stops there, {K - k + 1} of {K} reading slots not used"))
            break
        start, now = now, pose(k)
        ekf.predict(start[6:9], start[9:12], dt)
        if k in rec["hall"]:
            ekf.update(rec["hall"][k], now[0:3], now[3:6])
        states.append(ekf.s.copy())
        covs.append(ekf.P[:3, :3].copy())
    for a, b in runs_of(held):
        rec["problems"].append(("actuator.csv", "-", f"no actuator pose for t = {a * dt:g}"
                                f"{'' if a == b else f'-{b * dt:g}'} s: the nearest recorded pose used in its place"))
    return np.arange(len(states)) * rec["dt"], np.array(states), np.array(covs)

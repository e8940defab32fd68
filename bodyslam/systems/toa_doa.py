"""TOA/DOA and IMU hybrid localization of a capsule (paper 000: Jeong, Kang, Pahlavan, Tarokh 2017).

Two uniform rectangular arrays (URAs) worn on the front and back of the patient's jacket each measure, once per
slot of ``delta`` seconds, the time of arrival ``tau`` and the direction of arrival (azimuth ``theta`` from the
+x axis in the x-y plane, elevation ``phi`` from the x-y plane) of the capsule's signal, relative to the array's
reference element ``b`` (Eq. 3a, 5). The capsule carries an IMU that reports its acceleration (Eq. 12; the bias
is calibrated away, gravity removed). This module holds what the receivers and the capsule would run:

- :func:`toa_doa` and :func:`jacobian` -- the measurement function and its Jacobian (Eq. 17, checked against
  finite differences in the tests);
- :class:`Radio` -- the link budget (Eq. 2, Table 1: IEEE 802.15.6 implant-to-surface path loss at 405 MHz) and
  the Cramer-Rao variances of the TOA and DOA estimates for a given SNR (Eq. 7-8; checked in the tests against
  the Fisher information of the array response of Eq. 4);
- :class:`HybridEkf` -- Algorithm 1 (constant-velocity state driven by the IMU, Eq. 10-18) with the measurement
  subsets of the paper's reference schemes: ``toa_doa`` (proposed), ``toa``, ``doa`` and ``none`` (IMU only);
- :func:`snapshot_fix` -- the "RF only" reference: each slot's TOA/DOA alone, weighted Gauss-Newton;
- :func:`pcrb` -- Algorithm 2, the posterior Cramer-Rao bound (Eq. 28-29) for each scheme, the expectation over
  the channel taken by Monte Carlo over fading draws at the true positions, as the paper says.

Choices where the paper is silent (documented in the README, section "Jeong 2017"):

- The wavelength in the DOA bounds is the one in tissue, ``c_avg / f_c`` (0.53 m at 405 MHz), since the paper's
  propagation speed is ``c_avg``.
- ``SNR = |h|^2 / N0`` with the unit-energy signal of Eq. 1: the received power (dBm) less N0 (dBm/Hz), i.e. an
  energy-to-noise ratio; with the paper's numbers this gives 10-25 dB at the 40-60 cm between capsule and array
  reference, so TOA ranging errors of a few mm, in line with the paper's millimetre results.
- Each receiver knows its SNR (it measures the received power), so the filter's measurement covariance ``Z`` is
  Eq. 7-8 evaluated at the reported SNR and the measured angles (the true ones are unknown to it).
- The IMU's noise is white per slot (Eq. 12), so the true process noise is ``sigma^2 B B^T`` (rank 3). Algorithm
  1 uses the continuous-time ``Q`` of Eq. 15 (``q_model="eq15"``, faithful); ``q_model="discrete"`` uses the
  exact one. The bound always uses the true one, in the form of Eq. 28, which needs no inverse of ``Q``.

Units: SI inside (metres, seconds, radians, dBm, dBm/Hz); the paper's cm and cm/s^2 are converted in the
scenario file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bodyslam.errors import ConfigError
from bodyslam.systems import runs_of

__all__ = ["C_MPS", "Ura", "Radio", "toa_doa", "jacobian", "transition", "q_continuous", "q_discrete",
           "MEASUREMENTS", "HybridEkf", "snapshot_fix", "channel_draws", "measurement_information", "pcrb",
           "SCHEMES", "SCHEME_USE", "run_scheme", "scheme_pcrb", "load_recording"]

C_MPS = 299_792_458.0
MEASUREMENTS = {"toa_doa": (0, 1, 2), "toa": (0,), "doa": (1, 2), "none": ()}


@dataclass(frozen=True)
class Ura:
    """A uniform rectangular array: ``n_x`` elements along x spaced ``dx_m``, ``n_z`` along z spaced ``dz_m``;
    ``ref_m`` is the reference element (the corner the paper's ``b_i`` names)."""

    name: str
    ref_m: tuple[float, float, float]
    n_x: int = 5
    n_z: int = 5
    dx_m: float = 0.10
    dz_m: float = 0.10

    @classmethod
    def spanning(cls, name: str, ref_m, width_m: float, height_m: float, n_x: int, n_z: int) -> "Ura":
        """The paper's parameterisation: ``L_W x L_H`` spanned by ``N x M`` elements."""
        if n_x < 2 or n_z < 2:
            raise ConfigError(f"a URA needs at least 2 x 2 elements, got {n_x} x {n_z}")
        return cls(name, tuple(float(v) for v in ref_m), int(n_x), int(n_z), width_m / (n_x - 1),
                   height_m / (n_z - 1))


@dataclass(frozen=True)
class Radio:
    """Link budget and TOA/DOA accuracy (paper 000 Eq. 2, 7-8, Table 1; Sec. 5 values by default)."""

    pt_dbm: float = -16.0
    n0_dbm_hz: float = -121.0
    fc_hz: float = 405e6
    beta_hz: float = 300e6
    c_avg_mps: float = 2.14e8
    d0_m: float = 0.05
    deep: tuple[float, float, float] = (47.14, 4.26, 7.85)     # PL(d0) dB, exponent, shadowing sigma dB; d > 10 cm
    near: tuple[float, float, float] = (49.81, 4.22, 6.81)     # d <= 10 cm
    near_limit_m: float = 0.10

    @property
    def wavelength_m(self) -> float:
        return self.c_avg_mps / self.fc_hz

    def mean_rx_dbm(self, d_m) -> np.ndarray:
        """Large-scale received power without shadowing (Eq. 2)."""
        d = np.maximum(np.asarray(d_m, float), 1e-3)
        near = d <= self.near_limit_m
        pl0 = np.where(near, self.near[0], self.deep[0])
        mu = np.where(near, self.near[1], self.deep[1])
        return self.pt_dbm - pl0 - 10.0 * mu * np.log10(d / self.d0_m)

    def shadowing_db(self, d_m) -> np.ndarray:
        return np.where(np.asarray(d_m, float) <= self.near_limit_m, self.near[2], self.deep[2])

    def snr(self, rx_dbm) -> np.ndarray:
        """Energy-to-noise ratio (linear) of the unit-energy signal: received power over N0 (module docstring)."""
        return 10.0 ** ((np.asarray(rx_dbm, float) - self.n0_dbm_hz) / 10.0)

    def variances(self, theta, phi, snr, ura: Ura) -> np.ndarray:
        """CRB variances ``(..., 3)`` of (tau s^2, theta rad^2, phi rad^2), Eq. 7, 8a, 8b."""
        th, ph, snr = np.asarray(theta, float), np.asarray(phi, float), np.maximum(np.asarray(snr, float), 1e-300)
        N, M, dx, dz, lam = ura.n_x, ura.n_z, ura.dx_m, ura.dz_m, self.wavelength_m
        mn = M * N
        var_tau = 1.0 / (8 * math.pi**2 * self.beta_hz**2 * mn * snr)
        s2 = np.maximum(np.sin(th) ** 2 * np.cos(ph) ** 2, 1e-12)
        var_theta = 3 * lam**2 / (4 * math.pi**2 * dx**2 * s2 * mn * (N - 1) * (2 * N - 1) * snr)
        br = (dx**2 * np.cos(th) ** 2 * np.sin(ph) ** 2 * (N - 1) * (2 * N - 1) / 3
              - dx * dz * np.cos(th) * np.sin(ph) * np.cos(ph) * (M - 1) * (N - 1)
              + dz**2 * np.cos(ph) ** 2 * (M - 1) * (2 * M - 1) / 3)
        var_phi = lam**2 / (4 * math.pi**2 * mn * snr * np.maximum(br, 1e-300))
        return np.stack([var_tau, var_theta, var_phi], axis=-1)


def toa_doa(p_m, ref_m, c_mps: float) -> np.ndarray:
    """``(..., 3)``: TOA (s), azimuth and elevation (rad) of positions ``p_m (..., 3)`` seen from ``ref_m`` (Eq.
    3a, 5; the azimuth by ``atan2`` so every quadrant is right)."""
    d = np.asarray(p_m, float) - np.asarray(ref_m, float)
    rho = np.hypot(d[..., 0], d[..., 1])
    return np.stack([np.linalg.norm(d, axis=-1) / c_mps, np.arctan2(d[..., 1], d[..., 0]),
                     np.arctan2(d[..., 2], rho)], axis=-1)


def jacobian(p_m, ref_m, c_mps: float) -> np.ndarray:
    """``(..., 3, 3)``: d(tau, theta, phi)/d position (Eq. 17; the velocity columns are zero)."""
    d = np.asarray(p_m, float) - np.asarray(ref_m, float)
    r = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
    rho = np.maximum(np.hypot(d[..., 0], d[..., 1]), 1e-9)
    th, ph = np.arctan2(d[..., 1], d[..., 0]), np.arctan2(d[..., 2], rho)
    J = np.empty(d.shape[:-1] + (3, 3))
    J[..., 0, :] = d / (c_mps * r)[..., None]
    J[..., 1, 0] = -np.sin(th) / (r * np.cos(ph))
    J[..., 1, 1] = np.cos(th) / (r * np.cos(ph))
    J[..., 1, 2] = 0.0
    J[..., 2, 0] = -np.cos(th) * np.sin(ph) / r
    J[..., 2, 1] = -np.sin(th) * np.sin(ph) / r
    J[..., 2, 2] = np.cos(ph) / r
    return J


def transition(delta_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``A (6, 6)`` and ``B (6, 3)`` of Eq. 11 (state: position, velocity)."""
    I = np.eye(3)
    A = np.block([[I, delta_s * I], [np.zeros((3, 3)), I]])
    B = np.vstack([0.5 * delta_s**2 * I, delta_s * I])
    return A, B


def q_continuous(sigma_acc: float, delta_s: float) -> np.ndarray:
    """Eq. 15: process noise of continuous white acceleration noise of density ``sigma_acc^2``."""
    I = np.eye(3)
    return sigma_acc**2 * np.block([[delta_s**3 / 3 * I, delta_s**2 / 2 * I], [delta_s**2 / 2 * I, delta_s * I]])


def q_discrete(sigma_acc: float, delta_s: float) -> np.ndarray:
    """``sigma^2 B B^T``: the process noise of an IMU reading with white error ``sigma_acc`` per slot (rank 3)."""
    B = transition(delta_s)[1]
    return sigma_acc**2 * B @ B.T


def _wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def _stack_meas(p, arrays, radio, use):
    """Predicted measurements (n*k,), their Jacobian (n*k, 3) for the channels in ``use``."""
    idx = MEASUREMENTS[use]
    h = np.concatenate([toa_doa(p, a.ref_m, radio.c_avg_mps)[list(idx)] for a in arrays])
    H = np.concatenate([jacobian(p, a.ref_m, radio.c_avg_mps)[list(idx)] for a in arrays])
    return h, H


def _meas_vector(y, snr, arrays, radio, use):
    """Measured values and their variances (from the reported SNR and the measured angles)."""
    idx = list(MEASUREMENTS[use])
    var = np.stack([radio.variances(y[i, 1], y[i, 2], snr[i], a) for i, a in enumerate(arrays)])
    return y[:, idx].reshape(-1), var[:, idx].reshape(-1)


def _valid(y, snr, arrays):
    """The rows (arrays) with a full reading and an SNR: ``(y, snr, arrays)`` restricted to them."""
    y, snr = np.asarray(y, float), np.asarray(snr, float)
    ok = np.all(np.isfinite(y), axis=1) & np.isfinite(snr)
    return y[ok], snr[ok], [a for a, k in zip(arrays, ok) if k]


def _innovation(y, h, use, n_arrays):
    r = (y - h).reshape(n_arrays, -1)
    for j, ch in enumerate(MEASUREMENTS[use]):
        if ch == 1:  # azimuth wraps
            r[:, j] = _wrap(r[:, j])
    return r.reshape(-1)


@dataclass
class HybridEkf:
    """Algorithm 1: the EKF on state ``x = [p, v]`` (m, m/s), IMU acceleration as the control input.

    ``use`` picks the RF channels of the update: ``toa_doa`` (proposed), ``toa``, ``doa``, ``none`` (IMU only).
    ``update`` skips arrays whose row of ``y`` holds a NaN (a lost reading), so a missing array is handled.
    """

    arrays: list[Ura]
    radio: Radio
    x: np.ndarray
    P: np.ndarray
    sigma_acc: float
    delta_s: float = 1.0
    use: str = "toa_doa"
    q_model: str = "eq15"
    A: np.ndarray = field(init=False, repr=False)
    B: np.ndarray = field(init=False, repr=False)
    Q: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        if self.use not in MEASUREMENTS:
            raise ConfigError(f"unknown measurement set {self.use!r}; expected one of {sorted(MEASUREMENTS)}")
        if self.q_model not in ("eq15", "discrete"):
            raise ConfigError(f"q_model must be 'eq15' or 'discrete', got {self.q_model!r}")
        self.x = np.asarray(self.x, float).copy()
        self.P = np.asarray(self.P, float).copy()
        self.A, self.B = transition(self.delta_s)
        self.Q = (q_continuous if self.q_model == "eq15" else q_discrete)(self.sigma_acc, self.delta_s)

    def predict(self, u_mps2) -> None:
        """Eq. 14 with the IMU reading ``u`` (m/s^2)."""
        self.x = self.A @ self.x + self.B @ np.asarray(u_mps2, float)
        self.P = self.A @ self.P @ self.A.T + self.Q

    def update(self, y, snr) -> None:
        """Eq. 16-18. ``y (n_arrays, 3)``: tau (s), theta, phi (rad); ``snr (n_arrays,)`` linear."""
        if self.use == "none":
            return
        y, snr, arrays = _valid(y, snr, self.arrays)
        if not arrays:
            return
        z, var = _meas_vector(y, snr, arrays, self.radio, self.use)
        h, Hp = _stack_meas(self.x[:3], arrays, self.radio, self.use)
        H = np.hstack([Hp, np.zeros_like(Hp)])
        S = H @ self.P @ H.T + np.diag(var)
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ _innovation(z, h, self.use, len(arrays))
        IKH = np.eye(6) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ np.diag(var) @ K.T  # Joseph form of Eq. 18b (same value, stays PSD)


def snapshot_fix(y, snr, arrays: list[Ura], radio: Radio, p_init_m, iters: int = 20, max_step_m: float = 0.05,
                 max_jump_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """"RF only": the position from one slot's TOA/DOA alone (weighted Gauss-Newton from ``p_init_m``, steps
    capped at ``max_step_m``); returns ``(p (3,), covariance (3, 3))`` -- the inverse Fisher information at the
    solution -- or NaNs when it does not converge or lands more than ``max_jump_m`` from the start (a reading
    buried in a deep fade). NaN rows of ``y`` (a lost array) are skipped."""
    y, snr, arrays = _valid(y, snr, arrays)
    if not arrays:
        return np.full(3, np.nan), np.full((3, 3), np.nan)
    z, var = _meas_vector(y, snr, arrays, radio, "toa_doa")
    w = 1.0 / var
    p = np.asarray(p_init_m, float).copy()
    converged = False
    for _ in range(iters):
        h, H = _stack_meas(p, arrays, radio, "toa_doa")
        r = _innovation(z, h, "toa_doa", len(arrays))
        F = H.T @ (w[:, None] * H)
        step = np.linalg.lstsq(F, H.T @ (w * r), rcond=None)[0]
        n = np.linalg.norm(step)
        if n > max_step_m:  # a deep fade's reading can throw Gauss-Newton far off: damp the step
            step *= max_step_m / n
        p = p + step
        if n < 1e-7:
            converged = True
            break
    if not converged or np.linalg.norm(p - np.asarray(p_init_m, float)) > max_jump_m:
        return np.full(3, np.nan), np.full((3, 3), np.nan)  # no fix this slot (the caller keeps its last one)
    H = _stack_meas(p, arrays, radio, "toa_doa")[1]
    return p, np.linalg.pinv(H.T @ (w[:, None] * H))


def channel_draws(d_m, radio: Radio, rng: np.random.Generator) -> np.ndarray:
    """SNR (linear) for distances ``d_m``: log-normal shadowing (Table 1) times unit-power Rayleigh small-scale
    fading (Sec. 5)."""
    d = np.asarray(d_m, float)
    rx = radio.mean_rx_dbm(d) + rng.normal(0.0, 1.0, d.shape) * radio.shadowing_db(d)
    return radio.snr(rx) * rng.exponential(1.0, d.shape)


def measurement_information(p_m, arrays: list[Ura], radio: Radio, use: str, rng: np.random.Generator | None,
                            draws: int = 400, snr=None) -> np.ndarray:
    """``E{H^T Z^-1 H}`` (3 x 3, position block) at ``p_m``, the expectation over the channel by ``draws`` fading
    draws (Eq. 28: "the expectation with respect to the channel ... over Monte Carlo simulations"); with ``snr``
    (one per array) the information for that channel realisation instead."""
    idx = list(MEASUREMENTS[use])
    info = np.zeros((3, 3))
    if not idx:
        return info
    for i, a in enumerate(arrays):
        m = toa_doa(p_m, a.ref_m, radio.c_avg_mps)
        H = jacobian(p_m, a.ref_m, radio.c_avg_mps)[idx]
        d = np.linalg.norm(np.asarray(p_m, float) - np.asarray(a.ref_m, float))
        snr_i = channel_draws(np.full(draws, d), radio, rng) if snr is None else np.atleast_1d(float(snr[i]))
        if not np.all(np.isfinite(snr_i)):
            continue
        inv_var = 1.0 / radio.variances(m[1], m[2], snr_i, a)[:, idx]  # (draws, k)
        info += H.T @ (inv_var.mean(axis=0)[:, None] * H)
    return info


def pcrb(truth_m: np.ndarray, arrays: list[Ura], radio: Radio, sigma_acc: float, delta_s: float, use: str,
         rng: np.random.Generator | None, P0=None, imu: bool = True, draws: int = 400, snr=None) -> np.ndarray:
    """Algorithm 2: the position PCRB ``tr{J_p^-1}`` (m^2) at each of the ``K + 1`` true positions ``truth_m``.

    ``P0`` is the prior covariance of the initial state (6 x 6); ``None``: the initial state is known (the paper's
    capsule starts at the mouth, ``x0 = mu_x``). With ``imu=False`` (the RF-only scheme, no motion model) the
    bound is the per-slot Bayesian CRB ``tr{E{H^T Z^-1 H}^-1}``. With ``snr (K+1, n_arrays)`` (one run's channel)
    the bound conditional on that channel realisation: its mean over runs is a tighter bound than the paper's,
    which averages the information over the channel before inverting (Jensen). The recursion is Eq. 28 in covariance form,
    ``C_{k+1} = ((Q + A C_k A^T)^-1 + E{H^T Z^-1 H})^-1``, evaluated without inverting the rank-3 true ``Q``.
    """
    truth_m = np.asarray(truth_m, float)
    K1 = len(truth_m)
    out = np.zeros(K1)
    if not imu:
        for k in range(K1):
            info = measurement_information(truth_m[k], arrays, radio, use, rng, draws,
                                           None if snr is None else snr[k])
            out[k] = np.trace(np.linalg.pinv(info))
        return out
    A, _ = transition(delta_s)
    Q = q_discrete(sigma_acc, delta_s)
    C = np.zeros((6, 6)) if P0 is None else np.asarray(P0, float)
    out[0] = np.trace(C[:3, :3])
    for k in range(1, K1):
        Pp = A @ C @ A.T + Q
        info = measurement_information(truth_m[k], arrays, radio, use, rng, draws, None if snr is None else snr[k])
        w, V = np.linalg.eigh(info)
        L = V[:, w > 0] * np.sqrt(w[w > 0])  # info = L L^T (position block)
        if L.shape[1]:
            G = np.zeros((6, L.shape[1]))
            G[:3] = L
            S = np.eye(L.shape[1]) + G.T @ Pp @ G
            C = Pp - Pp @ G @ np.linalg.solve(S, G.T @ Pp)
        else:
            C = Pp
        C = 0.5 * (C + C.T)
        out[k] = np.trace(C[:3, :3])  # EFIM of Eq. 29 inverted = position block of the inverse FIM
    return out


# ------------------------------------------------------------------------------------ running on recorded data

from bodyslam.choices import SCHEMES  # noqa: E402  (the CLI reads the names from the light module)
SCHEME_USE = {"toa_doa_imu": "toa_doa", "doa_imu": "doa", "toa_imu": "toa", "imu_only": "none",
               "rf_only": "toa_doa", "rf_only_cv": "toa_doa"}


def run_scheme(name: str, x0, P0, y, snr, imu, arrays: list[Ura], radio: Radio, sigma_acc: float, delta_s: float,
               q_model: str = "eq15") -> tuple[np.ndarray, np.ndarray]:
    """One localization scheme over a recording: positions ``(K+1, 3)`` and their covariances ``(K+1, 3, 3)``.

    ``y (K+1, n_arrays, 3)`` and ``snr (K+1, n_arrays)`` per slot (NaN: no reading; row 0 is the start),
    ``imu (K, 3)`` the reading for each slot. Schemes: ``toa_doa_imu`` (Algorithm 1), ``doa_imu``, ``toa_imu``,
    ``imu_only``; ``rf_only_cv`` (Algorithm 1 without the IMU input: constant velocity); ``rf_only`` (each slot's
    fix alone, the last fix held through slots without one).
    """
    if name not in SCHEME_USE:
        raise ConfigError(f"unknown scheme {name!r}; expected one of {list(SCHEMES)}")
    x0, P0 = np.asarray(x0, float), np.asarray(P0, float)
    K1 = len(y)
    est, cov = np.empty((K1, 3)), np.empty((K1, 3, 3))
    est[0], cov[0] = x0[:3], P0[:3, :3]
    if name == "rf_only":
        p, c = x0[:3].copy(), P0[:3, :3].copy()
        for k in range(1, K1):
            q, qc = snapshot_fix(y[k], snr[k], arrays, radio, p)
            if np.all(np.isfinite(q)):
                p, c = q, qc
            est[k], cov[k] = p, c
        return est, cov
    ekf = HybridEkf(arrays, radio, x0, P0, sigma_acc, delta_s, use=SCHEME_USE[name], q_model=q_model)
    no_imu = name == "rf_only_cv"
    for k in range(1, K1):
        u = imu[k - 1]
        ekf.predict(np.zeros(3) if no_imu or not np.all(np.isfinite(u)) else u)
        ekf.update(y[k], snr[k])
        est[k], cov[k] = ekf.x[:3], ekf.P[:3, :3]
    return est, cov


def scheme_pcrb(name: str, truth_m: np.ndarray, arrays: list[Ura], radio: Radio, sigma_acc: float,
                delta_s: float, rng: np.random.Generator | None = None, draws: int = 400, snr=None) -> np.ndarray:
    """:func:`pcrb` for a scheme of :func:`run_scheme`: its RF channels, and the IMU's motion model unless it is
    an RF-only scheme (those get the per-slot bound; the constant-velocity filter has no IMU model to bound)."""
    if name not in SCHEME_USE:
        raise ConfigError(f"unknown scheme {name!r}; expected one of {list(SCHEMES)}")
    return pcrb(truth_m, arrays, radio, sigma_acc, delta_s, SCHEME_USE[name], rng, P0=None,
                imu=name not in ("rf_only", "rf_only_cv"), draws=draws, snr=snr)


MAX_RECORDING_S = 1e6  # readings stamped later than this (11 days) are malformed lines


def load_recording(seq_dir) -> dict:
    """A recording in the testbed's file layout (``meta.json`` with the arrays, radio, IMU noise and initial
    state; ``rf.csv``; ``imu.csv``) as the arrays :func:`run_scheme` takes. Malformed lines and unknown sensors
    are skipped and listed in ``problems`` as ``(file, line, reason)``; the slot's reading counts as lost."""
    from pathlib import Path

    from bodyslam.errors import InputError
    from bodyslam.io import csv_rows, read_json

    d = Path(seq_dir)
    meta = read_json(d / "meta.json")
    try:
        arrays = [Ura(str(a["name"]), tuple(float(v) for v in a["ref_m"]), int(a["n_x"]), int(a["n_z"]),
                      float(a["dx_m"]), float(a["dz_m"])) for a in meta["arrays"]]
        for a in arrays:  # an array's place and geometry enter every measurement model: refuse them here
            if len(a.ref_m) != 3 or not all(math.isfinite(v) for v in a.ref_m):
                raise ValueError(f"array {a.name!r}: ref_m needs 3 finite numbers, got {len(a.ref_m)}")
            if a.n_x < 2 or a.n_z < 2 or not (math.isfinite(a.dx_m) and a.dx_m > 0
                                              and math.isfinite(a.dz_m) and a.dz_m > 0):
                raise ValueError(f"array {a.name!r}: needs n_x, n_z >= 2 and positive, finite dx_m, dz_m")
        radio = Radio(**{k: float(v) for k, v in meta["radio"].items()})
        if not all(math.isfinite(v) for v in (radio.pt_dbm, radio.n0_dbm_hz)) or not all(
                math.isfinite(v) and v > 0 for v in (radio.fc_hz, radio.beta_hz, radio.c_avg_mps)):
            raise ValueError("radio: finite pt_dbm and n0_dbm_hz, positive finite fc_hz, beta_hz and c_avg_mps")
        sigma = float(meta["imu"]["sigma_acc_mps2"])
        delta = float(meta["interval_s"])
        init = meta["initial_state"]
        x0 = np.concatenate([np.asarray(init["position_m"], float), np.asarray(init["velocity_mps"], float)])
        P0 = np.asarray(init["covariance"], float).reshape(6, 6)
        if not (math.isfinite(delta) and delta > 0 and math.isfinite(sigma) and sigma >= 0):
            raise ValueError("interval_s must be positive and imu.sigma_acc_mps2 >= 0")
        if x0.shape != (6,) or not (np.all(np.isfinite(x0)) and np.all(np.isfinite(P0))):
            raise ValueError("initial_state: position_m and velocity_mps need 3 numbers each, covariance 6 x 6 numbers")
        # a covariance: symmetric and positive definite (one that is not made the filter's first solve singular)
        if not np.allclose(P0, P0.T, rtol=1e-6, atol=0.0) or np.any(np.linalg.eigvalsh(0.5 * (P0 + P0.T)) <= 0):
            raise ValueError("initial_state.covariance must be symmetric and positive definite")
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"{d / 'meta.json'}: not a TOA/DOA + IMU recording ({exc!r} missing or malformed)") from None
    names = {a.name: i for i, a in enumerate(arrays)}
    rows, problems = [], []
    with csv_rows(d / "rf.csv", ["t", "sensor", "toa_s", "azimuth_rad", "elevation_rad", "snr_db"]) as lines:
        for ln, r in lines:
            try:
                vals = [float(r[c]) for c in ("t", "toa_s", "azimuth_rad", "elevation_rad", "snr_db")]
                if not all(math.isfinite(v) for v in vals):
                    raise ValueError("non-finite value")
                if not 0.0 <= vals[0] <= MAX_RECORDING_S:
                    raise ValueError(f"time {vals[0]:g} s outside 0-{MAX_RECORDING_S:g} s")
                if not -100.0 <= vals[4] <= 200.0:
                    raise ValueError(f"snr_db {vals[4]:g} outside -100-200 dB")
            except (TypeError, ValueError) as exc:
                problems.append(("rf.csv", ln, f"malformed line ({exc})"))
                continue
            if r["sensor"] not in names:
                problems.append(("rf.csv", ln, f"unknown sensor {r['sensor']!r}"))
                continue
            rows.append((vals[0], names[r["sensor"]], vals[1:]))
    imu_rows = []
    with csv_rows(d / "imu.csv", ["t", "ax_mps2", "ay_mps2", "az_mps2"]) as lines:
        for ln, r in lines:
            try:
                v = [float(r[c]) for c in ("t", "ax_mps2", "ay_mps2", "az_mps2")]
                if not all(math.isfinite(x) for x in v):
                    raise ValueError("non-finite value")
                if not 0.0 <= v[0] <= MAX_RECORDING_S:
                    raise ValueError(f"time {v[0]:g} s outside 0-{MAX_RECORDING_S:g} s")
                imu_rows.append(v)
            except (TypeError, ValueError) as exc:
                problems.append(("imu.csv", ln, f"malformed line ({exc})"))
    t_end = max([r[0] for r in rows] + [r[0] + delta for r in imu_rows] + [0.0])
    K = int(round(t_end / delta))
    y = np.full((K + 1, len(arrays), 3), np.nan)
    snr = np.full((K + 1, len(arrays)), np.nan)
    for t, i, (toa, az, el, snr_db) in rows:
        k = int(round(t / delta))
        if 1 <= k <= K:
            y[k, i] = (toa, az, el)
            snr[k, i] = 10.0 ** (snr_db / 10.0)
    imu = np.full((K, 3), np.nan)
    for t, *a in imu_rows:
        k = int(round(t / delta))
        if 0 <= k < K:
            imu[k] = a
    missing = np.flatnonzero(~np.all(np.isfinite(imu), axis=1))
    if K and len(missing) == K:  # an IMU that gave nothing: one line, not one per slot
        problems.append(("imu.csv", "-", f"no reading at all: every one of the {K} slots predicted without one"))
        missing = missing[:0]
    for a, b in runs_of(missing):  # each run of slots without a reading once (a long gap was a line per slot)
        when = f"t = {a * delta:g} s" if a == b else f"t = {a * delta:g}-{b * delta:g} s ({b - a + 1} slots)"
        problems.append(("imu.csv", "-", f"no reading for the slot at {when} (predicted without one)"))
    return {"arrays": arrays, "radio": radio, "sigma_acc": sigma, "delta_s": delta, "x0": x0, "P0": P0,
            "t": np.arange(K + 1) * delta, "y": y, "snr": snr, "imu": imu, "problems": problems}

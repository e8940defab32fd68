"""Particle-filter RF tracking of a capsule (papers 002 and 003: Ito, Anzai and Wang) and the waypoint method
for moving distance and heading (paper 003).

Measurement models (shared with the testbed's emulation, like :class:`bodyslam.fusion.rf.PathLossModel`):

- UWB TOA through tissue of average relative permittivity ``eps_r`` (002 Eq. 6, 17): ``tau = sqrt(eps_r) d / c``,
  Gaussian sampling error ``sigma_s`` (Eq. 16).
- UWB electric field (002 Eq. 9): ``E / E0 = (A / d) exp(-alpha(eps_r) d)`` with ``alpha`` the attenuation
  constant of a lossy dielectric. Eq. 10 as printed, ``omega sqrt(mu0 eps0 eps_r) Im[1 - j sigma/(omega eps0
  eps_r)]``, lacks a square root: the attenuation constant is ``omega sqrt(mu0 eps0 eps_r) |Im sqrt(1 - j
  sigma/(omega eps0 eps_r))|`` (69.2 Np/m for 2.17 S/m, eps_r 34.25 at 4.1 GHz; the printed form gives 139.7,
  negative). Eq. 11, the inverse used to estimate the permittivity from the field, is exact for the corrected
  Eq. 10 (``eps_r = (sigma^2 omega^2 mu0^2 - 4 alpha^4) / (4 eps0 omega^2 mu0 alpha^2)``), which confirms it.
- The permittivity estimated from each receiver's field is log-normal about the true one (002 Eq. 18, sigma_e =
  1.23 from the paper's FDTD study). Eq. 18 as printed subtracts the particle's permittivity from a logarithm,
  ``(log eps_m - eps_i)``; the log-normal it describes has ``log eps_i`` there, which is used.
- MICS RSSI (003 Eq. 3-4, Anzai 2012): ``P(dB) = 10 log10(alpha d^-n)`` with log-normal shadowing, alpha =
  10^-7.5, n = 6.65, sigma = 5.50 dB (003 writes ``log``; with sigma in dB the model is in decibels).

Filter (002 Sec. 3.2, 003 Sec. 2.2), vectorised over particles: each particle has a position, a destination, a
speed and a remaining stop time (random waypoint motion: move straight to the destination at its speed; on arrival
stop for U(0, 20) s, then draw a new destination), and, for TOA with unknown permittivity, its own ``eps_r``
(one averaged value per particle: 002 says "for each receiver", but with an independent permittivity per receiver
the TOA ranges have no common scale and only Eq. 18's very broad likelihood would constrain them; the paper's
title and Sec. 3.1 estimate *the* averaged permittivity). Weights multiply by the likelihoods (Eq. 13-14);
systematic resampling when the effective sample size falls below ``resample_threshold`` x N, the copies spread by
a kernel sized to the cloud (regularised PF; 002 Sec. 3.2.3 adds "a little variation" to them). Estimate: the weighted mean (Eq. 19).
Destinations are drawn uniformly within ``leg_max_m`` of the particle, inside the analysis area: the filter does
not know the intestine's shape (the papers do not say what the particles' destinations are).

Units: metres, seconds, dB; ``rng`` arguments take a seed or a ``numpy.random.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from bodyslam.errors import ConfigError

__all__ = ["C_MPS", "attenuation_np_per_m", "field_ratio", "permittivity_from_field", "MicsRssiModel",
           "RandomWaypoint", "ParticleFilter", "loglik_toa", "loglik_permittivity", "waypoint_distance",
           "simple_distance", "TRACKERS", "TrackSettings", "Track", "track", "converged_from"]

C_MPS = 299_792_458.0
MU0 = 4e-7 * math.pi
EPS0 = 8.8541878128e-12


def attenuation_np_per_m(eps_r, sigma_s_per_m: float, freq_hz: float):
    """Attenuation constant (Np/m) of a lossy dielectric: 002 Eq. 10 with its square root restored."""
    w = 2 * math.pi * freq_hz
    eps_r = np.asarray(eps_r, float)
    x = sigma_s_per_m / (w * EPS0 * eps_r)
    return w * np.sqrt(MU0 * EPS0 * eps_r) * np.abs(np.imag(np.sqrt(1 - 1j * x)))


def field_ratio(d_m, eps_r, sigma_s_per_m: float, freq_hz: float, A: float = 1.0):
    """``E / E0`` at distance ``d_m`` (002 Eq. 9)."""
    d_m = np.asarray(d_m, float)
    return A / d_m * np.exp(-attenuation_np_per_m(eps_r, sigma_s_per_m, freq_hz) * d_m)


def permittivity_from_field(E_over_E0, d_m, sigma_s_per_m: float, freq_hz: float, A: float = 1.0):
    """Average relative permittivity from the received field (002 Eq. 11); NaN where no permittivity >= 1 fits
    (the field is stronger than any lossy tissue allows)."""
    w = 2 * math.pi * freq_hz
    d_m = np.asarray(d_m, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.log(np.asarray(E_over_E0, float) * d_m) - math.log(A)  # = -alpha d (Eq. 12)
        eps = (sigma_s_per_m**2 * w**2 * MU0**2 * d_m**4 - 4 * L**4) / (4 * EPS0 * w**2 * MU0 * d_m**2 * L**2)
    return np.where(np.isfinite(eps) & (eps >= 1.0) & (L < 0), eps, np.nan)


@dataclass(frozen=True)
class MicsRssiModel:
    """003 Eq. 3-4: mean RSSI ``10 log10(alpha) - 10 n log10(d)`` dB, log-normal shadowing ``sigma_db``."""

    log10_alpha: float = -7.5
    n: float = 6.65
    sigma_db: float = 5.50

    def mean_db(self, d_m):
        return 10.0 * self.log10_alpha - 10.0 * self.n * np.log10(np.maximum(np.asarray(d_m, float), 1e-4))

    def loglik(self, pos_m: np.ndarray, rssi_db: np.ndarray, rx_m: np.ndarray) -> np.ndarray:
        """Log-likelihood per particle ``(N,)`` of readings ``(M,)`` (NaN = missing) at receivers ``(M, 3)``."""
        ok = np.isfinite(rssi_db)
        d2 = np.maximum(_dist2(pos_m, rx_m[ok]), 1e-8)
        # mean in dB = 10 log10(alpha) - 5 n log10(d^2): no square root needed
        r = (rssi_db[ok][None, :] - 10.0 * self.log10_alpha + 5.0 * self.n * np.log10(d2)) / self.sigma_db
        return -0.5 * np.einsum("ij,ij->i", r, r)


def _dist2(pos_m: np.ndarray, rx_m: np.ndarray) -> np.ndarray:
    """Squared distances ``(N, M)`` by one matrix product (3x faster than broadcasting over (N, M, 3))."""
    d2 = (pos_m * pos_m).sum(axis=1)[:, None] + (rx_m * rx_m).sum(axis=1)[None, :] - 2.0 * (pos_m @ rx_m.T)
    return np.maximum(d2, 0.0)


def loglik_toa(pos_m: np.ndarray, eps_r: np.ndarray, toa_s: np.ndarray, rx_m: np.ndarray,
               sigma_s: float) -> np.ndarray:
    """002 Eq. 16-17 per particle: TOA ``(M,)`` (NaN = missing), particle permittivities ``(N,)``."""
    ok = np.isfinite(toa_s)
    d = np.sqrt(_dist2(pos_m, rx_m[ok]))
    eps_r = np.asarray(eps_r, float)
    k = np.sqrt(eps_r)[:, None] / C_MPS if eps_r.ndim else math.sqrt(float(eps_r)) / C_MPS
    r = (toa_s[ok][None, :] - k * d) / sigma_s
    return -0.5 * np.einsum("ij,ij->i", r, r)


def loglik_permittivity(log_eps_r: np.ndarray, eps_obs: np.ndarray, sigma_e: float) -> np.ndarray:
    """002 Eq. 18 per particle (with ``log eps_i``): the receivers' permittivity estimates ``(M,)``; the
    particles' permittivities are given as logarithms ``(N,)``. Up to a constant: ``-0.5 sum_m (log eps_m -
    log eps_i)^2 / sigma_e^2`` expands into a quadratic in ``log eps_i`` (no (N, M) array)."""
    lo = np.log(eps_obs[np.isfinite(eps_obs)])
    if lo.size == 0:
        return np.zeros(len(log_eps_r))
    x = np.asarray(log_eps_r, float)
    return -0.5 * (lo.size * x * x - 2.0 * lo.sum() * x) / sigma_e**2


@dataclass(frozen=True)
class RandomWaypoint:
    """The particles' motion model (002 Sec. 3.2.1, 003 Sec. 2.2, Table 1): speed N(0.05 cm/s, 0.005 (cm/s)^2)
    per leg (kept >= 0), stops of U(0, 20) s at each destination."""

    speed_mean_mps: float = 5e-4
    speed_sd_mps: float = math.sqrt(5e-7)
    stop_max_s: float = 20.0
    leg_max_m: float = 0.03


class ParticleFilter:
    """Random-waypoint particle filter over positions (and optionally one permittivity per particle).

    Parameters
    ----------
    n : number of particles.
    area_min_m, area_max_m : (3,) corners of the analysis area (particles start uniform in it, stay inside).
    motion : RandomWaypoint.
    eps_range : ``(lo, hi)`` to estimate the permittivity (particles start log-uniform in it); None: no
        permittivity state.
    resample_threshold : resample when ESS < threshold x n (002 Fig. 6: 0.06; 003 Table 1: 0.7).
    jitter_m, jitter_log_eps : standard deviations added to resampled copies.
    """

    def __init__(self, n: int, area_min_m, area_max_m, motion: RandomWaypoint = RandomWaypoint(),
                 eps_range: tuple[float, float] | None = None, resample_threshold: float = 0.06,
                 jitter_m: float = 2e-4, jitter_log_eps: float = 0.005, rng=None):
        if n < 2:
            raise ConfigError(f"a particle filter needs at least 2 particles, got {n}")
        if not 0 < resample_threshold <= 1:
            raise ConfigError(f"resample_threshold must be in (0, 1], got {resample_threshold}")
        self.rng = np.random.default_rng(rng)
        self.lo = np.asarray(area_min_m, float)
        self.hi = np.asarray(area_max_m, float)
        if self.lo.shape != (3,) or self.hi.shape != (3,) or np.any(self.hi <= self.lo):
            raise ConfigError("area_min_m/area_max_m must be (3,) with min < max")
        self.n = int(n)
        self.motion = motion
        self.resample_threshold = float(resample_threshold)
        self.jitter_m = float(jitter_m)
        self.jitter_log_eps = float(jitter_log_eps)
        self.pos = self.rng.uniform(self.lo, self.hi, (n, 3))
        self.dest = self._draw_dest(self.pos)
        self.speed = self._draw_speed(n)
        self.stop_left = np.zeros(n)
        self.log_eps = None  # permittivity state, as logarithms (it is positive and multiplicative)
        if eps_range is not None:
            lo, hi = eps_range
            self.log_eps = self.rng.uniform(math.log(lo), math.log(hi), n)
        self.w = np.full(n, 1.0 / n)
        self.n_resampled = 0

    # -- model -------------------------------------------------------------------------------------------------
    def _draw_dest(self, pos: np.ndarray) -> np.ndarray:
        step = self.rng.uniform(-1.0, 1.0, pos.shape) * self.motion.leg_max_m
        return np.clip(pos + step, self.lo, self.hi)

    def _draw_speed(self, n: int) -> np.ndarray:
        return np.abs(self.rng.normal(self.motion.speed_mean_mps, self.motion.speed_sd_mps, n))

    def predict(self, dt_s: float) -> None:
        """Move every particle by ``dt_s`` of its random-waypoint motion."""
        moving = self.stop_left <= 0
        np.maximum(self.stop_left - dt_s, 0.0, out=self.stop_left)
        to = self.dest - self.pos
        dist = np.sqrt(np.einsum("ij,ij->i", to, to))
        step = self.speed * dt_s
        arrive = moving & (step >= dist)
        frac = np.where(moving, np.minimum(step / np.maximum(dist, 1e-15), 1.0), 0.0)
        self.pos += to * frac[:, None]
        if arrive.any():  # stop, then a new leg
            k = int(arrive.sum())
            self.stop_left[arrive] = self.rng.uniform(0.0, self.motion.stop_max_s, k)
            self.dest[arrive] = self._draw_dest(self.pos[arrive])
            self.speed[arrive] = self._draw_speed(k)

    @property
    def eps(self) -> np.ndarray | None:
        return None if self.log_eps is None else np.exp(self.log_eps)

    def update(self, loglik: np.ndarray) -> None:
        """Multiply the weights by the likelihoods (Eq. 13-14), then resample if degenerate."""
        ll = np.asarray(loglik, float)
        if ll.shape != (self.n,):
            raise ConfigError(f"loglik must have shape ({self.n},), got {ll.shape}")
        m = ll.max()
        if not np.isfinite(m):  # no particle explains the reading: keep the prior weights (an outlier)
            return
        w = self.w * np.exp(ll - m)
        sw = w.sum()
        if not sw > 0:  # the likelihood's peak missed every weighted particle: redo it in logs
            lw = np.log(np.maximum(self.w, 1e-300)) + ll
            w = np.exp(lw - lw.max())
            sw = w.sum()
        w /= sw
        self.w = w
        if 1.0 / np.dot(w, w) < self.resample_threshold * self.n:  # effective sample size
            self._resample()

    def _resample(self) -> None:
        """Systematic resampling, then the copies are spread by a Gaussian kernel of the weighted cloud's own
        covariance scaled by Silverman's bandwidth (a regularised particle filter), plus the fixed floors
        ``jitter_m`` / ``jitter_log_eps``. Without the kernel a peaked likelihood (TOA: 3 mm per range) leaves
        only the few initial particles nearest the truth, and the cloud can never move off them (measured: 8 mm
        stuck on a stopped capsule, 4000 particles)."""
        X = self.pos if self.log_eps is None else np.c_[self.pos, self.log_eps]
        mu = self.w @ X
        D = X - mu
        C = (D * self.w[:, None]).T @ D
        dim = X.shape[1]
        h = (4.0 / (self.n * (dim + 2))) ** (1.0 / (dim + 4))
        try:
            L = np.linalg.cholesky(C * h * h + 1e-18 * np.eye(dim))
        except np.linalg.LinAlgError:
            L = np.zeros((dim, dim))
        u = (self.rng.random() + np.arange(self.n)) / self.n  # systematic
        idx = np.minimum(np.searchsorted(np.cumsum(self.w), u), self.n - 1)
        kick = self.rng.standard_normal((self.n, dim)) @ L.T
        self.pos = np.clip(self.pos[idx] + kick[:, :3] + self.rng.normal(0, self.jitter_m, (self.n, 3)),
                           self.lo, self.hi)
        self.dest, self.speed, self.stop_left = self.dest[idx], self.speed[idx], self.stop_left[idx]
        if self.log_eps is not None:
            self.log_eps = self.log_eps[idx] + kick[:, 3] + self.rng.normal(0, self.jitter_log_eps, self.n)
        self.w = np.full(self.n, 1.0 / self.n)
        self.n_resampled += 1

    # -- estimates ---------------------------------------------------------------------------------------------
    @property
    def weights(self) -> np.ndarray:
        return self.w

    def estimate(self) -> np.ndarray:
        """Weighted mean position (Eq. 19)."""
        return self.w @ self.pos

    def covariance(self) -> np.ndarray:
        """Weighted covariance of the particle positions (3x3)."""
        d = self.pos - self.w @ self.pos
        return (d * self.w[:, None]).T @ d

    def estimate_log_eps(self) -> float:
        """Weighted mean of log permittivity (its exponential: the geometric mean permittivity)."""
        if self.log_eps is None:
            raise ConfigError("this filter does not estimate the permittivity")
        return float(self.w @ self.log_eps)


def simple_distance(est_m: np.ndarray) -> np.ndarray:
    """003 Eq. 5: moving distance as the sum of the estimated positions' increments, per time step."""
    est_m = np.asarray(est_m, float)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(est_m, axis=0), axis=1))])


def converged_from(spread_m: np.ndarray, threshold_m: float) -> int:
    """The first step whose particle-cloud spread is below ``threshold_m`` (the filter has found the capsule);
    the last step when it never is."""
    below = np.flatnonzero(np.asarray(spread_m) < threshold_m)
    return int(below[0]) if len(below) else max(len(spread_m) - 1, 0)


def waypoint_distance(est_m: np.ndarray, S: int = 20, r_thr_m: float = 0.003,
                      p_thr_m: float = 0.03) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """003 Sec. 3.2-3.3: moving distance from waypoints detected in the estimated track, and headings.

    A step is *stopped* when the means of the first and second halves of the last ``S`` estimates are closer than
    ``r_thr_m`` (Eq. 6-7); a stopped estimate farther than ``p_thr_m`` from the last waypoint becomes the next
    waypoint. Distance (Eq. 8): the path through the waypoints plus the way from the last one to the estimate.

    Returns ``(distance_m (T,), waypoints (K, 3), headings_rad (K-1, 2))`` with headings ``(theta, phi)`` per
    leg (Eq. 9-10: azimuth in the x-z plane, elevation toward y).
    """
    est_m = np.asarray(est_m, float)
    T = len(est_m)
    if T == 0:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2))
    q = [est_m[0]]
    path = 0.0
    out = np.zeros(T)
    half = max(S // 2, 1)
    csum = np.vstack([np.zeros(3), np.cumsum(est_m, axis=0)])
    for n in range(T):
        if n + 1 >= S:
            a = n + 1 - S
            r1 = (csum[a + half] - csum[a]) / half
            r2 = (csum[n + 1] - csum[a + half]) / (S - half)
            if np.linalg.norm(r1 - r2) < r_thr_m and np.linalg.norm(est_m[n] - q[-1]) > p_thr_m:
                path += float(np.linalg.norm(est_m[n] - q[-1]))
                q.append(est_m[n].copy())
        out[n] = path + float(np.linalg.norm(est_m[n] - q[-1]))
    Q = np.array(q)
    d = np.diff(Q, axis=0)
    heads = np.c_[np.arctan2(d[:, 2], d[:, 0]), np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))]
    return out, Q, heads


# ------------------------------------------------------------------------------------ running on recorded data

from bodyslam.choices import TRACKERS  # noqa: E402


@dataclass(frozen=True)
class TrackSettings:
    """Everything a tracker needs besides the readings (002 Table 3 / 003 Table 1 defaults; the scenario files
    ``ito2016``/``ito_heading`` carry the evaluated values)."""

    particles: int = 20000
    motion: RandomWaypoint = RandomWaypoint()
    resample_threshold: float = 0.5
    jitter_m: float = 5e-4          # TOA filters' resampling jitter floor
    rssi_jitter_m: float = 1e-3     # the RSSI filter's
    jitter_log_eps: float = 0.005
    eps_range: tuple[float, float] = (15.0, 70.0)
    eps_known: float = 34.25        # ``toa_pf_true_eps``: the tissue's permittivity, known
    sigma_toa_s: float = 62.5e-12
    sigma_s_per_m: float = 2.17
    freq_hz: float = 4.1e9
    sigma_e: float = 1.23
    mics: MicsRssiModel = MicsRssiModel()

    @classmethod
    def from_tables(cls, uwb: dict, mics: dict, filter_: dict | None = None, motion: dict | None = None,
                    **overrides) -> "TrackSettings":
        """From the ``uwb``/``mics`` model tables (a recording's ``meta.json`` or a scenario) and, optionally, the
        ``filter`` and ``motion`` tables of a scenario; ``overrides`` win over all of them."""
        flt, mot, d = filter_ or {}, motion or {}, cls()
        kw = dict(
            particles=int(flt.get("particles", d.particles)),
            motion=RandomWaypoint(float(mot.get("speed_mean_mps", d.motion.speed_mean_mps)),
                                  math.sqrt(float(mot["speed_var_m2ps2"])) if "speed_var_m2ps2" in mot
                                  else d.motion.speed_sd_mps,
                                  float(mot.get("stop_max_s", d.motion.stop_max_s)),
                                  float(flt.get("leg_max_m", d.motion.leg_max_m))),
            resample_threshold=float(flt.get("resample_threshold", d.resample_threshold)),
            jitter_m=float(flt.get("jitter_m", d.jitter_m)), rssi_jitter_m=float(flt.get("rssi_jitter_m", d.rssi_jitter_m)),
            jitter_log_eps=float(flt.get("jitter_log_eps", d.jitter_log_eps)),
            eps_range=tuple(flt.get("eps_range", d.eps_range)), eps_known=float(uwb.get("eps_r", d.eps_known)),
            sigma_toa_s=float(uwb.get("sigma_toa_s", d.sigma_toa_s)),
            sigma_s_per_m=float(uwb.get("sigma_s_per_m", d.sigma_s_per_m)), freq_hz=float(uwb.get("freq_hz", d.freq_hz)),
            sigma_e=float(uwb.get("sigma_e", d.sigma_e)),
            mics=MicsRssiModel(float(mics.get("log10_alpha", d.mics.log10_alpha)), float(mics.get("n", d.mics.n)),
                               float(mics.get("sigma_db", d.mics.sigma_db))))
        kw.update(overrides)
        return cls(**kw)


class Track(NamedTuple):
    """A tracker's output per step: weighted-mean positions ``(T, 3)`` (m), the permittivity estimate ``(T,)``
    (``toa_rssi_pf`` only, else None) and the particle cloud's RMS spread ``(T,)`` (m, sqrt of the covariance's
    trace: how far from converged the filter is)."""

    positions_m: np.ndarray
    eps_r: np.ndarray | None
    spread_m: np.ndarray


def track(name: str, t_s: np.ndarray, rx_m: np.ndarray, readings: dict[str, np.ndarray], area_min_m, area_max_m,
          settings: TrackSettings = TrackSettings(), rng=None, progress=None) -> Track:
    """One particle-filter tracker over a recording (see :class:`Track`).

    ``readings`` holds ``(T, M)`` arrays (NaN: no reading) for the receivers ``rx_m (M, 3)``: ``toa_s`` and
    ``uwb_field_db`` (``20 log10(E / E0)``) for the TOA trackers, ``rss_db`` for ``rssi_pf``. Trackers:
    ``toa_rssi_pf`` (002: TOA with the permittivity estimated from the UWB field), ``toa_pf_true_eps`` (002's
    reference: TOA with ``settings.eps_known``), ``rssi_pf`` (003: MICS RSSI). ``progress(done, total)`` is called
    every 100 steps.
    """
    if name not in TRACKERS:
        raise ConfigError(f"unknown RF tracking algorithm {name!r} (known: {', '.join(TRACKERS)})")
    need = {"toa_rssi_pf": ("toa_s", "uwb_field_db"), "toa_pf_true_eps": ("toa_s",), "rssi_pf": ("rss_db",)}[name]
    missing = [k for k in need if k not in readings]
    if missing:
        raise ConfigError(f"{name} needs the readings {', '.join(missing)}")
    st = settings
    kw = dict(motion=st.motion, resample_threshold=st.resample_threshold,
              jitter_m=st.rssi_jitter_m if name == "rssi_pf" else st.jitter_m, jitter_log_eps=st.jitter_log_eps,
              rng=rng)
    pf = ParticleFilter(st.particles, area_min_m, area_max_m,
                        eps_range=st.eps_range if name == "toa_rssi_pf" else None, **kw)
    t_s = np.asarray(t_s, float)
    est = np.zeros((len(t_s), 3))
    spread = np.zeros(len(t_s))
    eps_est = np.zeros(len(t_s)) if pf.log_eps is not None else None
    for k in range(len(t_s)):
        if k:
            pf.predict(float(t_s[k] - t_s[k - 1]))
        if name == "rssi_pf":
            ll = st.mics.loglik(pf.pos, readings["rss_db"][k], rx_m)
        elif name == "toa_pf_true_eps":
            ll = loglik_toa(pf.pos, st.eps_known, readings["toa_s"][k], rx_m, st.sigma_toa_s)
        else:
            # Eq. 11 needs each receiver's distance: the TOA range with the filter's current permittivity
            d_rng = readings["toa_s"][k] * C_MPS / math.exp(0.5 * pf.estimate_log_eps())
            eps_obs = permittivity_from_field(10 ** (readings["uwb_field_db"][k] / 20.0), np.maximum(d_rng, 1e-3),
                                              st.sigma_s_per_m, st.freq_hz)
            ll = loglik_toa(pf.pos, np.exp(pf.log_eps), readings["toa_s"][k], rx_m, st.sigma_toa_s) + \
                loglik_permittivity(pf.log_eps, eps_obs, st.sigma_e)
        pf.update(ll)
        est[k] = pf.estimate()
        spread[k] = math.sqrt(max(float(np.trace(pf.covariance())), 0.0))
        if eps_est is not None:
            eps_est[k] = math.exp(pf.estimate_log_eps())
        if progress is not None and (k % 100 == 99 or k == len(t_s) - 1):
            progress(k + 1, len(t_s))
    return Track(est, eps_est, spread)

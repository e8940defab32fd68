"""RF localization of the capsule from body-mounted sensors (dissertation Sec. 2.3.3, 3.3.3).

Measurement model (shared with the testbed's emulation): :class:`PathLossModel`, Eq. 2.1 / 3.34 with the NIST
MICS parameters of Table 2.2 (deep tissue / near surface).

Estimators, each returning a position with its 3x3 covariance (:class:`Fix`):

- :func:`locate_lls`: ranges from RSS by Eq. 3.35 (``d = d0 10^((PL - PL(d0)) / (10 alpha))``, with the
  deep-tissue parameters: the depth is unknown before the position is), then the linearised least squares of
  Eq. 2.6-2.12, referenced to the sensor with the strongest signal (the printed form references sensor 1; any
  reference gives the same equations, the nearest one the best conditioned). Covariance from first-order
  propagation of the range errors (log-normal: ``sigma_d = d ln(10) sigma_dB / (10 alpha)``).
- :func:`locate_nls`: Eq. 3.36 minimised by Gauss-Newton (robust soft-L1 loss), residual
  ``|x - s_i| - d_i`` weighted by ``1 / sigma_d``. Eq. 3.36 as printed subtracts ``d_i^2`` from a distance, a
  typo (units of m and m^2); the residual here is the distance minus the range.
- :func:`locate_ml`: maximum likelihood on the RSS itself: log-normal shadowing makes the RSS Gaussian in dB, so
  ML minimises ``sum ((RSS_i - mean_i(x)) / sigma_i)^2`` with the deep / near-surface switch evaluated at ``x``
  (Sec. 2.3.3.2's idea with Eq. 2.1 as the mean model instead of Eq. 2.14's ``C / m^2``). Covariance: inverse
  Fisher information.

Missing sensors (NaN readings) are dropped; outliers are damped by the robust loss and, for ML, gated at
``gate_sigma`` standard deviations after a first fit.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import numpy as np
from scipy.optimize import least_squares

from bodyslam.errors import InputError
from bodyslam.io import csv_rows

__all__ = ["PathLossModel", "Fix", "read_sensors", "read_rf", "read_rf_columns", "rss_per_frame", "rss_to_range",
           "locate_lls", "locate_nls", "locate_ml", "RF_METHODS"]

RF_METHODS = ("lls", "nls", "ml")


@dataclass(frozen=True)
class PathLossModel:
    """Eq. 2.1 with Table 2.2 (NIST, MICS band). Powers in dBm/dB, distances in metres."""

    pt_dbm: float = -16.0  # 25 uW EIRP, the MICS limit (the dissertation gives no Pt)
    d0_m: float = 0.05
    deep: tuple[float, float, float] = (47.14, 4.26, 7.85)  # PL(d0) dB, alpha, sigma dB
    near: tuple[float, float, float] = (49.81, 4.22, 6.81)
    near_surface_depth_m: float = 0.10  # assumption: the switch depth (the dissertation does not state it)

    def params(self, depth_m):
        """``(PL(d0), alpha, sigma)`` for capsule depths below the sensors' surfaces."""
        near = np.asarray(depth_m) < self.near_surface_depth_m
        p = np.where(near[..., None], np.array(self.near), np.array(self.deep))
        return p[..., 0], p[..., 1], p[..., 2]

    def mean_rss_dbm(self, d_m, depth_m):
        pl0, alpha, _ = self.params(depth_m)
        return self.pt_dbm - pl0 - 10.0 * alpha * np.log10(np.maximum(d_m, 1e-4) / self.d0_m)

    def predict(self, p_w_m: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray):
        """At capsule position ``p``: mean RSS (n,) dBm, its 1-sigma (n,) dB and gradient d(mean)/dp (n, 3)
        dB/m, with the deep / near-surface switch by the depth below each sensor's surface."""
        diff = sensors_w_m - p_w_m
        d = np.linalg.norm(diff, axis=1)
        depth = np.maximum(np.einsum("ij,ij->i", diff, normals_w), 0.0)
        _, alpha, sigma = self.params(depth)
        # d(mean)/dp = -10 alpha / ln10 * d(ln d)/dp = +10 alpha / ln10 * (s - p) / d^2
        grad = (10.0 * alpha / np.log(10.0))[:, None] * diff / (d**2)[:, None]
        return self.mean_rss_dbm(d, depth), sigma, grad

    @classmethod
    def from_dict(cls, d: dict) -> "PathLossModel":
        if not isinstance(d, dict):
            raise InputError(f"path-loss model must be an object, got {d!r}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"path-loss model: unknown field(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        out = {}
        for k, v in d.items():
            n = 3 if k in ("deep", "near") else 1
            vals = v if isinstance(v, (list, tuple)) else [v]
            if len(vals) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                         and math.isfinite(x) for x in vals):
                raise InputError(f"path-loss model: {k} must be {'3 numbers' if n == 3 else 'a number'}, got {v!r}")
            out[k] = tuple(float(x) for x in vals) if n == 3 else float(vals[0])
        if out.get("d0_m", cls.d0_m) <= 0:
            raise InputError(f"path-loss model: d0_m must be positive, got {out['d0_m']!r}")
        return cls(**out)


@dataclass(frozen=True)
class Fix:
    position_w_m: np.ndarray  # (3,), NaN when no fix
    cov_m2: np.ndarray  # (3, 3)
    n_sensors: int
    status: str = "ok"  # ok | too_few_sensors | failed


def _no_fix(n: int, status: str) -> Fix:
    return Fix(np.full(3, np.nan), np.full((3, 3), np.nan), n, status)


def read_sensors(path: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """``sensors.csv`` (``sensor,x,y,z[,nx,ny,nz]``): names, positions (n, 3), outward normals (n, 3)."""
    names, pos, nrm = [], [], []
    with csv_rows(path, ("sensor", "x", "y", "z")) as lines:
        for i, r in lines:
            try:
                p = [float(r["x"]), float(r["y"]), float(r["z"])]
                n = [float(r[k]) for k in ("nx", "ny", "nz")] if r.get("nx") not in (None, "") else None
            except (TypeError, ValueError):
                raise InputError(f"{path}:{i}: not a number in {r}") from None
            if r["sensor"] in names:
                raise InputError(f"{path}:{i}: sensor {r['sensor']!r} listed twice")
            names.append(r["sensor"])
            pos.append(p)
            nrm.append(n if n is not None else list(np.asarray(p) / max(float(np.linalg.norm(p)), 1e-9)))
    if not names:
        raise InputError(f"{path}: no sensors")
    nrm = np.array(nrm, float)
    return tuple(names), np.array(pos, float), nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def read_rf(path: str | os.PathLike, sensor_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``rf.csv`` (long format) -> ``(stamps (T,), rss_dbm (T, n) NaN where missing, problems)``.

    Malformed lines and unknown sensors are skipped and reported (``file:line: reason``), never fatal.
    """
    stamps, cols, problems = read_rf_columns(path, sensor_names, ("rss_dbm",))
    return stamps, cols["rss_dbm"], problems


def read_rf_columns(path: str | os.PathLike, sensor_names: tuple[str, ...],
                    columns: tuple[str, ...]) -> tuple[np.ndarray, dict[str, np.ndarray], list[str]]:
    """``rf.csv`` (long format: ``t,sensor,<columns>``) -> ``(stamps (T,), {column: (T, n)}, problems)``, NaN
    where a sensor has no reading. Lines with a non-number or an unknown sensor are skipped and reported
    (``file:line: reason``), never fatal."""
    index = {n: j for j, n in enumerate(sensor_names)}
    problems: list[str] = []
    data: dict[float, dict[int, list[float]]] = {}
    with csv_rows(path, ("t", "sensor", *columns)) as lines:
        for lineno, row in lines:
            try:
                t, v = float(row["t"]), [float(row[c]) for c in columns]
            except (TypeError, ValueError):
                problems.append(f"{path}:{lineno}: not a number ({row})")
                continue
            if row["sensor"] not in index:
                problems.append(f"{path}:{lineno}: unknown sensor {row['sensor']!r}")
                continue
            data.setdefault(t, {})[index[row["sensor"]]] = v
    stamps = np.array(sorted(data))
    out = {c: np.full((len(stamps), len(sensor_names)), np.nan) for c in columns}
    for k, t in enumerate(stamps):
        for j, v in data[t].items():
            for c, x in zip(columns, v):
                out[c][k, j] = x if math.isfinite(x) else np.nan
    return stamps, out, problems


def rss_per_frame(stamps_s: np.ndarray, rss_dbm: np.ndarray, frame_stamps_s: np.ndarray,
                  frame_rate_hz: float) -> np.ndarray:
    """RF readings per frame: the reading nearest in time within half a frame interval, else NaN.

    ``stamps_s (T,)`` sorted, ``rss_dbm (T, n)``, ``frame_stamps_s (F,)`` -> ``(F, n)``.
    """
    frame_t = np.asarray(frame_stamps_s, float)
    out = np.full((len(frame_t), rss_dbm.shape[1] if rss_dbm.ndim == 2 else 0), np.nan)
    if len(stamps_s) == 0 or out.shape[1] == 0:
        return out
    j = np.clip(np.searchsorted(stamps_s, frame_t), 0, len(stamps_s) - 1)
    prev = np.maximum(j - 1, 0)
    j = np.where((j > 0) & (np.abs(stamps_s[prev] - frame_t) < np.abs(stamps_s[j] - frame_t)), prev, j)
    near = np.abs(stamps_s[j] - frame_t) <= 0.5 / frame_rate_hz
    out[near] = rss_dbm[j[near]]
    return out


def rss_to_range(rss_dbm: np.ndarray, pl: PathLossModel, deep: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3.35: ranges (m) and their 1-sigma (m) from RSS readings, with the deep (or near) parameters."""
    pl0, alpha, sigma = pl.deep if deep else pl.near
    loss = pl.pt_dbm - np.asarray(rss_dbm, float)
    d = pl.d0_m * 10.0 ** ((loss - pl0) / (10.0 * alpha))
    return d, d * math.log(10.0) * sigma / (10.0 * alpha)


def locate_lls(sensors_w_m: np.ndarray, rss_dbm: np.ndarray, pl: PathLossModel) -> Fix:
    ok = np.isfinite(rss_dbm)
    if ok.sum() < 4:
        return _no_fix(int(ok.sum()), "too_few_sensors")
    s, rss = sensors_w_m[ok], rss_dbm[ok]
    m, sig = rss_to_range(rss, pl)
    r = int(np.argmax(rss))  # reference: the strongest (nearest) sensor
    others = np.arange(len(s)) != r
    k = np.sum(s * s, axis=1)
    A = s[others] - s[r]  # Eq. 2.10
    b = m[r] ** 2 - m[others] ** 2 + k[others] - k[r]  # Eq. 2.11
    try:
        AtA_inv = np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        return _no_fix(len(s), "failed")
    x = 0.5 * AtA_inv @ A.T @ b  # Eq. 2.12
    # covariance: b_i depends on m_r and m_i; var(m^2) ~ (2 m sigma_m)^2
    J_b = np.zeros((len(b), len(s)))
    J_b[:, r] = 2 * m[r]
    J_b[np.arange(len(b)), np.nonzero(others)[0]] = -2 * m[others]
    G = 0.5 * AtA_inv @ A.T @ J_b
    cov = G @ np.diag(sig**2) @ G.T
    return Fix(x, cov, len(s))


def _solve(fun, x0, sensors_n: int) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        sol = least_squares(fun, x0, loss="soft_l1", f_scale=2.0, method="trf", max_nfev=100)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(sol.x)):
        return None
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    return sol.x, cov


def locate_nls(sensors_w_m: np.ndarray, rss_dbm: np.ndarray, pl: PathLossModel, x0: np.ndarray | None = None) -> Fix:
    ok = np.isfinite(rss_dbm)
    if ok.sum() < 4:
        return _no_fix(int(ok.sum()), "too_few_sensors")
    s, rss = sensors_w_m[ok], rss_dbm[ok]
    d, sig = rss_to_range(rss, pl)
    if x0 is None:
        start = locate_lls(sensors_w_m, rss_dbm, pl)
        x0 = start.position_w_m if start.status == "ok" else s.mean(axis=0)

    def res(x):
        return (np.linalg.norm(s - x, axis=1) - d) / sig  # Eq. 3.36 with its d_i^2 typo corrected

    out = _solve(res, np.asarray(x0, float), len(s))
    if out is None:
        return _no_fix(len(s), "failed")
    return Fix(out[0], out[1], len(s))


def locate_ml(sensors_w_m: np.ndarray, normals_w: np.ndarray, rss_dbm: np.ndarray, pl: PathLossModel,
              x0: np.ndarray | None = None, gate_sigma: float = 3.0) -> Fix:
    ok = np.isfinite(rss_dbm)
    if ok.sum() < 4:
        return _no_fix(int(ok.sum()), "too_few_sensors")
    s, n, rss = sensors_w_m[ok], normals_w[ok], rss_dbm[ok]
    if x0 is None:
        start = locate_nls(sensors_w_m, rss_dbm, pl)
        x0 = start.position_w_m if start.status == "ok" else s.mean(axis=0)

    def res_for(sel):
        def res(x):
            mean, sigma, _ = pl.predict(x, s[sel], n[sel])
            return (rss[sel] - mean) / sigma
        return res

    sel = np.ones(len(s), bool)
    out = _solve(res_for(sel), np.asarray(x0, float), len(s))
    if out is None:
        return _no_fix(len(s), "failed")
    r = np.abs(res_for(np.ones(len(s), bool))(out[0]))
    sel = r < gate_sigma  # gate outlying readings, refit once
    if (~sel).any() and sel.sum() >= 4:
        again = _solve(res_for(sel), out[0], int(sel.sum()))
        if again is not None:
            out = again
    return Fix(out[0], out[1], int(sel.sum()))

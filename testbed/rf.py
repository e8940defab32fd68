"""RF emulation: what body-mounted sensors would measure of the capsule's transmitter (dissertation Sec. 2.3,
Table 2.2, Eq. 2.1; SPEC.md "RF measurements").

Clean signal and noise are separate, seeded models:

- RSS (dBm): ``RSS(d) = Pt - PL(d0) - 10 alpha log10(d / d0)`` (Eq. 2.1's mean) with the NIST MICS-band implant
  to body surface parameters of Table 2.2; the *deep tissue* set applies when the capsule lies deeper than
  ``near_surface_depth_m`` below the body surface the sensor is on (the distance from the capsule to the sensor's
  plane along its normal), the *near surface* set otherwise. Noise: log-normal shadowing, ``S ~ N(0, sigma_dB)``
  of the applicable set, independent per reading (Eq. 2.1's ``S``).
- TOA (s): ``d sqrt(eps_r) / c`` with an average tissue relative permittivity (clean), plus Gaussian ranging error
  ``sigma_toa_s`` (noise).
- The real channel (:class:`ChannelModel`, all off by default, so ``thesis`` keeps the dissertation's ideal world
  in which the estimator's model is exactly the truth's): shadowing correlated along the capsule's path with
  Gudmundson's exponential model (M. Gudmundson, "Correlation model for shadow fading in mobile radio systems",
  Electron. Lett. 27(23), 1991: ``corr = exp(-|dx| / d_corr)``, each sensor its own process); per-sensor
  path-loss parameters that differ from the calibration written to ``meta.json`` (Sayrafian-Pour et al., "A
  statistical path loss model for medical implant communication channels", PIMRC 2009 -- the source of Table
  2.2 -- report the parameters varying with body location; the spread here is a stated choice); true sensor
  positions off the ``sensors.csv`` the pipeline reads (placement error); missing readings (dropouts, not
  written to ``rf.csv``) and outliers (a reading off by ``outlier_db``).

Sensor layouts (:class:`SensorLayout`): the ``thesis`` grids (SPEC: two 4x4 grids on the front (y = +0.15 m) and
back (y = -0.15 m) planes spanning x, z in [-0.15, 0.15] m), uniform rectangular arrays, the vertices of a cuboid,
or a ``sensors.csv`` file (``sensor,x,y,z[,nx,ny,nz]``). World (body) frame as SPEC.md: origin at the centre of
the abdomen, y anterior.

Files: ``rf.csv`` long format ``t,sensor,rss_dbm[,toa_s]``; ``sensors.csv`` ``sensor,x,y,z,nx,ny,nz``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bodyslam.errors import ConfigError
from bodyslam.io import write_csv
from bodyslam.fusion.rf import PathLossModel, read_sensors

__all__ = ["SensorLayout", "PathLossModel", "TOAModel", "ChannelModel", "emulate_rf", "write_rf", "layout_from_config"]

C_M_S = 299_792_458.0


@dataclass(frozen=True, eq=False)
class SensorLayout:
    names: tuple[str, ...]
    positions_w_m: np.ndarray  # (n, 3)
    normals_w: np.ndarray  # (n, 3) unit, pointing out of the body

    def __post_init__(self) -> None:
        if len(self.names) != len(self.positions_w_m) or len(set(self.names)) != len(self.names):
            raise ConfigError("sensor names must be unique, one per position")

    @classmethod
    def thesis_grids(cls, n_side: int = 4, half_span_m: float = 0.15, plane_y_m: float = 0.15) -> "SensorLayout":
        g = np.linspace(-half_span_m, half_span_m, n_side)
        X, Z = np.meshgrid(g, g, indexing="ij")
        names, pos, nrm = [], [], []
        for tag, y, ny in (("F", plane_y_m, 1.0), ("B", -plane_y_m, -1.0)):
            for i, (x, z) in enumerate(zip(X.ravel(), Z.ravel())):
                names.append(f"{tag}{i:02d}")
                pos.append((x, y, z))
                nrm.append((0.0, ny, 0.0))
        return cls(tuple(names), np.array(pos), np.array(nrm))

    @classmethod
    def ura(cls, n_side: int, width_m: float, plane_y_m: float, both_sides: bool = True) -> "SensorLayout":
        """Uniform rectangular array(s) of ``n_side x n_side`` on the plane ``y = +-plane_y_m``."""
        return cls.thesis_grids(n_side, width_m / 2.0, plane_y_m) if both_sides else cls._one_grid(
            n_side, width_m / 2.0, plane_y_m)

    @classmethod
    def _one_grid(cls, n_side, half, y):
        g = np.linspace(-half, half, n_side)
        X, Z = np.meshgrid(g, g, indexing="ij")
        pos = np.c_[X.ravel(), np.full(X.size, y), Z.ravel()]
        return cls(tuple(f"F{i:02d}" for i in range(len(pos))), pos, np.tile([0.0, 1.0, 0.0], (len(pos), 1)))

    @classmethod
    def cuboid(cls, size_m=(0.40, 0.40, 0.20)) -> "SensorLayout":
        """The 8 vertices of a cuboid centred on the origin (normals point away from the centre)."""
        s = np.asarray(size_m, float) / 2.0
        pos = np.array([[sx * s[0], sy * s[1], sz * s[2]] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        return cls(tuple(f"V{i}" for i in range(8)), pos, pos / np.linalg.norm(pos, axis=1, keepdims=True))

    @classmethod
    def read_csv(cls, path: str | os.PathLike) -> "SensorLayout":
        names, pos, nrm = read_sensors(path)
        return cls(names, pos, nrm)

    def write_csv(self, path: str | os.PathLike) -> None:
        write_csv(path, ["sensor", "x", "y", "z", "nx", "ny", "nz"],
                  [[n, *p, *q] for n, p, q in zip(self.names, self.positions_w_m.tolist(), self.normals_w.tolist())])


@dataclass(frozen=True)
class TOAModel:
    eps_r: float = 50.0  # average relative permittivity of abdominal tissue at MICS frequencies (assumption)
    sigma_toa_s: float = 0.0  # 0: no TOA column

    def mean_toa_s(self, d_m: np.ndarray) -> np.ndarray:
        return np.asarray(d_m) * math.sqrt(self.eps_r) / C_M_S


@dataclass(frozen=True)
class ChannelModel:
    """How the real channel departs from the calibration the pipeline is given (module docstring). Every
    default is "no departure"; the ``realistic`` scenario's values and their reasons are in its file."""

    shadowing_corr_m: float = 0.0  # Gudmundson correlation distance along the path (0: independent per reading)
    pl0_sd_db: float = 0.0  # per-sensor offset of PL(d0) from the calibration, N(0, sd)
    alpha_sd: float = 0.0  # per-sensor offset of the path-loss exponent, N(0, sd)
    placement_sd_m: float = 0.0  # true sensor position = sensors.csv + N(0, sd) per axis
    dropout_prob: float = 0.0  # a reading is lost
    outlier_prob: float = 0.0  # a reading is off by +-outlier_db
    outlier_db: float = 15.0

    def __post_init__(self) -> None:
        for name in ("shadowing_corr_m", "pl0_sd_db", "alpha_sd", "placement_sd_m", "outlier_db"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"[rf.channel] {name} must be >= 0, got {getattr(self, name)}")
        for name in ("dropout_prob", "outlier_prob"):
            if not 0 <= getattr(self, name) < 1:
                raise ConfigError(f"[rf.channel] {name} must be in [0, 1), got {getattr(self, name)}")

    @property
    def ideal(self) -> bool:
        return self == ChannelModel(outlier_db=self.outlier_db)


def correlated_shadowing(positions_w_m: np.ndarray, n_sensors: int, corr_m: float,
                         rng: np.random.Generator) -> np.ndarray:
    """Unit-variance shadowing ``(T, n)`` whose correlation between poses ``i, j`` is ``exp(-s_ij / corr_m)``,
    ``s`` the path length between them (Gudmundson's model as a first-order Gauss-Markov process along the
    path, exact for it); each sensor an independent process. ``corr_m = 0``: independent per reading."""
    e = rng.normal(size=(len(positions_w_m), n_sensors))
    if corr_m <= 0 or len(e) < 2:
        return e
    step = np.linalg.norm(np.diff(np.asarray(positions_w_m, float), axis=0), axis=1)
    rho = np.exp(-step / corr_m)
    out = np.empty_like(e)
    out[0] = e[0]
    for k in range(1, len(e)):
        out[k] = rho[k - 1] * out[k - 1] + math.sqrt(1.0 - rho[k - 1] ** 2) * e[k]
    return out


def geometry(positions_w_m: np.ndarray, layout: SensorLayout):
    """Distances ``(T, n)`` and depths below each sensor's surface ``(T, n)``."""
    diff = layout.positions_w_m[None, :, :] - np.asarray(positions_w_m)[:, None, :]
    d = np.linalg.norm(diff, axis=2)
    depth = np.einsum("tnk,nk->tn", diff, layout.normals_w)
    return d, np.maximum(depth, 0.0)


def emulate_rf(positions_w_m: np.ndarray, layout: SensorLayout, pl: PathLossModel = PathLossModel(),
               toa: TOAModel = TOAModel(), rng: np.random.Generator | int | None = None,
               channel: ChannelModel = ChannelModel()) -> dict[str, np.ndarray]:
    """Clean and noisy RSS (and TOA) for every pose and sensor: arrays ``(T, n)``. With a non-ideal ``channel``
    the readings come from the *true* channel (sensors where they really are, their own path-loss parameters,
    correlated shadowing), NaN where a reading was lost; ``layout`` and ``pl`` stay what the pipeline is told."""
    rng = np.random.default_rng(rng)
    shadow_rng, toa_rng = rng.spawn(2)  # (the ideal channel's streams: thesis sequences stay as they were)
    true_layout, pl0_off, alpha_off = layout, 0.0, 0.0
    if not channel.ideal:
        chan_rng = rng.spawn(1)[0]
        n = len(layout.names)
        moved = layout.positions_w_m + chan_rng.normal(0.0, channel.placement_sd_m, (n, 3))
        true_layout = SensorLayout(layout.names, moved, layout.normals_w)
        pl0_off = chan_rng.normal(0.0, channel.pl0_sd_db, n)
        alpha_off = chan_rng.normal(0.0, channel.alpha_sd, n)
    d, depth = geometry(positions_w_m, true_layout)
    pl0, alpha, sigma = pl.params(depth)
    clean = pl.pt_dbm - (pl0 + pl0_off) - 10.0 * (alpha + alpha_off) * np.log10(np.maximum(d, 1e-4) / pl.d0_m)
    shadow = correlated_shadowing(positions_w_m, len(layout.names), channel.shadowing_corr_m, shadow_rng)
    out = {"distance_m": d, "depth_m": depth, "rss_clean_dbm": clean, "rss_dbm": clean + shadow * sigma}
    if not channel.ideal:
        lost = chan_rng.random(clean.shape) < channel.dropout_prob
        wild = chan_rng.random(clean.shape) < channel.outlier_prob
        out["rss_dbm"] = np.where(wild, out["rss_dbm"] + chan_rng.choice([-1.0, 1.0], clean.shape) * channel.outlier_db,
                                  out["rss_dbm"])
        out["rss_dbm"][lost] = np.nan
        out["true_sensors_w_m"] = true_layout.positions_w_m
    if toa.sigma_toa_s > 0:
        t_clean = toa.mean_toa_s(d)
        out["toa_clean_s"] = t_clean
        out["toa_s"] = t_clean + toa_rng.normal(size=t_clean.shape) * toa.sigma_toa_s
    return out


def write_rf(path: str | os.PathLike, stamps_s: np.ndarray, layout: SensorLayout, meas: dict) -> None:
    """``rf.csv`` in SPEC.md's long format."""
    has_toa = "toa_s" in meas
    header = ["t", "sensor", "rss_dbm"] + (["toa_s"] if has_toa else [])
    rows = []
    for k, t in enumerate(np.asarray(stamps_s)):
        for j, name in enumerate(layout.names):
            if not np.isfinite(meas["rss_dbm"][k, j]):
                continue  # a lost reading: no line (what a receiver that heard nothing writes)
            r = [float(t), name, float(meas["rss_dbm"][k, j])]
            if has_toa:
                r.append(float(meas["toa_s"][k, j]))
            rows.append(r)
    write_csv(path, header, rows)


def layout_from_config(sec: dict, base_dir: Path | None = None) -> SensorLayout:
    kind = sec.get("layout", "thesis")
    if kind == "thesis":
        return SensorLayout.thesis_grids()
    if kind == "ura":
        return SensorLayout.ura(int(sec.get("n_side", 5)), float(sec.get("width_m", 0.4)),
                                float(sec.get("plane_y_m", 0.15)), bool(sec.get("both_sides", True)))
    if kind == "cuboid":
        return SensorLayout.cuboid(tuple(sec.get("size_m", (0.4, 0.4, 0.2))))
    if kind == "file":
        f = Path(sec.get("file", ""))
        if base_dir is not None and not f.is_absolute():
            f = base_dir / f
        return SensorLayout.read_csv(f)
    raise ConfigError(f"[rf] layout must be thesis, ura, cuboid or file, got {kind!r}")

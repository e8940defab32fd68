"""Body-SLAM localization as one function: visual steps + RF readings -> trajectory (dissertation Sec. 3.3).

The chain, the same for ``bodyslam localize``, ``bodyslam batch`` and ``testbed evaluate``:

1. :meth:`RfInput.read`: sensors (``sensors.csv``), readings (``rf.csv``, malformed lines skipped and listed) and
   the path-loss calibration (``meta.json``'s ``rf.pathloss``; default Table 2.2);
2. readings per frame (:func:`bodyslam.fusion.rf.rss_per_frame`: nearest within half a frame interval);
3. ML position fixes per frame (:func:`bodyslam.fusion.rf.locate_ml_frames`: vectorised over frames; solved in blocks
   where first read, :class:`bodyslam.fusion.rf.FixesOnDemand` -- the raw-RSS fusion reads its start window's),
   which start the filter;
4. the error-state EKF (:func:`bodyslam.fusion.body_slam.fuse`, on raw RSS or on the fixes) and its RTS smoothing,
   then (raw RSS) the whole exam solved at once from the smoother's trajectory (:func:`bodyslam.fusion.refine.
   refine_map`, with its own covariances): the smoothed output; the plain smoother's is kept beside it
   (``Localization.rts``);
5. their covariances scaled by the readings' measured correlation (:mod:`bodyslam.fusion.channel`: the smoother's
   by the whole exam's, the online filter's frame ``k`` by frames ``0 .. k``'s, over lags up to
   :data:`~bodyslam.fusion.channel.STATED_MAX_LAG_FRAMES`, the summed correlations scaled by ``m / (m - 3)`` for what
   the positions they were read at took up, :data:`~bodyslam.fusion.channel.POSITION_DOF`), so that the stated
   1-sigma admits a channel that is not the calibration's independent shadowing (1.0 on an ideal one). The
   whole-exam solve's orientation takes the factor on the readings' share of its information only
   (:func:`bodyslam.fusion.refine.stated_covariances`, session 65);
6. the path travelled (:func:`bodyslam.vision.tracking.path_travelled`).

:func:`write_localization` writes the one output set: ``trajectory.tum`` (smoothed), ``trajectory_filter.tum``
(online filter), ``uncertainty.csv`` (:data:`UNCERTAINTY_COLUMNS`, also written by dead reckoning and the other
papers' localizers), ``rf_fixes.csv``, ``rss_bias.csv`` (with the bias states: :func:`write_rss_bias`),
``trajectory.png`` (3-D view and three projections with the 1-sigma and the marked frames), ``path.png`` (path
travelled with its 1-sigma) and ``report.html`` (a 3-D view to turn).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bodyslam.errors import InputError
from bodyslam.fusion.body_slam import RSS_BIAS_STATES, FusionResult, fuse, released, rts_smooth
from bodyslam.fusion.refine import refine_map
from bodyslam.fusion.channel import (POSITION_DOF, STATED_MAX_LAG_FRAMES, ResidualCorrelation, causal_inflation,
                                     filter_memory, inflate, normalised_residuals, residual_correlation,
                                     smoother_inflation)
from bodyslam.io import write_csv, write_image, write_tum
from bodyslam.fusion.rf import (Fix, FixesOnDemand, PathLossModel, check_rss_units, read_rf, read_sensors,
                               rss_per_frame)
from bodyslam.steps import StepMotion, lost_step_floor_m
from bodyslam.vision.tracking import path_travelled

__all__ = ["RfInput", "Localization", "localize", "online_inflation", "net_of_bias", "write_localization",
           "write_rss_bias", "write_uncertainty", "UNCERTAINTY_COLUMNS"]

# corr_xy, corr_xz, corr_yz: the position's correlation coefficients, so that the whole 3x3 covariance (and its 68%
# ellipsoid) can be rebuilt, cov_ij = corr_ij sd_i sd_j (session 63; before, a user or a benchmark had the per-axis
# 1-sigma only: on the realistic_exam reporting runs 740-743 and 866-877 the share inside the 68% ellipsoid reads
# 0.53 from them and 0.51 from the whole covariance)
UNCERTAINTY_COLUMNS = ["frame", "t", "sd_x_m", "sd_y_m", "sd_z_m", "sd_position_m", "sd_heading_rad", "path_m",
                       "sd_path_m", "corr_xy", "corr_xz", "corr_yz"]


@dataclass
class RfInput:
    """What the body sensors recorded, and their calibration."""

    sensor_names: tuple[str, ...]
    sensors_w_m: np.ndarray  # (m, 3)
    normals_w: np.ndarray  # (m, 3)
    stamps_s: np.ndarray  # (T,)
    rss_dbm: np.ndarray  # (T, m), NaN where a sensor has no reading
    pathloss: PathLossModel = field(default_factory=PathLossModel)
    problems: list[str] = field(default_factory=list)  # skipped lines, "file:line: reason"

    @classmethod
    def read(cls, rf_path: str | os.PathLike, sensors_path: str | os.PathLike,
             pathloss: dict | None = None) -> "RfInput":
        names, pos, nrm = read_sensors(sensors_path)
        stamps, rss, problems = read_rf(rf_path, names)
        pl = PathLossModel.from_dict(pathloss) if pathloss else PathLossModel()
        check_rss_units(rf_path, rss, pl)
        return cls(names, pos, nrm, stamps, rss, pl, problems)


@dataclass
class Localization:
    frames: np.ndarray  # (n,) frame numbers
    stamps_s: np.ndarray  # (n,)
    filtered: FusionResult  # the online (causal after its start window) filter; its passes released (bias rows only)
    smoothed: FusionResult  # the RTS smoother refined over the whole exam (refine_map; RTS alone where not refined)
    fixes: Sequence[Fix]  # ML fixes per frame (FixesOnDemand: solved when read)
    rss_dbm: np.ndarray  # (n, m) the readings of each frame (NaN: none)
    path_m: np.ndarray | None  # (n,) path travelled from the first frame (None: not asked for, localize)
    path_var_m2: np.ndarray | None  # (n,)
    rf_problems: list[str]
    # the readings' measured correlation behind the smoother's covariance, and the online filter's factor per
    # frame (None / ones: covariances as the filter computed them, ``honest_cov=False``)
    channel: ResidualCorrelation | None = None
    kappa_online: np.ndarray | None = None
    rts: FusionResult | None = None  # the RTS smoother before the refinement (its covariance scaled the same way)
    # the smoother's factor per frame (bodyslam.fusion.channel.smoother_inflation): the whole-exam solve's position
    # covariance and the plain smoother's are scaled by it; the solve's orientation takes it on the readings' share
    # (bodyslam.fusion.refine.stated_covariances)
    kappa_smoothed: np.ndarray | float | None = None
    sensor_names: tuple[str, ...] = ()  # the readings' columns (RfInput.sensor_names)

    @property
    def rss_bias_db(self) -> np.ndarray | None:
        """(n, m) the online filter's per-sensor RSS bias estimates after each frame (dB; None without the bias
        states, ``localize(bias_states=True)``)."""
        return None if self.filtered.passes is None else self.filtered.passes.post_bias_db


def localize(steps: list[StepMotion], stamps_s: np.ndarray, rf: RfInput, frame_rate_hz: float,
             frames: np.ndarray | None = None, mode: str = "rss", honest_cov: bool = True,
             radius_sd_rel: float = 0.0, refine: bool = True, radius_m: float | None = None,
             bias_states: bool = False, travelled: bool = True) -> Localization:
    """Fuse the steps into frames ``0 .. len(steps)`` with the RF readings (module docstring). ``honest_cov``:
    scale the covariances by the readings' measured correlation (step 5; False: as the filter computed them).
    ``radius_sd_rel``: relative 1-sigma of the lumen radius the steps assumed; above 0 the fusion estimates the
    visual scale as a state (:mod:`bodyslam.fusion.ekf`), and the steps' 1-sigma is expected to include it
    (:func:`bodyslam.vision.odometry.with_lumen_uncertainty`). ``refine``: solve the whole exam at once from the
    smoother's trajectory (step 4; raw-RSS mode only). ``radius_m``: the lumen radius the steps assumed (the
    floor of a lost step's length, in the filters and in the path travelled,
    :func:`bodyslam.vision.tracking.path_travelled`). ``bias_states``: per-sensor RSS bias states in the raw-RSS
    filter (:data:`bodyslam.fusion.body_slam.RSS_BIAS_STATES`; off by default, docs/RESULTS.md); the whole-exam
    solve and the 1-sigma then take the readings less the filter's biases. ``travelled``: also the path travelled
    (step 6); False for a caller that makes its own (``bodyslam batch``, while this runs on a worker): then
    ``path_m`` and ``path_var_m2`` are None.

    Raises
    ------
    InputError
        Fewer than 3 frames with an RF fix (the visual path cannot be placed in the body frame).
    """
    stamps_s = np.asarray(stamps_s, float)
    if len(stamps_s) != len(steps) + 1:
        raise ValueError(f"{len(steps)} steps need {len(steps) + 1} frame stamps, got {len(stamps_s)}")
    rss = rss_per_frame(rf.stamps_s, rf.rss_dbm, stamps_s, frame_rate_hz)
    fixes = FixesOnDemand(rf.sensors_w_m, rf.normals_w, rss, rf.pathloss)  # solved where the fusion reads them
    n_ok, why = 0, {"too_few_sensors": 0, "failed": 0}
    for f in fixes:  # (stops at the third: usually within the first block)
        n_ok += f.status == "ok"
        why[f.status] = why.get(f.status, 0) + 1
        if n_ok == 3:
            break
    if n_ok < 3:  # every frame was solved: say what stopped them
        reasons = [f"{why['too_few_sensors']} with readings from fewer than 3 sensors in time with the frames"]
        if why["failed"]:
            reasons.append(f"{why['failed']} whose solve found no position (readings that this sensor layout "
                           "cannot place: sensors.csv or rf.csv wrong?)")
        span = (f"; the readings at t = {rf.stamps_s.min():g}-{rf.stamps_s.max():g} s, the frames at "
                f"{stamps_s.min():g}-{stamps_s.max():g} s" if len(rf.stamps_s) and len(stamps_s) else "")
        raise InputError(f"RF not usable: {n_ok} of {len(fixes)} frame(s) with an RF fix, need at least 3; "
                         + ", ".join(reasons) + span)
    floor = lost_step_floor_m(radius_m)
    ekf = fuse(steps, fixes, rss, rf.sensors_w_m, rf.normals_w, rf.pathloss, mode=mode, scale_sd_rel=radius_sd_rel,
               lost_floor_m=floor, **(RSS_BIAS_STATES if bias_states else {}))
    # the online factor's taper and the smoother's two-sided one, from the filter's priors and posteriors; they and
    # F are not needed once the smoother has run: released then, not held through the rest (~1 kB a frame)
    memory = filter_memory(ekf) if honest_cov else None
    ekf, rts = released(ekf), released(rts_smooth(ekf))
    smoothed = rts
    rss_net = net_of_bias(ekf, rss)  # the readings less the filter's RSS bias states (step 4)
    measured: dict = {}

    def smoother_kappa(positions_w_m: np.ndarray):
        """The readings' correlation at the smoothed positions, and the smoother's factor from it (step 5)."""
        measured["channel"] = residual_correlation(normalised_residuals(rss_net, positions_w_m, rf.sensors_w_m,
                                                                        rf.normals_w, rf.pathloss),
                                                   STATED_MAX_LAG_FRAMES, POSITION_DOF)
        measured["kappa"] = smoother_inflation(measured["channel"], memory)
        return measured["kappa"]

    refined = refine and mode == "rss"
    if refined:  # the whole-exam solve states its covariance with the factor (refine.stated_covariances)
        bias_var = None if ekf.passes is None else ekf.passes.post_bias_var_db2
        smoothed = refine_map(rts, steps, rss_net, rf.sensors_w_m, rf.normals_w, rf.pathloss, lost_floor_m=floor,
                              reading_var_db2=bias_var, reading_kappa=smoother_kappa if honest_cov else None)
    channel = kappa_online = kappa_smoothed = None
    if honest_cov:
        kappa_online = online_inflation(ekf, rss, rf, memory)
        if not refined:
            smoother_kappa(smoothed.positions_w_m)
        channel, kappa_smoothed = measured["channel"], measured["kappa"]
        ekf, rts = inflate(ekf, kappa_online), inflate(rts, kappa_smoothed)
        if not refined:
            smoothed = rts
    path, var = path_travelled(steps, radius_sd_rel, radius_m) if travelled else (None, None)
    frames = np.arange(len(stamps_s)) if frames is None else np.asarray(frames)
    return Localization(frames, stamps_s, ekf, smoothed, fixes, rss, path, var, list(rf.problems), channel,
                        kappa_online, rts, kappa_smoothed, tuple(rf.sensor_names))


def online_inflation(res: FusionResult, rss: np.ndarray, rf: RfInput,
                     memory: np.ndarray | None = None) -> np.ndarray:
    """Per frame ``k``, the correlation factor of the readings of frames ``0 .. k`` (less the run's RSS bias states,
    :func:`net_of_bias`) at an online run's positions, over the filter's own memory
    (:func:`bodyslam.fusion.channel.causal_inflation`; ``memory``: the run's :func:`filter_memory`, computed here
    when not given)."""
    return causal_inflation(normalised_residuals(net_of_bias(res, rss), res.positions_w_m, rf.sensors_w_m,
                                                 rf.normals_w, rf.pathloss),
                            STATED_MAX_LAG_FRAMES, filter_memory(res) if memory is None else memory, POSITION_DOF)


def net_of_bias(res: FusionResult, rss: np.ndarray) -> np.ndarray:
    """The readings ``rss (n, m)`` less the filter run's RSS bias states after each frame's update (causal: frame
    ``k``'s from readings ``0 .. k``; :mod:`bodyslam.fusion.ekf`), or ``rss`` itself for a run without them. What the
    filter counts as independent noise is what is left: the whole-exam solve fits it, and its measured correlation
    scales the stated covariances (the factor measured on the raw readings would count the correlation the bias
    states already carry a second time)."""
    bias = None if res.passes is None else res.passes.post_bias_db
    return rss if bias is None else rss - bias


def write_uncertainty(path: str | os.PathLike, frames, stamps_s, cov_position_m2: np.ndarray,
                      sd_heading_rad: np.ndarray | None = None, path_m: np.ndarray | None = None,
                      path_var_m2: np.ndarray | None = None) -> None:
    """``uncertainty.csv`` (:data:`UNCERTAINTY_COLUMNS`): 1-sigma per axis and in all (m), of the heading (rad,
    the orientation's 1-sigma over its three axes), the path travelled and its 1-sigma, and the position's
    correlation coefficients; empty where a localizer has no such figure (a correlation where an axis has no
    spread)."""
    cov = np.asarray(cov_position_m2, float)
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    n = len(sd)
    nan = np.full(n, np.nan)
    head = nan if sd_heading_rad is None else np.asarray(sd_heading_rad, float)
    pm = nan if path_m is None else np.asarray(path_m, float)
    psd = nan if path_var_m2 is None else np.sqrt(np.maximum(np.asarray(path_var_m2, float), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.stack([cov[:, i, j] / (sd[:, i] * sd[:, j]) for i, j in ((0, 1), (0, 2), (1, 2))], axis=1)

    def cell(x):
        return "" if not math.isfinite(x) else float(x)

    write_csv(path, UNCERTAINTY_COLUMNS,  # (rows made as written: a whole exam's as lists took ~350 bytes a frame)
              ([int(frames[k]), float(stamps_s[k]), *map(float, sd[k]), float(np.sqrt(np.sum(sd[k] ** 2))),
                cell(head[k]), cell(pm[k]), cell(psd[k]), *map(cell, corr[k])] for k in range(n)))


def write_rss_bias(path: str | os.PathLike, loc: Localization) -> bool:
    """With the RSS bias states: per sensor, what its readings ran above the path-loss calibration by the online
    filter (dB; its mean over the exam and its last value) and how many readings it gave. Returns whether it
    wrote (nothing without the bias states)."""
    bias = loc.rss_bias_db
    if bias is None:
        return False
    write_csv(path, ["sensor", "bias_mean_db", "bias_last_db", "readings"],
              [[name, float(np.mean(bias[:, j])), float(bias[-1, j]), int(np.isfinite(loc.rss_dbm[:, j]).sum())]
               for j, name in enumerate(loc.sensor_names)])
    return True


def write_localization(out: str | os.PathLike, loc: Localization, title: str = "Body-SLAM") -> None:
    """The output set of a localization run (module docstring) into the directory ``out`` (marked frames are
    ``bodyslam batch``'s: ``--mark``)."""
    from bodyslam.plots import Path3D, path_figure, trajectory_figure
    from bodyslam.report import table, view_3d, write_page

    out = Path(out)
    res, ekf = loc.smoothed, loc.filtered
    write_tum(out / "trajectory.tum", loc.stamps_s, res.positions_w_m, res.rotations_w_c)
    write_tum(out / "trajectory_filter.tum", loc.stamps_s, ekf.positions_w_m, ekf.rotations_w_c)
    c = res.cov
    write_uncertainty(out / "uncertainty.csv", loc.frames, loc.stamps_s, c[:, :3, :3],
                      np.sqrt(np.trace(c[:, 3:, 3:], axis1=1, axis2=2)), loc.path_m, loc.path_var_m2)
    fx = np.array([f.position_w_m for f in loc.fixes])
    write_csv(out / "rf_fixes.csv", ["frame", "t", "x_m", "y_m", "z_m", "status"],
              [[int(loc.frames[k]), t, *fx[k], loc.fixes[k].status] for k, t in enumerate(loc.stamps_s)])
    write_rss_bias(out / "rss_bias.csv", loc)
    fixes_ok = np.where(np.array([f.status == "ok" for f in loc.fixes])[:, None], fx, np.nan)
    paths = [Path3D(f"{title} (smoothed)", res.positions_w_m, (214, 39, 40), 1.8, res.cov[:, :3, :3]),
             Path3D(f"{title} (online filter)", ekf.positions_w_m, (31, 119, 180), 1.0),
             Path3D("RF fixes (ML)", fixes_ok, (170, 170, 170), 0.8)]
    write_image(out / "trajectory.png", trajectory_figure(f"{title}: where the capsule was (body frame)", paths))
    write_image(out / "path.png", path_figure(f"{title}: how far along the gut", loc.stamps_s, loc.path_m,
                                              loc.path_var_m2))
    sd = np.sqrt(np.trace(c[:, :3, :3], axis1=1, axis2=2))
    rows = [["frames", len(loc.frames)], ["duration (s)", f"{loc.stamps_s[-1] - loc.stamps_s[0]:.1f}"],
            ["path travelled (cm)", f"{loc.path_m[-1] * 100:.1f} +- {math.sqrt(max(loc.path_var_m2[-1], 0)) * 100:.1f}"],
            ["position 1-sigma, median / max (cm)", f"{np.median(sd) * 100:.2f} / {sd.max() * 100:.2f}"],
            ["RF readings' correlation factor kappa (whole exam / smoother's window, mean)",
             f"{loc.channel.kappa:.2f} / {np.mean(loc.kappa_smoothed):.2f}" if loc.channel is not None
             else "not measured"],
            ["RF updates / readings rejected", f"{ekf.n_updates} / {ekf.n_rejected}"]]
    body = (table(None, rows) + "<h2>3-D view</h2>" + view_3d(paths[:2], [], loc.stamps_s, loc.frames)
            + "<h2>Plots</h2>")
    write_page(out / "report.html", f"{title} localization", "Positions in the body frame (x toward the patient's "
               "left, y anterior, z cranial), from the visual steps fused with the RF readings; 1-sigma as stated by "
               "the smoother, scaled by the readings' measured correlation.", body, ["trajectory.png", "path.png"])

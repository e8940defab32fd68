"""Evaluation runs: every localization algorithm on the same rendered sequences and RF draws, scored against the
truth (SPEC.md "How accuracy is scored"; dissertation Sec. 4.3, Fig. 4.20-4.24).

For each seed: render the scenario, run ``bodyslam motion`` on the frames (the pipeline never sees the truth),
then on the same RF draws: RF only (ML and NLS fixes), dead reckoning (the rigid fit of its first window to the
RF fixes, as the filters' start before their orientation search, then vision only), the dissertation's KF, the
EKF on ML fixes, the EKF on raw RSS and its RTS smoothing. Scores: per-frame Euclidean error (mean, RMSE, median,
p90, max in cm), RMSE / sqrt(PCRB) (:mod:`testbed.bound`), the mean error of a causal filter at the bound, the
smoothing bound (the smoother's reference), and Table 4.1 of the motion. The bound uses the vision's measured step
errors on each run (see :func:`_measured_step_noise`) and, where the scenario's RF channel departs from the
calibration, that true channel (:func:`testbed.bound.channel_bounds`).
Writes ``report.json`` (keys carry units) and PNG plots: trajectories against the truth (two
projections), error against step, error histogram and error CDF.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from bodyslam.fusion.body_slam import fuse, kf_thesis, step_pose
from bodyslam.errors import InputError
from bodyslam.io import read_motion_steps, read_tum, write_image, write_json, write_tum
from bodyslam.fusion.channel import inflate
from bodyslam.fusion.localize import RfInput, localize, online_inflation
from bodyslam.meta import read_meta
from bodyslam.plots import Figure
from bodyslam.steps import MEASURED, WITH_ESTIMATE, WITH_ROTATION, lost_step_floor_m
from bodyslam.fusion.rf import locate_nls
from bodyslam.vision.lumen_scale import radius_sd_rel_after, scale_of_steps
from bodyslam.vision.odometry import MotionSettings, lumen_scale_measured
from testbed.bound import channel_bounds, efficient_mean_error, position_bounds
from testbed.score import CHI2_3_683, score_motion, score_path
from testbed.simulate import prepare_output_dir, simulate
from testbed.rf import ChannelModel
from testbed.scenario import rf_channel

log = logging.getLogger(__name__)

__all__ = ["evaluate_sequence", "evaluate"]

ALGORITHMS = ("rf_ml", "rf_nls", "dead_reckoning", "thesis_kf", "thesis_kf_ml", "ekf_fixes", "ekf_rss", "ekf_rss_causal",
              "ekf_rss_rts_plain", "ekf_rss_rts", "ekf_rss_bias", "ekf_rss_bias_rts")


def evaluate_sequence(d: Path, channel: ChannelModel | None = None) -> dict:
    """Run every algorithm on one rendered sequence directory (which has motion.csv next to its frames).
    ``channel``: the scenario's true RF channel (scoring only: the bounds are built under it,
    :func:`testbed.bound.channel_bounds`; ideal or None: the calibration's model, paper 000's bound)."""
    meta = read_meta(d)
    rf = RfInput.read(d / meta.rf.file, d / meta.rf.sensors, meta.rf.pathloss)
    _, gt, grot = read_tum(d / "groundtruth.tum")
    steps = read_motion_steps(d / "motion.csv", range(1, len(gt)))
    # the pipeline's one localization chain (bodyslam.fusion.localize), on the frames' time stamps
    # the radius's relative 1-sigma the steps carry: the measured lumen scale's where it applied, else the prior's
    lumen = scale_of_steps(steps, lumen_scale_measured(MotionSettings(), meta.radius_sd_rel))
    rel = radius_sd_rel_after(lumen, meta.radius_sd_rel)
    loc = localize(steps, np.arange(len(gt)) / meta.frame_rate_hz, rf, meta.frame_rate_hz, mode="rss",
                   radius_sd_rel=rel, radius_m=meta.tube_radius_m)
    ekf, fixes = loc.filtered, loc.fixes
    # the same chain with per-sensor RSS bias states (opt-in: bodyslam localize --rss-bias-states)
    loc_b = localize(steps, np.arange(len(gt)) / meta.frame_rate_hz, rf, meta.frame_rate_hz, mode="rss",
                     radius_sd_rel=rel, radius_m=meta.tube_radius_m, bias_states=True)
    pos, nrm, pl = rf.sensors_w_m, rf.normals_w, rf.pathloss
    rss = loc.rss_dbm
    nls = [locate_nls(pos, x, pl) for x in rss]
    R0, p0 = ekf.init
    R_fit, p_fit = ekf.alignment  # dead reckoning's best rigid fit to the fixes of the first window
    dr = ekf.dead_reckoning  # in the first camera frame, steps without an estimate as no motion
    # strictly causal: frame k sees frames 0..k only (no alignment window; the start searched from frame 0)
    floor = lost_step_floor_m(meta.tube_radius_m)
    causal = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", causal_start=True, scale_sd_rel=rel, lost_floor_m=floor)
    causal = inflate(causal, online_inflation(causal, rss, rf))  # the covariance localize states (step 5)
    est = {
        "rf_ml": np.array([f.position_w_m for f in fixes]),
        "rf_nls": np.array([f.position_w_m for f in nls]),
        "dead_reckoning": p_fit + R_fit.apply(dr),
        "thesis_kf": kf_thesis(steps, nls, (R0, p0), resets=ekf.resets),
        # the same filter fed by the dissertation's other RF localizer (ML, Sec. 2.3.3.2) instead of Eq. 3.36's NLS
        "thesis_kf_ml": kf_thesis(steps, fixes, (R0, p0), resets=ekf.resets),
        "ekf_fixes": fuse(steps, fixes, rss, pos, nrm, pl, mode="fix", scale_sd_rel=rel,
                          lost_floor_m=floor).positions_w_m,
        "ekf_rss": ekf.positions_w_m,
        "ekf_rss_causal": causal.positions_w_m,
        # the smoother alone, and refined over the whole exam (bodyslam.fusion.refine: the shipped smoothed output)
        "ekf_rss_rts_plain": loc.rts.positions_w_m,
        "ekf_rss_rts": loc.smoothed.positions_w_m,
        "ekf_rss_bias": loc_b.filtered.positions_w_m,
        "ekf_rss_bias_rts": loc_b.smoothed.positions_w_m,
    }
    with_cov = {"ekf_rss": ekf, "ekf_rss_causal": causal, "ekf_rss_rts_plain": loc.rts, "ekf_rss_rts": loc.smoothed,
                "ekf_rss_bias": loc_b.filtered, "ekf_rss_bias_rts": loc_b.smoothed}
    _write_trajectories(d / "trajectories", np.arange(len(gt)) / meta.frame_rate_hz, est, with_cov)
    problems = rf.problems
    sig_t, sig_r = _measured_step_noise(steps, gt, grot)
    # prior of the bound: no information beyond the abdomen (10 cm, 45 deg); every RF reading counted once. The
    # filters' start aligns the first window of fixes, so over that window they are not strictly causal.
    P0 = np.diag([0.10**2] * 3 + [np.radians(45.0) ** 2] * 3)
    if channel is None or channel.ideal:  # smooth: the smoother's reference
        bounds, smooth = position_bounds(gt, grot, sig_t, sig_r, pos, nrm, pl, P0)
    else:  # the true channel's model: correlated shadowing, per-sensor departures as nuisances with their priors
        bounds, smooth = channel_bounds(gt, grot, sig_t, sig_r, pos, nrm, pl, P0, channel)
    pcrb = np.trace(bounds, axis1=1, axis2=2)
    errors = {k: np.linalg.norm(v - gt, axis=1) for k, v in est.items()}
    return {"estimates": est, "errors": errors, "pcrb_m2": pcrb, "pcrb_mean_error_m": efficient_mean_error(bounds),
            "smoothing_bound_m2": np.trace(smooth, axis1=1, axis2=2),
            "smoothing_bound_mean_error_m": efficient_mean_error(smooth),
            "truth": gt, "rf_problems": len(problems), "stamps_s": np.arange(len(gt)) / meta.frame_rate_hz,
            "cov_m2": {k: r.cov[:, :3, :3] for k, r in with_cov.items()},  # for the plots' 1-sigma
            "consistency": {k: {**consistency(r.positions_w_m, r.cov[:, :3, :3], gt),
                                **orientation_consistency(r.rotations_w_c, r.cov[:, 3:6, 3:6], grot)}
                            for k, r in with_cov.items()},
            "orientation_error_deg": {k: orientation_errors_deg(r.rotations_w_c, grot) for k, r in with_cov.items()},
            "motion": score_motion(d, d / "motion.csv"),
            "path_travelled": score_path(d, d / "motion.csv", rel, meta.tube_radius_m),
            # the scale the steps were rescaled by (bodyslam.vision.lumen_scale; 1 where not measured, too few rings,
            # or no more of them than a lumen without rings shows), the rings seen and the sampled steps fitted
            "lumen_scale": lumen,
            # the readings' measured correlation that scales the stated covariances (bodyslam.fusion.channel)
            "kappa": {"smoothed": float(np.mean(loc.kappa_smoothed)), "whole_run": loc.channel.kappa,
                      "online_last_frame": float(loc.kappa_online[-1])}}


def _write_trajectories(out: Path, stamps_s: np.ndarray, est: dict, with_cov: dict) -> None:
    """Every algorithm's trajectory as ``out/<algorithm>.tum`` (body frame; evo reads them beside
    ``groundtruth.tum``). Frames without a position (an RF fix that failed) are left out; algorithms that estimate
    no orientation carry the identity, and their header says so."""
    out.mkdir(parents=True, exist_ok=True)
    for name, pos in est.items():
        ok = np.isfinite(pos).all(axis=1)
        res = with_cov.get(name)
        rot = res.rotations_w_c[np.nonzero(ok)[0]] if res is not None else Rotation.identity(int(ok.sum()))
        write_tum(out / f"{name}.tum", stamps_s[ok], pos[ok], rot,
                  world="body frame" if res is not None else "body frame; orientation not estimated: identity")


def consistency(positions_w_m: np.ndarray, cov_m2: np.ndarray, truth_w_m: np.ndarray) -> dict:
    """How honest a position's stated uncertainty is, per frame: NEES ``e^T C^-1 e`` (3 on average for an honest
    filter), whether the error is inside the 68.3% ellipsoid, and the fraction of the three axes with
    ``|e_i| <= sigma_i`` (0.683 expected)."""
    e = positions_w_m - truth_w_m
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(cov_m2, e[..., None])[..., 0])
    sd = np.sqrt(np.maximum(np.diagonal(cov_m2, axis1=1, axis2=2), 1e-30))
    return {"nees": nees, "inside_68": nees <= CHI2_3_683, "axis_inside_1sigma": np.mean(np.abs(e) <= sd, axis=1)}


def nees_band(nees_runs: list[np.ndarray], dof: int = 3, level: float = 0.95) -> dict:
    """The chi-square test of a filter's NEES over ``N`` Monte Carlo runs (Bar-Shalom, Li and Kirubarajan 2001,
    Sec. 5.4.2): at each frame the runs' mean NEES times ``N`` is chi-square with ``N dof`` degrees of freedom if the
    stated covariances are honest, so the mean lies inside ``[chi2_lo(N dof) / N, chi2_hi(N dof) / N]`` (two-sided,
    ``level``) on about ``level`` of the frames. Returns the band, the frames whose mean is inside it, below it
    (too cautious) and above it (over-sure), over the frames every run has (``N`` the runs; frames with a
    non-finite NEES in some run are left out)."""
    n = min(len(v) for v in nees_runs)
    a = np.stack([np.asarray(v[:n], float) for v in nees_runs])
    a = a[:, np.isfinite(a).all(axis=0)]
    runs = len(a)
    lo, hi = (float(chi2.ppf(q, runs * dof) / runs) for q in ((1 - level) / 2, (1 + level) / 2))
    mean = a.mean(axis=0)
    return {"runs": runs, "band": [round(lo, 3), round(hi, 3)], "level": level,
            "frames_inside": float(np.mean((mean >= lo) & (mean <= hi))) if mean.size else float("nan"),
            "frames_below": float(np.mean(mean < lo)) if mean.size else float("nan"),
            "frames_above": float(np.mean(mean > hi)) if mean.size else float("nan")}


def orientation_consistency(rotations_w_c: Rotation, cov_rad2: np.ndarray, truth_w_c: Rotation) -> dict:
    """The same for the orientation, per frame: the error in the filter's convention (``R_true = R_est Exp(e)``, ``e``
    in the camera frame: :class:`bodyslam.fusion.ekf.ErrorStateEkf`), its NEES against the stated orientation
    covariance, and whether it is inside the 68.3% ellipsoid. An error of tens of degrees is beyond the
    linearisation; it is counted as it is."""
    e = (rotations_w_c.inv() * truth_w_c).as_rotvec()
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(cov_rad2, e[..., None])[..., 0])
    return {"orientation_nees": nees, "orientation_inside_68": nees <= CHI2_3_683}


def orientation_errors_deg(est_w_c: Rotation, truth_w_c: Rotation) -> np.ndarray:
    """``(3, n)`` per-frame orientation errors (deg): the whole rotation's angle, the angle between the estimated
    and the true optical axes, and the roll about the optical axis (the error rotation's twist about camera z)."""
    whole = np.degrees((est_w_c.inv() * truth_w_c).magnitude())
    za, zb = est_w_c.apply([0.0, 0.0, 1.0]), truth_w_c.apply([0.0, 0.0, 1.0])
    axis = np.degrees(np.arccos(np.clip(np.sum(za * zb, axis=1), -1.0, 1.0)))
    q = (truth_w_c.inv() * est_w_c).as_quat()
    roll = np.degrees(2.0 * np.arctan2(np.abs(q[:, 2]), np.abs(q[:, 3])))
    return np.stack([whole, axis, np.minimum(roll, 360.0 - roll)])


def _orientation_stats(e_deg: np.ndarray) -> dict:
    """Mean and p90 of the whole orientation error, means of its parts (rows of :func:`orientation_errors_deg`)."""
    return {"mean": float(e_deg[0].mean()), "p90": float(np.percentile(e_deg[0], 90)),
            "axis_mean": float(e_deg[1].mean()), "roll_mean": float(e_deg[2].mean())}


def _measured_step_noise(steps, gt, grot) -> tuple[np.ndarray, np.ndarray]:
    """Process noise for the bound from the vision's *actual* errors on this run (scoring may use the truth):
    RMS translation and rotation error of the estimated steps, and for steps without an estimate the RMS of
    the true step itself (a filter knows nothing of it; a ``rotation`` step's rotation: its own RMS error). The
    filter's own noise settings are floors chosen for robustness; a bound built on them would not bound the real
    errors."""
    t_true = np.array([grot[k].inv().apply(gt[k + 1] - gt[k]) for k in range(len(gt) - 1)])
    R_true = [grot[k].inv() * grot[k + 1] for k in range(len(gt) - 1)]
    ok = np.array([s.has_estimate for s in steps])
    poses = [step_pose(s) for s in steps]
    et = np.array([np.linalg.norm(t - t_true[k]) for k, (_, t) in enumerate(poses)])
    er = np.array([(R.inv() * R_true[k]).magnitude() for k, (R, _) in enumerate(poses)])
    sig_t = np.full(len(steps), 1e-3)
    sig_r = np.full(len(steps), 1e-2)
    for group in (ok & ~np.array([s.bridged for s in steps]), np.array([s.bridged for s in steps])):
        if group.any():  # measured steps and bridged shares of gaps, each with its own RMS error
            sig_t[group] = np.sqrt(np.mean(et[group] ** 2) / 3)
            sig_r[group] = np.sqrt(np.mean(er[group] ** 2) / 3)
    if (~ok).any():
        sig_t[~ok] = np.sqrt(np.mean(np.sum(t_true[~ok] ** 2, axis=1)) / 3)
        rot = np.array([s.has_rotation for s in steps]) & ~ok  # rotation steps: their rotation's own RMS error
        none = ~ok & ~rot
        if rot.any():
            sig_r[rot] = np.sqrt(np.mean(er[rot] ** 2) / 3)
        if none.any():
            sig_r[none] = np.sqrt(np.mean([R_true[k].magnitude() ** 2 for k in np.nonzero(none)[0]]) / 3)
    return sig_t, sig_r


def _step_weighted(blocks: list[dict], key: str) -> float | None:
    """The mean of ``key`` over the seeds' score blocks that have it, weighted by their steps (None: none has it)."""
    have = [b for b in blocks if key in b and b.get("n_steps_scored")]
    n = sum(b["n_steps_scored"] for b in have)
    return sum(b[key] * b["n_steps_scored"] for b in have) / n if n else None


def _rotation_summary(blocks: list[dict]) -> dict:
    """The seeds' ``rotation_only`` blocks (:func:`testbed.score.score_motion`) as one: step-weighted means."""
    blocks = [b for b in blocks if b.get("n_steps_scored")]
    n = sum(b["n_steps_scored"] for b in blocks)
    if not n:
        return {"n_steps_scored": 0}
    out = {"n_steps_scored": n}
    for k in ("mean_true_roll_deg", "mae_roll_deg", "mean_true_tilt_deg", "mae_tilt_deg"):
        out[k] = _step_weighted(blocks, k)
    out["rms_roll_error_deg"] = float(np.sqrt(sum(b["rms_roll_error_deg"] ** 2 * b["n_steps_scored"]
                                                  for b in blocks) / n))
    stated = _step_weighted(blocks, "rotation_within_68pct")  # over the steps that state a rotation 1-sigma
    if stated is not None:
        out["rotation_within_68pct"] = stated
    return out


def _beside_wall_summary(blocks: list[dict], n_measured: int) -> dict:
    """The seeds' ``beside_wall_only`` blocks (:func:`testbed.score.score_motion`: steps whose tube fit put the
    camera beside its own cylinder's wall) as one, step-weighted, with their share of the ``n_measured`` steps
    measured from their own pair."""
    n = sum(b.get("n_steps_scored", 0) for b in blocks)
    out = {"n_steps_scored": n, "share_of_measured": n / n_measured if n_measured else 0.0}
    for k in ("mae_distance_cm", "mae_roll_deg", "mae_tilt_deg", "distance_within_1sigma", "rotation_within_68pct"):
        v = _step_weighted(blocks, k)
        if v is not None:
            out[k] = v
    return out


def _beside_wall_html(bw: dict) -> str:
    """The report page's line on the steps fitted beside the wall ("" when there are none)."""
    if not bw.get("n_steps_scored"):
        return ""
    return (f"<p>Steps fitted beside the wall of their own tube (beside_wall: motion kept, 1-sigma widened): "
            f"{bw['n_steps_scored']} ({bw['share_of_measured']:.0%} of the measured), distance error "
            f"{bw['mae_distance_cm']:.4f} cm, roll {bw['mae_roll_deg']:.2f} deg, tilt {bw['mae_tilt_deg']:.2f} deg"
            + (f"; inside their 1-sigma: {bw['distance_within_1sigma']:.0%}" if "distance_within_1sigma" in bw
               else "") + ".</p>")


def _rotation_html(rot: dict) -> str:
    """The report page's line on the steps with only their rotation measured ("" when there are none)."""
    if not rot.get("n_steps_scored"):
        return ""
    return (f"<p>Steps with only their rotation measured (status rotation or rotation_slow, distance unknown): "
            f"{rot['n_steps_scored']}, roll error {rot['mae_roll_deg']:.2f} deg mean "
            f"({rot['rms_roll_error_deg']:.2f} RMS; their true roll {rot['mean_true_roll_deg']:.2f} deg), "
            f"tilt error {rot['mae_tilt_deg']:.2f} deg (true {rot['mean_true_tilt_deg']:.2f})"
            + (f"; inside their stated 68% radius: {rot['rotation_within_68pct']:.0%}" if "rotation_within_68pct" in rot
               else "") + ".</p>")


def _stats(e_m: np.ndarray, pcrb_m2: np.ndarray) -> dict:
    """Error statistics over the frames an algorithm gave a position for (RF only: frames with a fix); how many it
    gave none for is counted."""
    ok = np.isfinite(e_m)
    e = e_m[ok] * 100
    rmse = float(np.sqrt(np.mean(e**2)))
    out = {"mean_error_cm": float(e.mean()), "rmse_cm": rmse, "median_error_cm": float(np.median(e)),
           "p90_error_cm": float(np.percentile(e, 90)), "max_error_cm": float(e.max()),
           "rmse_over_sqrt_pcrb": rmse / float(np.sqrt(pcrb_m2[ok].mean()) * 100)}
    if not ok.all():
        out["frames_without_position"] = int((~ok).sum())
    return out


def _run_seed(args) -> dict:
    """One evaluation run (a worker's task): render, motion from the frames, every algorithm, scores."""
    import time

    from threadpoolctl import threadpool_limits

    scenario, seed, d, n_frames, render_jobs, motion_jobs, keep, reuse = args
    d = Path(d)
    t0 = time.perf_counter()
    reused = reuse and _reusable(d)
    if not reused:
        with threadpool_limits(1 if render_jobs == 1 else None):  # a worker among others: one BLAS/OpenMP thread
            simulate(scenario, seed, d, n_frames=n_frames, jobs=render_jobs, force=True)
    t1 = time.perf_counter()
    if not reused:
        cmd = [sys.executable, "-m", "bodyslam.cli", "motion", str(d), "--out", str(d / "motion.csv")]
        if motion_jobs:
            cmd += ["--jobs", str(motion_jobs)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode not in (0, 3):  # 3: done, with bad frames listed
            raise RuntimeError(f"bodyslam motion failed on seed {seed}: {r.stderr.strip()}")
    t2 = time.perf_counter()
    res = evaluate_sequence(d, rf_channel(scenario))
    t3 = time.perf_counter()
    if not keep and not reused:  # frames this run did not render are not its to delete
        for sub in ("frames", "depth"):
            p = d / sub
            if p.is_dir():
                for f in p.iterdir():
                    f.unlink()
                p.rmdir()
    res["seconds"] = {"render": t1 - t0, "motion": t2 - t1, "filters_and_scoring": t3 - t2}
    res["seed"] = seed
    return res


def _reusable(d: Path) -> bool:
    """A seed's directory holds an earlier run ``--reuse`` can score again: its sequence and motion.csv."""
    return (d / "meta.json").is_file() and (d / "motion.csv").is_file()


def evaluate(scenario: dict, seeds: list[int], out_dir: str | os.PathLike, n_frames: int | None = None,
             force: bool = False, keep: bool = False, progress: Callable[[str], None] | None = None,
             jobs: int | None = 1, reuse: bool = False) -> dict:
    """Evaluate every algorithm over ``seeds`` (module docstring). ``jobs``: seeds run in parallel worker
    processes (each renders and estimates with one core); ``1``: seeds one after another, each using every
    core for rendering and motion. ``reuse``: a seed whose directory in ``out_dir`` already holds a sequence
    and its ``motion.csv`` is scored again without rendering or motion; the others are rendered and run (listed
    through ``progress``).

    Raises
    ------
    InputError
        ``reuse`` where no seed's directory holds an earlier run (checked before any work: rendering every seed
        is not what was asked).
    """
    import time

    from bodyslam.parallel import available_cores, imap_tasks

    out = Path(out_dir)
    if reuse:
        missing = [s for s in seeds if not _reusable(out / "sequences" / f"seed_{s}")]
        if len(missing) == len(seeds):
            raise InputError(f"--reuse: {out / 'sequences'} holds no earlier run of seed(s) {_seed_text(seeds)} "
                             f"(each needs seed_N/meta.json and seed_N/motion.csv); run without --reuse to render "
                             f"and run them")
        if missing and progress:
            progress(f"--reuse: no earlier run of seed(s) {_seed_text(missing)} in {out / 'sequences'}: "
                     f"rendered and run")
    prepare_output_dir(out, force)
    jobs = available_cores() if jobs is None else max(1, int(jobs))
    jobs = min(jobs, len(seeds))
    per_seed, errs, pcrbs, motion, timing, eff = [], {a: [] for a in ALGORITHMS}, [], [], [], []
    step_counts: dict[str, int] = {}
    rot_blocks: list[dict] = []
    beside_blocks: list[dict] = []
    paths: list[dict] = []
    lumen: list[dict] = []
    cons: dict[str, list] = {}
    orient: dict[str, list] = {}
    sm, sm_eff = [], []
    first = None
    t_start = time.perf_counter()
    tasks = [(scenario, seed, str(out / "sequences" / f"seed_{seed}"), n_frames, 1 if jobs > 1 else None,
              1 if jobs > 1 else None, keep, reuse) for seed in seeds]
    for res in imap_tasks(_run_seed, tasks, jobs):
        seed = res["seed"]
        first = first or res
        for a in ALGORITHMS:
            errs[a].append(res["errors"][a])
        pcrbs.append(res["pcrb_m2"])
        eff.append(res["pcrb_mean_error_m"])
        for a, c in res["consistency"].items():
            cons.setdefault(a, []).append(c)
            orient.setdefault(a, []).append(res["orientation_error_deg"][a])
        sm.append(res["smoothing_bound_m2"])
        sm_eff.append(res["smoothing_bound_mean_error_m"])
        motion.append(res["motion"]["all"])
        rot_blocks.append(res["motion"].get("rotation_only", {}))
        beside_blocks.append(res["motion"].get("beside_wall_only", {}))
        paths.append(res["path_travelled"])
        lumen.append(res["lumen_scale"])
        for st, c in res["motion"]["status_counts"].items():
            step_counts[st] = step_counts.get(st, 0) + c
        timing.append(res["seconds"])
        per_seed.append({"seed": seed, **{a: _stats(res["errors"][a], res["pcrb_m2"]) for a in ALGORITHMS},
                         "sqrt_mean_pcrb_cm": float(np.sqrt(res["pcrb_m2"].mean()) * 100),
                         "covariance_inflation_kappa": {k: round(v, 3) for k, v in res["kappa"].items()},
                         # this run's NEES and 1-sigma coverage (the run-to-run spread behind the means)
                         "consistency": {a: {"mean_nees": round(float(np.mean(c["nees"])), 3),
                                             "inside_68pct_ellipsoid": round(float(np.mean(c["inside_68"])), 4),
                                             "orientation_inside_68pct_ellipsoid":
                                                 round(float(np.mean(c["orientation_inside_68"])), 4)}
                                         for a, c in res["consistency"].items()},
                         "path_travelled": {k: round(v, 5) for k, v in res["path_travelled"].items()},
                         "lumen_scale": {"factor": round(lumen[-1]["factor"], 4), "samples": lumen[-1]["samples"],
                                         "steps_tried": lumen[-1]["steps_tried"],
                                         "steps_chained": lumen[-1]["steps_chained"],
                                         "factor_sd_rel": (None if lumen[-1]["factor_sd_rel"] is None
                                                           else round(lumen[-1]["factor_sd_rel"], 4)),
                                         "distance_scale_after": round(res["motion"]["all"].get("distance_scale",
                                                                                                math.nan), 4)},
                         "orientation_error_deg": {a: {k: round(v, 2) for k, v in _orientation_stats(e).items()}
                                                   for a, e in res["orientation_error_deg"].items()},
                         "seconds": {k: round(v, 2) for k, v in res["seconds"].items()}})
        if progress:
            progress(f"seed {seed} ({len(per_seed)}/{len(seeds)}): Body-SLAM smoothed "
                     f"{per_seed[-1]['ekf_rss_rts']['mean_error_cm']:.2f} cm, EKF "
                     f"{per_seed[-1]['ekf_rss']['mean_error_cm']:.2f} cm, RF only "
                     f"{per_seed[-1]['rf_ml']['mean_error_cm']:.2f} cm")
    pc = np.concatenate(pcrbs)
    report = {
        "scenario": scenario.get("name"), "seeds": list(seeds), "n_runs": len(seeds),
        "frames_per_run": int(len(pcrbs[0])),
        "algorithms": {a: _stats(np.concatenate(errs[a]), pc) for a in ALGORITHMS},
        "sqrt_mean_pcrb_cm": float(np.sqrt(pc.mean()) * 100),
        # the mean error of a causal filter that attains the bound (testbed.bound.efficient_mean_error)
        "pcrb_mean_error_cm": float(np.concatenate(eff).mean() * 100),
        # the smoother's reference: the bound of smoothing (testbed.bound.smoothing_bound_positions)
        "smoothing_bound": {
            "sqrt_mean_cm": float(np.sqrt(np.concatenate(sm).mean()) * 100),
            "mean_error_cm": float(np.concatenate(sm_eff).mean() * 100),
            **{f"{name}_rmse_over_sqrt_bound": float(np.sqrt(np.mean(np.concatenate(errs[a]) ** 2))
                                                      / np.sqrt(np.concatenate(sm).mean()))
               for name, a in (("rts", "ekf_rss_rts"), ("rts_plain", "ekf_rss_rts_plain"),
                               ("rts_bias", "ekf_rss_bias_rts"))}},
        # Table 4.1, and whether the per-step 1-sigma holds (distance_within_1sigma: 0.683 if honest)
        # (distance_scale: each run's best factor, testbed.score; its mean over the runs)
        "table_4_1": {k: float(np.nanmean([m.get(k, np.nan) for m in motion])) for k in motion[0]
                      if k.endswith(("_cm", "_deg", "sigma", "_68pct")) or k == "distance_scale"},
        # what became of every step over all seeds (bodyslam.steps.StepStatus), and the fractions with an estimate:
        # measured from the pair (ok, wall), with the bridged gaps' shares, and with the rotation steps
        "step_status_counts": dict(sorted(step_counts.items())),
        "rotation_steps": _rotation_summary(rot_blocks),
        "beside_wall_steps": _beside_wall_summary(beside_blocks, sum(m.get("n_steps_scored", 0) for m in motion)),
        **{f"steps_{name}_frac": sum(step_counts.get(k, 0) for k in which) / max(sum(step_counts.values()), 1)
           for name, which in (("measured", MEASURED), ("with_estimate", WITH_ESTIMATE),
                               ("with_rotation", WITH_ROTATION))},
        # honest uncertainty: NEES (3 expected), frames inside the 68.3% ellipsoid, axes inside 1-sigma (0.683)
        "consistency": {a: {"mean_nees": float(np.concatenate([c["nees"] for c in v]).mean()),
                            "inside_68pct_ellipsoid": float(np.concatenate([c["inside_68"] for c in v]).mean()),
                            "axis_inside_1sigma": float(np.concatenate([c["axis_inside_1sigma"] for c in v]).mean()),
                            # the orientation's stated 1-sigma (orientation_consistency): 0.683 if honest
                            "orientation_inside_68pct_ellipsoid":
                                float(np.concatenate([c["orientation_inside_68"] for c in v]).mean()),
                            # the runs' mean NEES per frame against its chi-square band (nees_band; 0.95 if honest)
                            "nees_chi2": nees_band([c["nees"] for c in v]),
                            "orientation_nees_chi2": nees_band([c["orientation_nees"] for c in v])}
                        for a, v in cons.items()},
        # what the stated covariances were scaled by: the RSS residuals' variance inflation factor (1: independent)
        "covariance_inflation_kappa": {k: float(np.mean([p["covariance_inflation_kappa"][k] for p in per_seed]))
                                       for k in per_seed[0]["covariance_inflation_kappa"]},
        # the whole rotation's error, and its parts: the optical axis's direction, the roll about the axis
        "orientation_error_deg": {a: _orientation_stats(np.concatenate(v, axis=1)) for a, v in orient.items()},
        # how far along the gut (vision only, the figure marks and plots give): testbed.score.score_path
        "path_travelled": _path_summary(paths),
        # the lumen scale seen in the frames, run by run (bodyslam.vision.lumen_scale)
        "lumen_scale": _lumen_summary(lumen),
        "per_seed": per_seed,
        "seconds": {"wall": round(time.perf_counter() - t_start, 2), "jobs": jobs,
                    **{f"{k}_total": round(sum(t[k] for t in timing), 2) for k in timing[0]}},
        "notes": "errors per frame against groundtruth.tum; PCRB bounds causal filtering (paper 000 Eq. 28-29); "
                 "RTS smoothing and its whole-exam refinement use future readings and may go below it"
                 + ("; this scenario's RF channel departs from the calibration ([rf.channel]): the bounds are "
                    "built on the true channel (correlated shadowing; per-sensor path-loss and placement offsets as "
                    "unknowns with their priors; dropouts and outliers left out, which only lowers a bound)"
                    if not rf_channel(scenario).ideal else ""),
    }
    write_json(out / "report.json", report)
    _plots(out, first, errs)
    _html(out, report, _view(first))
    return report


def _band_cell(b: dict | None) -> str:
    """A :func:`nees_band` result as one table cell: inside (below / above); the band is the header's."""
    return f"{b['frames_inside']:.2f} ({b['frames_below']:.2f} / {b['frames_above']:.2f})" if b else "--"


def _lumen_summary(lumen: list[dict]) -> dict:
    """The runs' lumen scales (:func:`bodyslam.vision.lumen_scale.exam_scale` of their steps): on how many runs one
    was applied (enough ratios: a radius prior, the tube estimator, a run long enough), its factor over those runs,
    and the ratios behind it."""
    f = np.array([x["factor"] for x in lumen if x["factor"] != 1.0])
    return {"runs": len(lumen), "runs_applied": int(len(f)),
            "factor_mean": float(f.mean()) if len(f) else None, "factor_min": float(f.min()) if len(f) else None,
            "factor_max": float(f.max()) if len(f) else None,
            # the applied factors' stated relative 1-sigma (bodyslam.vision.lumen_scale.exam_scale_sd_rel)
            "factor_sd_rel_mean": (float(np.mean(sds)) if (sds := [x["factor_sd_rel"] for x in lumen
                                                                   if x.get("factor_sd_rel") is not None]) else None),
            "samples_mean": float(np.mean([x["samples"] for x in lumen])),
            # steps a run whose scale was tied to their neighbours' (bodyslam.vision.scale_chain)
            "steps_chained_mean": float(np.mean([x.get("steps_chained", 0) for x in lumen]))}


def _lumen_html(sc: dict | None, distance_scale: float | None) -> str:
    """The report page's line on the lumen scale ("" for a report written before it, or where no run measured
    one)."""
    if not sc or not sc["samples_mean"]:
        return ""
    text = (f"<p>Lumen scale seen in the frames (a tube with one contraction ring against the cylinder, "
            f"bodyslam.vision.lumen_scale): applied on {sc['runs_applied']} of {sc['runs']} runs")
    if sc["runs_applied"]:
        text += (f", the steps x{sc['factor_mean']:.3f} on average ({sc['factor_min']:.3f} to "
                 f"{sc['factor_max']:.3f}" + (f"; stated 1-sigma {100 * sc['factor_sd_rel_mean']:.0f}% on average"
                                               if sc.get("factor_sd_rel_mean") else "") + ")")
    text += f", from {sc['samples_mean']:.0f} ratios a run on average"
    if sc.get("steps_chained_mean"):
        text += (f"; {sc['steps_chained_mean']:.0f} steps a run had their scale tied to their neighbours' "
                 f"(bodyslam.vision.scale_chain)")
    if distance_scale is not None and math.isfinite(distance_scale):
        text += f"; the factor that would still fit the steps best to the truth: {distance_scale:.3f} (mean over runs)"
    return text + ".</p>"


def _path_summary(paths: list[dict]) -> dict:
    """The runs' path-travelled scores (:func:`testbed.score.score_path`) as one: the error at each run's end in
    percent of the true path (mean, mean absolute, the largest absolute), the runs whose end is inside its stated
    1-sigma and 2-sigma (0.683 and 0.954 if honest), and the frames inside 1-sigma over all runs."""
    e = np.array([p["error_rel"] for p in paths]) * 100
    z = np.abs([p["z"] for p in paths])
    return {"true_mean_cm": float(np.mean([p["true_m"] for p in paths]) * 100),
            "end_error_mean_pct": float(np.mean(e)), "end_error_mean_abs_pct": float(np.mean(np.abs(e))),
            "end_error_max_abs_pct": float(np.max(np.abs(e))),
            "runs_inside_1sigma": float(np.mean(z <= 1.0)), "runs_inside_2sigma": float(np.mean(z <= 2.0)),
            "frames_inside_1sigma": float(np.mean([p["frames_inside_1sigma"] for p in paths]))}


LABELS = {"rf_ml": "RF only (ML)", "rf_nls": "RF only (NLS, Eq. 3.36)", "dead_reckoning": "dead reckoning",
          "thesis_kf": "dissertation's KF (Eq. 3.26-3.38) on NLS fixes", "thesis_kf_ml": "dissertation's KF on ML fixes",
          "ekf_fixes": "EKF on RF fixes",
          "ekf_rss": "EKF on RSS (online; start aligned on the first 40-80 frames' fixes)",
          "ekf_rss_causal": "EKF on RSS (strictly causal: frame k sees frames 0..k)",
          "ekf_rss_rts_plain": "EKF on RSS + RTS smoother, not refined (offline)",
          "ekf_rss_rts": "EKF on RSS + RTS smoother + whole-exam refinement (offline; shipped)",
          "ekf_rss_bias": "EKF on RSS with per-sensor bias states (online; opt-in --rss-bias-states)",
          "ekf_rss_bias_rts": "the same + RTS smoother + whole-exam refinement (offline; opt-in)"}
# the plots' legends
SHORT = {"rf_ml": "RF only", "rf_nls": "RF only (NLS)", "dead_reckoning": "vision only (dead reckoning)",
         "ekf_fixes": "EKF on RF fixes", "ekf_rss": "Body-SLAM online", "ekf_rss_causal": "Body-SLAM strictly causal",
         "ekf_rss_rts": "Body-SLAM smoothed", "ekf_rss_rts_plain": "RTS, not refined", "thesis_kf": "dissertation's KF",
         "thesis_kf_ml": "dissertation's KF (ML)", "ekf_rss_bias": "Body-SLAM online, bias states",
         "ekf_rss_bias_rts": "Body-SLAM smoothed, bias states"}


def _path_html(p: dict | None) -> str:
    """The path-travelled paragraph of the HTML page (empty for a report written before it was scored)."""
    if not p:
        return ""
    return ("<h2>How far along the gut (path travelled, vision only)</h2>"
            f"<p>True path {p['true_mean_cm']:.1f} cm per run on average. Error at the run's end: "
            f"{p['end_error_mean_pct']:+.1f}% mean, {p['end_error_mean_abs_pct']:.1f}% mean absolute, "
            f"{p['end_error_max_abs_pct']:.1f}% at most. Runs whose end is inside its stated 1-sigma: "
            f"{p['runs_inside_1sigma']:.0%} (2-sigma: {p['runs_inside_2sigma']:.0%}); frames inside 1-sigma: "
            f"{p['frames_inside_1sigma']:.0%} (68% if the 1-sigma is honest).</p>")


def _html(out: Path, report: dict, view_html: str = "") -> None:
    """``report.html``: the tables, the 3-D view ``view_html`` and the plots, one self-contained page next to
    report.json."""
    from testbed.htmlpage import table, write_report_page

    # each algorithm against its own bound: offline smoothing against the smoothing bound, the rest the PCRB
    sb = report["smoothing_bound"]
    smoothers = {"ekf_rss_rts": sb["rts_rmse_over_sqrt_bound"],
                 "ekf_rss_rts_plain": sb.get("rts_plain_rmse_over_sqrt_bound", float("nan")),
                 "ekf_rss_bias_rts": sb.get("rts_bias_rmse_over_sqrt_bound", float("nan"))}
    own = {k: smoothers.get(k, v["rmse_over_sqrt_pcrb"]) for k, v in report["algorithms"].items()}
    rows = [[LABELS[k], f"{v['mean_error_cm']:.2f}", f"{v['rmse_cm']:.2f}", f"{v['median_error_cm']:.2f}",
             f"{v['p90_error_cm']:.2f}", f"{v['rmse_over_sqrt_pcrb']:.2f}", f"{own[k]:.2f}"]
            for k, v in report["algorithms"].items()]
    band = next(iter(report["consistency"].values()), {}).get("nees_chi2")  # one band: every filter has N runs
    crows = [[LABELS[k], f"{v['mean_nees']:.2f}", _band_cell(v.get("nees_chi2")),
              f"{v['inside_68pct_ellipsoid']:.2f}", f"{v['axis_inside_1sigma']:.2f}",
              *(f"{report['orientation_error_deg'][k].get(c, float('nan')):.1f}"
                for c in ("mean", "p90", "axis_mean", "roll_mean")),
              f"{v.get('orientation_inside_68pct_ellipsoid', float('nan')):.2f}",
              _band_cell(v.get("orientation_nees_chi2"))]
             for k, v in report["consistency"].items()]
    body = (table(["algorithm", "mean (cm)", "RMSE (cm)", "median (cm)", "p90 (cm)", "RMSE / sqrt(PCRB)",
                   "RMSE / sqrt(its bound)"], rows)
            + "<h2>Is the stated uncertainty honest? Orientation</h2>"
            + table(["algorithm", "mean NEES (3 if honest)",
                     "frames whose runs' mean NEES is inside its 95% chi-square band"
                     + (" [{:.2f}, {:.2f}]".format(*band["band"]) if band else "") + " (0.95 if honest; below / above)",
                     "inside the 68% ellipsoid", "axes inside 1-sigma (0.68)",
                     "orientation error mean (deg)", "p90 (deg)", "optical axis mean (deg)", "roll mean (deg)",
                     "orientation inside its 68% ellipsoid", "the same chi-square test, orientation"], crows)
            + "<p>Covariances are scaled by the RSS residuals' measured correlation (kappa, 1 on an independent "
              f"channel): mean kappa {report['covariance_inflation_kappa']['smoothed']:.2f} (smoother, each lag "
              "weighted by its two-sided memory; the whole run's readings: "
              f"{report['covariance_inflation_kappa'].get('whole_run', float('nan')):.2f}), "
              f"{report['covariance_inflation_kappa']['online_last_frame']:.2f} (online filter at the last frame). "
              "The whole-exam refinement's orientation takes kappa on the readings' share of its information only "
              "(bodyslam.fusion.refine.stated_covariances).</p>"
            + "<h2>Per-step motion (Table 4.1)</h2>"
            + table(["figure", "value"], [[k, f"{v:.4f}"] for k, v in report["table_4_1"].items()])
            + (f"<p>Steps measured from their own pair (ok, wall): {report['steps_measured_frac']:.1%}; with the "
               f"bridged gaps' shares: {report['steps_with_estimate_frac']:.1%}; with at least a rotation "
               f"(status rotation too): {report.get('steps_with_rotation_frac', float('nan')):.1%}. What became "
               "of every step: "
               + ", ".join(f"{k} {v}" for k, v in report["step_status_counts"].items()) + ".</p>"
               if "step_status_counts" in report else "")
            + _rotation_html(report.get("rotation_steps", {}))
            + _beside_wall_html(report.get("beside_wall_steps", {}))
            + _path_html(report.get("path_travelled"))
            + _lumen_html(report.get("lumen_scale"), report["table_4_1"].get("distance_scale"))
            + view_html + "<h2>Plots (Fig. 4.20-4.24)</h2>")
    write_report_page(out, report["scenario"], f"{report['n_runs']} runs (seeds {_seed_text(report['seeds'])}), "
                      f"{report['frames_per_run']} frames each; errors per frame against the ground truth. "
                      f"sqrt(mean PCRB) = {report['sqrt_mean_pcrb_cm']:.2f} cm; mean error of a causal filter that attains "
                      f"the bound: {report['pcrb_mean_error_cm']:.2f} cm; the smoothing bound: sqrt(mean) "
                      f"{report['smoothing_bound']['sqrt_mean_cm']:.2f} cm, a smoother at it "
                      f"{report['smoothing_bound']['mean_error_cm']:.2f} cm mean (the table's last column: the two "
                      f"smoothers against the smoothing bound, every other algorithm against the PCRB). "
                      f"{report['notes'][:1].upper() + report['notes'][1:]}.", body,
                      PLOT_FILES)


def _seed_text(seeds: list[int]) -> str:
    if seeds and seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


PLOT_FILES = ["trajectory.png", "error_vs_time.png", "error_cdf.png", "error_histogram.png"]
# the plots' colours per algorithm (RGB)
_COLOURS = {"rf_ml": (170, 170, 170), "dead_reckoning": (44, 160, 44), "ekf_rss": (31, 119, 180),
            "ekf_rss_causal": (148, 103, 189), "ekf_rss_rts": (214, 39, 40), "truth": (0, 0, 0)}


def _plots(out: Path, first: dict, errs: dict) -> None:
    """The evaluation's PNGs (:data:`PLOT_FILES`): the first seed's trajectories in 3-D and three projections
    against the truth with the smoother's 1-sigma; its error against time beside the matching bound (the online
    filter against the PCRB of causal filtering, the smoother against the smoothing bound); the error CDF and the
    smoother's error histogram over all seeds."""
    from bodyslam.plots import trajectory_figure

    t = first["stamps_s"]
    img = trajectory_figure(f"Seed {first['seed']}: where the capsule was, estimated and true (body frame)",
                            _first_seed_paths(first))
    write_image(out / "trajectory.png", img)
    f = Figure(f"Seed {first['seed']}: position error against time, with the matching bound", "time (s)",
               "position error (cm)", size=(900, 460))
    f.line(t, first["errors"]["rf_ml"] * 100, SHORT["rf_ml"], _COLOURS["rf_ml"], width=1)
    f.line(t, first["errors"]["ekf_rss"] * 100, SHORT["ekf_rss"], _COLOURS["ekf_rss"], width=1.6)
    f.line(t, np.sqrt(first["pcrb_m2"]) * 100, "bound of online filtering (sqrt PCRB)", _COLOURS["ekf_rss"], width=1,
           dashed=True)
    f.line(t, first["errors"]["ekf_rss_rts"] * 100, SHORT["ekf_rss_rts"], _COLOURS["ekf_rss_rts"], width=1.6)
    f.line(t, np.sqrt(first["smoothing_bound_m2"]) * 100, "bound of smoothing", _COLOURS["ekf_rss_rts"], width=1,
           dashed=True)
    write_image(out / "error_vs_time.png", f.image())
    f = Figure("Position error CDF, all seeds and frames", "position error (cm)", "fraction of frames at or below",
               size=(760, 460))
    for name in ("rf_ml", "dead_reckoning", "ekf_rss_causal", "ekf_rss", "ekf_rss_rts"):
        e = np.concatenate(errs[name])
        x = np.sort(e[np.isfinite(e)] * 100)  # frames without an RF fix have no RF error
        f.line(x, np.arange(1, len(x) + 1) / max(len(x), 1), SHORT[name], _COLOURS[name], step=True, width=1.6)
    write_image(out / "error_cdf.png", f.image())
    e_fused = np.concatenate(errs["ekf_rss_rts"]) * 100
    edges = np.linspace(0, max(float(np.percentile(e_fused, 99)), 1.0), 31)
    h, _ = np.histogram(np.clip(e_fused, 0, edges[-1]), bins=edges, density=True)
    write_image(out / "error_histogram.png",
                Figure(f"{SHORT['ekf_rss_rts']}: position error histogram, all seeds", "position error (cm)",
                       "density (1/cm)", size=(640, 420)).bars(edges, h, colour=_COLOURS["ekf_rss_rts"]).image())


def _view(first: dict) -> str:
    """The first seed's 3-D view for the page (:func:`bodyslam.report.view_3d`)."""
    from bodyslam.report import view_3d

    return f"<h2>Seed {first['seed']} in 3-D</h2>" + view_3d(_first_seed_paths(first), stamps_s=first["stamps_s"])


def _first_seed_paths(first: dict) -> list:
    """What the trajectory plot and the 3-D view draw of the first seed: the smoother with its 1-sigma, the truth,
    the online filter and the RF fixes."""
    from bodyslam.plots import Path3D

    est = first["estimates"]
    return [Path3D(SHORT["ekf_rss_rts"], est["ekf_rss_rts"], _COLOURS["ekf_rss_rts"], 1.8,
                   first["cov_m2"]["ekf_rss_rts"]),
            Path3D("truth", first["truth"], _COLOURS["truth"], 1.2),
            Path3D(SHORT["ekf_rss"], est["ekf_rss"], _COLOURS["ekf_rss"], 1.0),
            Path3D(SHORT["rf_ml"], est["rf_ml"], _COLOURS["rf_ml"], 0.8)]


def main_report_line(report: dict) -> str:
    a = report["algorithms"]
    return (f"{report['n_runs']} runs of {report['scenario']}: mean error RF only {a['rf_ml']['mean_error_cm']:.2f} cm, "
            f"dead reckoning {a['dead_reckoning']['mean_error_cm']:.2f}, thesis KF {a['thesis_kf']['mean_error_cm']:.2f}"
            f", EKF {a['ekf_rss']['mean_error_cm']:.2f} (strictly causal {a['ekf_rss_causal']['mean_error_cm']:.2f}), "
            f"Body-SLAM smoothed (RTS + refinement) {a['ekf_rss_rts']['mean_error_cm']:.2f} cm; "
            f"sqrt(PCRB) {report['sqrt_mean_pcrb_cm']:.2f} cm (a filter at the bound: mean error "
            f"{report['pcrb_mean_error_cm']:.2f} cm), EKF RMSE/sqrt(PCRB) "
            f"{a['ekf_rss']['rmse_over_sqrt_pcrb']:.2f}" + _honesty_clause(report.get("consistency", {})))


def _honesty_clause(cons: dict) -> str:
    """The stated 1-sigma of the online and smoothed filters in a few words: frames inside the 68% ellipsoid
    (0.68 if honest) and inside the NEES's 95% chi-square band (0.95 if honest)."""
    parts = [f"{name} {c['inside_68pct_ellipsoid']:.0%} inside its 68% ellipsoid, "
             f"{c['nees_chi2']['frames_inside']:.0%} of frames in the NEES's 95% band"
             for name, c in (("EKF", cons.get("ekf_rss")), ("smoothed", cons.get("ekf_rss_rts")))
             if c and "nees_chi2" in c]
    return "; 1-sigma: " + ", ".join(parts) if parts else ""


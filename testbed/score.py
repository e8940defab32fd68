"""Scoring per-step motion against the testbed's ground truth (dissertation Table 4.1, SPEC.md "How accuracy is
scored").

Table 4.1 figures: mean true value and mean absolute error per step of the distance travelled (cm), the roll (deg) and
the tilt (deg, the angle between consecutive optical axes: ``|tilt_est - tilt_true|``). Beside them: the error of the
tilt as a vector (pitch, yaw: the swing rotation's x, y components), which also checks its direction, and the coverage
(steps measured from their own pair: status ``ok`` or ``wall``; ``coverage_with_bridged`` also counts the shares of
bridged gaps). Errors are over the measured steps; the ``ft_only`` block restricts them to steps whose two frames are
both labelled FT (facing the tunnel) by the truth, ``wall_only`` to the steps the pipeline estimated although its
classifier said a frame faces the wall (status ``wall``), ``beside_wall_only`` to the steps whose tube fit put the
camera beside its own cylinder's wall (``beside_wall``: their 1-sigma widened). Beside the distance error,
``mae_distance_scale_aligned_cm``: the error left once the run's distances are multiplied by the one factor that fits
them best to the truth (``distance_scale``: the factor of least mean absolute error, the median of ``t / e`` weighted
by ``|e|``, so never above the raw error), as monocular odometry benchmarks align scale before scoring. It is an
oracle no pipeline has: it separates the scale a monocular step cannot see (here the lumen radius the tube fit is
told) from everything else. ``rotation_only`` scores the roll and tilt of the steps that measured only their rotation
(status ``rotation`` or ``rotation_slow``), which are not in the coverage. Steps without an estimate are counted,
never scored as zero.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from bodyslam.errors import InputError
from bodyslam.io import read_motion_csv
from bodyslam.steps import MEASURED, StepStatus

__all__ = ["score_motion", "score_path", "format_table", "CHI2_3_683", "CHI_3_683"]

# the statuses of steps that measured only their rotation
ROTATION_ONLY = [str(StepStatus.ROTATION), str(StepStatus.ROTATION_SLOW)]


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _angle_errors(tr: dict, es: dict, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(|roll error|, |tilt error|, |swing error|)`` (rad) of the steps ``idx``; the swing error is the pitch and
    yaw errors as one vector."""
    return (np.abs(_wrap(es["roll_rad"][idx] - tr["roll_rad"][idx])),
            np.abs(es["tilt_rad"][idx] - tr["tilt_rad"][idx]),
            np.hypot(es["pitch_rad"][idx] - tr["pitch_rad"][idx], es["yaw_rad"][idx] - tr["yaw_rad"][idx]))


def _block(tr: dict, es: dict, idx: np.ndarray) -> dict:
    if len(idx) == 0:
        return {"n_steps_scored": 0}
    d_est, d_true = es["distance_m"][idx], tr["distance_m"][idx]
    e_d = np.abs(d_est - d_true)
    scale = _l1_scale(d_est, d_true)
    e_r, e_t, e_v = _angle_errors(tr, es, idx)
    return {
        "n_steps_scored": int(len(idx)),
        "mean_true_distance_cm": float(np.mean(np.abs(d_true)) * 100),
        "mae_distance_cm": float(np.mean(e_d) * 100),
        "mae_distance_scale_aligned_cm": float(np.mean(np.abs(scale * d_est - d_true)) * 100),
        "distance_scale": scale,
        "mean_true_roll_deg": float(np.degrees(np.mean(np.abs(tr["roll_rad"][idx])))),
        "mae_roll_deg": float(np.degrees(np.mean(e_r))),
        "mean_true_tilt_deg": float(np.degrees(np.mean(tr["tilt_rad"][idx]))),
        "mae_tilt_deg": float(np.degrees(np.mean(e_t))),
        "mae_tilt_vector_deg": float(np.degrees(np.mean(e_v))),
        "p90_distance_error_cm": float(np.percentile(e_d, 90) * 100),
        "p90_roll_error_deg": float(np.degrees(np.percentile(e_r, 90))),
        "p90_tilt_error_deg": float(np.degrees(np.percentile(e_t, 90))),
        # is the stated per-step 1-sigma honest? the fraction of steps whose distance error is within it (0.683
        # for an honest Gaussian 1-sigma), over the steps that state one
        **_within_sigma(e_d, es["sigma_distance_m"][idx]),
        # the same for the rotation: its error angle (roll and swing, small angles) against the stated 1-sigma
        # (the largest axis's) at the 3-D 68.3% radius; an honest one holds 0.683 or more of the steps
        **_rotation_within_sigma(np.hypot(e_r, e_v), es["sigma_rotation_rad"][idx]),
    }


def _l1_scale(e: np.ndarray, t: np.ndarray) -> float:
    """The factor ``s`` of least ``sum |s e - t|``: the median of ``t / e`` weighted by ``|e|`` (steps with ``e = 0``
    do not depend on it); 1 where no step has a distance."""
    nz = e != 0
    if not nz.any():
        return 1.0
    r, w = t[nz] / e[nz], np.abs(e[nz])
    order = np.argsort(r, kind="stable")
    cum = np.cumsum(w[order])
    return float(r[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _rotation_block(tr: dict, es: dict, idx: np.ndarray) -> dict:
    """Roll and tilt errors of steps that measured only their rotation (status ``rotation`` or ``rotation_slow``; no
    distance)."""
    if len(idx) == 0:
        return {"n_steps_scored": 0}
    e_r, e_t, e_v = _angle_errors(tr, es, idx)
    return {"n_steps_scored": int(len(idx)),
            "mean_true_roll_deg": float(np.degrees(np.mean(np.abs(tr["roll_rad"][idx])))),
            "mae_roll_deg": float(np.degrees(np.mean(e_r))),
            "rms_roll_error_deg": float(np.degrees(np.sqrt(np.mean(e_r**2)))),
            "mean_true_tilt_deg": float(np.degrees(np.mean(tr["tilt_rad"][idx]))),
            "mae_tilt_deg": float(np.degrees(np.mean(e_t))),
            **_rotation_within_sigma(np.hypot(e_r, e_v), es["sigma_rotation_rad"][idx])}


def _within_sigma(err: np.ndarray, sigma: np.ndarray) -> dict:
    ok = np.isfinite(sigma) & (sigma > 0)
    if not ok.any():
        return {}
    return {"distance_within_1sigma": float(np.mean(err[ok] <= sigma[ok])),
            "distance_within_2sigma": float(np.mean(err[ok] <= 2 * sigma[ok]))}


# The chi-square (3 dof) quantile at 68.27% (a 1-sigma's mass, erf(1 / sqrt 2)): a 3-D Gaussian's NEES lies below it
# on 68.27% of draws; its square root is the radius holding that share of a Gaussian with that sigma on every axis.
# (scipy.stats.chi2.ppf(0.6827, 3); tests/testbed/test_score.py checks it.) One constant for every "inside 1-sigma".
CHI2_3_683 = 3.5268
CHI_3_683 = math.sqrt(CHI2_3_683)


def _rotation_within_sigma(err_rad: np.ndarray, sigma_rad: np.ndarray) -> dict:
    ok = np.isfinite(sigma_rad) & (sigma_rad > 0)
    if not ok.any():
        return {}
    return {"rotation_within_68pct": float(np.mean(err_rad[ok] <= CHI_3_683 * sigma_rad[ok])),
            # 1.54 for an honest 1-sigma on every axis (the median of a chi distribution with 3 degrees of freedom)
            "median_rotation_error_over_sigma": float(np.median(err_rad[ok] / sigma_rad[ok]))}


def score_path(seq_dir: str | os.PathLike, motion_csv: str | os.PathLike, scale_sd_rel: float,
               radius_m: float | None = None) -> dict:
    """How far along the gut, scored: the path travelled from the first frame
    (:func:`bodyslam.vision.tracking.path_travelled` on ``motion_csv``, the figure ``bodyslam`` writes for marks and
    plots) against the true one (the summed lengths of the true steps), with the stated 1-sigma. ``scale_sd_rel``:
    the relative 1-sigma of the radius the steps amount to (the prior's, or where the motion stage applied a lumen
    scale its factor's: :func:`bodyslam.vision.lumen_scale.radius_sd_rel_after`); ``radius_m``: the radius prior the
    steps assumed (the floor of a lost step's length; None: none).

    Returns the run's end (``true_m``, ``estimated_m``, ``sigma_m``, ``error_rel``: (estimated - true) / true, and
    ``z``: the error over its 1-sigma) and over every frame the mean absolute error (``mean_abs_error_m``) and the
    fraction of frames whose error is inside the stated 1-sigma (``frames_inside_1sigma``; 0.683 if honest)."""
    from bodyslam.io import read_motion_steps
    from bodyslam.vision.tracking import path_travelled

    seq_dir = Path(seq_dir)
    if not (seq_dir / "motion_truth.csv").exists():
        raise InputError(f"{seq_dir}: no motion_truth.csv (only testbed sequences have ground truth)")
    truth = read_motion_csv(seq_dir / "motion_truth.csv")
    frames = sorted(truth)
    path, var = path_travelled(read_motion_steps(motion_csv, frames), scale_sd_rel, radius_m)
    true = np.r_[0.0, np.cumsum([abs(truth[k]["distance_m"]) for k in frames])]
    err, sd = path - true, np.sqrt(var)
    inside = np.abs(err[1:]) <= sd[1:]
    return {"true_m": float(true[-1]), "estimated_m": float(path[-1]), "sigma_m": float(sd[-1]),
            "error_rel": float(err[-1] / true[-1]) if true[-1] > 0 else math.nan,
            "z": float(err[-1] / sd[-1]) if sd[-1] > 0 else math.nan,
            "mean_abs_error_m": float(np.mean(np.abs(err[1:]))) if len(err) > 1 else 0.0,
            "frames_inside_1sigma": float(np.mean(inside)) if len(inside) else math.nan}


def score_motion(seq_dir: str | os.PathLike, motion_csv: str | os.PathLike) -> dict:
    """Table 4.1 of an estimated ``motion.csv`` against ``SEQDIR/motion_truth.csv``."""
    seq_dir = Path(seq_dir)
    truth = read_motion_csv(seq_dir / "motion_truth.csv") if (seq_dir / "motion_truth.csv").exists() else None
    if truth is None:
        raise InputError(f"{seq_dir}: no motion_truth.csv (only testbed sequences have ground truth)")
    est = read_motion_csv(motion_csv)
    frames = np.array(sorted(truth))
    missing = [k for k in frames if k not in est]
    keys = ("distance_m", "roll_rad", "pitch_rad", "yaw_rad", "tilt_rad")
    tr = {c: np.array([truth[k][c] for k in frames]) for c in keys}
    es = {c: np.array([est[k][c] if k in est else math.nan for k in frames]) for c in keys}
    for c in ("sigma_distance_m", "sigma_rotation_rad"):
        es[c] = np.array([est[k].get(c, math.nan) if k in est else math.nan for k in frames])
    status = np.array([est[k]["status"] if k in est else "missing" for k in frames])
    beside = np.array([bool(est[k].get("beside_wall", False)) if k in est else False for k in frames])
    label = np.array([truth[k]["label"] for k in frames])
    has = np.isin(status, MEASURED) & np.isfinite(es["distance_m"]) & np.isfinite(es["roll_rad"])
    has &= np.isfinite(es["tilt_rad"])
    labels_prev = np.r_[label[:1], label[:-1]]
    ft = (label == "FT") & (labels_prev == "FT")
    counts = {s: int(np.sum(status == s)) for s in sorted(set(status.tolist()))}
    return {
        "sequence": str(seq_dir),
        "motion_csv": str(motion_csv),
        "n_steps": int(len(frames)),
        "n_steps_missing_rows": len(missing),
        "status_counts": counts,
        "coverage": float(np.mean(has)),
        "coverage_with_bridged": float(np.mean(has | (status == StepStatus.BRIDGED))),
        "all": _block(tr, es, np.nonzero(has)[0]),
        "ft_only": _block(tr, es, np.nonzero(has & ft)[0]),
        "wall_only": _block(tr, es, np.nonzero(has & (status == StepStatus.WALL))[0]),
        "beside_wall_only": _block(tr, es, np.nonzero(has & beside)[0]),
        "rotation_only": _rotation_block(tr, es, np.nonzero(np.isin(status, ROTATION_ONLY)
                                                            & np.isfinite(es["roll_rad"]))[0]),
    }


def format_table(rep: dict) -> str:
    """The report as dissertation Table 4.1 (plain text)."""
    a = rep["all"]
    if not a.get("n_steps_scored"):
        return f"{rep['sequence']}: no step has an estimate ({rep['status_counts']})"
    lines = [
        f"{rep['sequence']}: {a['n_steps_scored']}/{rep['n_steps']} steps with an estimate "
        f"(coverage {rep['coverage']:.3f}; {rep['status_counts']})",
        f"{'':10s} {'mean true':>12s} {'mean abs error':>15s} {'p90 error':>10s}",
        f"{'distance':10s} {a['mean_true_distance_cm']:9.3f} cm {a['mae_distance_cm']:12.4f} cm "
        f"{a['p90_distance_error_cm']:7.4f} cm   (scale-aligned: {a['mae_distance_scale_aligned_cm']:.4f} cm at "
        f"x{a['distance_scale']:.3f})",
        f"{'roll':10s} {a['mean_true_roll_deg']:8.2f} deg {a['mae_roll_deg']:11.3f} deg "
        f"{a['p90_roll_error_deg']:6.3f} deg",
        f"{'tilt':10s} {a['mean_true_tilt_deg']:8.2f} deg {a['mae_tilt_deg']:11.3f} deg "
        f"{a['p90_tilt_error_deg']:6.3f} deg   (as a vector: {a['mae_tilt_vector_deg']:.3f} deg)",
    ]
    for key, what in (("ft_only", "FT-FT steps only (truth's labels)"),
                      ("wall_only", "steps facing the wall (status wall)"),
                      ("beside_wall_only", "steps fitted beside the wall (beside_wall)")):
        f = rep.get(key, {})
        if f.get("n_steps_scored"):
            lines.append(f"{what} ({f['n_steps_scored']}): distance {f['mae_distance_cm']:.4f} cm, roll "
                         f"{f['mae_roll_deg']:.3f} deg, tilt {f['mae_tilt_deg']:.3f} deg")
    f = rep.get("rotation_only", {})
    if f.get("n_steps_scored"):
        lines.append(f"steps with only their rotation ({f['n_steps_scored']}): roll {f['mae_roll_deg']:.3f} deg "
                     f"(true {f['mean_true_roll_deg']:.2f}), tilt {f['mae_tilt_deg']:.3f} deg"
                     + (f", inside the stated 68% radius {f['rotation_within_68pct']:.2f}"
                        if "rotation_within_68pct" in f else ""))
    honest = [f"{what} {a[k]:.2f}" for k, what in (("distance_within_1sigma", "distance within 1-sigma"),
                                                    ("rotation_within_68pct", "rotation within the 68% radius"))
              if k in a]
    if honest:
        lines.append("stated uncertainty (0.68 if honest): " + ", ".join(honest)
                     + (f"; median rotation error {a['median_rotation_error_over_sigma']:.2f} sigma (1.54 if honest)"
                        if "median_rotation_error_over_sigma" in a else ""))
    return "\n".join(lines)

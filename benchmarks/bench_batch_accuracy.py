"""What a user gets from `bodyslam batch` with its defaults, on rendered exams with exact truth (issues 15 and 16).

For each seed: render SCENARIO (default `realistic_exam`: the realistic gut at a whole exam's pace) with `testbed
simulate`, run `bodyslam batch SEQ --out D` as a user would (its defaults: fast mode, both cores, the FT/FL
classifier, RF fused from the sequence's `rf.csv` and `sensors.csv`), then score the exam's outputs against the truth
the sequence keeps (scoring only; the pipeline never reads it):

- the path travelled at the exam's end (`summary.json`) against `truth.json`'s, whether the error lies inside the
  stated 1-sigma, and the share of the path in steps without an estimate (`path_without_estimate_share`) and in
  fits beside the wall (`path_beside_wall_share`: both the speed model's lengths);
- the steps (`testbed score-motion`'s code): share with a full estimate, mean distance error, share fitted beside
  the wall;
- FT/FL (`frames.csv` against `labels.csv`): lumen-facing frames called FL, wall-facing frames found;
- the fused trajectory (`trajectory.tum` against `groundtruth.tum`): mean position error, and the share of frames
  inside the 68% ellipsoid of their stated covariance (`uncertainty.csv`: the per-axis 1-sigma and, since session 63,
  their correlations; an older file's per-axis 1-sigma alone);
- how far along the gut a marked frame lies between two landmarks (session 78): the run is given landmarks at 5%
  and 95% of its frames (`--landmark`) and a mark every 10 frames between them (`--mark`); `marks.csv`'s fraction
  by the path travelled (with its 1-sigma) and by the time (the transit-time convention) against the true fraction
  of the centre line's length between the landmarks (`labels.csv` `s_m`): mean and p90 absolute error, the share
  inside the stated 1-sigma, and the fraction a perfect odometer would give (the true path travelled: the capsule's
  back-and-forth and wobble, which no path travelled removes).

Prints a line per seed and the mean over seeds; ``--json`` writes them. Use tuning seeds (500-599) to choose
anything and reporting seeds (700-799) to report (README, "Seeds"). ``--frames`` and ``--set`` change the scenario as
`testbed simulate`'s do, e.g. the ideal world at the same pace and length: ``--scenario exam --frames 400`` (the
`exam` stand-in is `realistic_exam`'s motion in a rigid tube of known radius, 10,000 frames a run).

    .venv/bin/python benchmarks/bench_batch_accuracy.py --seeds 744-751 [--scenario realistic_exam] [--frames K]
        [--set SECTION.KEY=VALUE ...] [--keep DIR]
"""

from __future__ import annotations

import argparse
import collections
import csv
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bodyslam.errors import BodySlamError
from bodyslam.io import read_tum
from testbed.cli import parse_seeds
from testbed.scenario import load_scenario
from testbed.score import score_motion
from testbed.simulate import simulate

CHI2_3DOF_68 = 3.527  # the chi-square quantile of a 3-D 68% ellipsoid


def score_exam(seq: Path, ex: Path) -> dict:
    """The scores of one exam's outputs ``ex`` (``bodyslam batch``'s folder for it) against the sequence ``seq``."""
    summary = json.loads((ex / "summary.json").read_text())
    true_path = json.loads((seq / "truth.json").read_text())["path_travelled_m"]
    path, sd_path = summary["path_travelled_m"], summary["sd_path_travelled_m"]
    label = {int(r["frame"]): r["label"] for r in csv.DictReader(open(seq / "labels.csv", newline=""))}
    called = [(label[int(r["frame"])], r["class"]) for r in csv.DictReader(open(ex / "frames.csv", newline=""))]
    ft = np.array([c for t, c in called if t == "FT"])
    fl = np.array([c for t, c in called if t == "FL"])
    motion = score_motion(seq, ex / "motion.csv")
    rows = list(csv.DictReader(open(ex / "motion.csv", newline="")))
    beside = [r.get("beside_wall") == "1" for r in rows]
    status = collections.Counter(r["status"] for r in rows)
    _, p_est, _ = read_tum(ex / "trajectory.tum")
    _, p_true, _ = read_tum(seq / "groundtruth.tum")
    err = p_est - p_true
    rows_u = list(csv.DictReader(open(ex / "uncertainty.csv", newline="")))
    sd = np.array([[float(r[k]) for k in ("sd_x_m", "sd_y_m", "sd_z_m")] for r in rows_u])
    if rows_u and "corr_xy" in rows_u[0]:  # the whole covariance (since session 63): its 68% ellipsoid
        corr = np.array([[float(r[k] or "nan") for k in ("corr_xy", "corr_xz", "corr_yz")] for r in rows_u])
        c = np.repeat(np.eye(3)[None], len(sd), axis=0)
        for col, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
            c[:, i, j] = c[:, j, i] = np.nan_to_num(corr[:, col])
        cov = c * sd[:, :, None] * sd[:, None, :]
        inside = np.array([np.isfinite(e).all() and np.all(np.isfinite(v)) and np.linalg.det(v) > 0
                           and float(e @ np.linalg.solve(v, e)) <= CHI2_3DOF_68 for e, v in zip(err, cov)])
    else:  # an older run's file: the per-axis 1-sigma alone (its correlations not written)
        with np.errstate(divide="ignore", invalid="ignore"):
            inside = np.sum((err / sd) ** 2, axis=1) <= CHI2_3DOF_68
    return {
        "path_m": path, "sd_path_m": sd_path, "true_path_m": true_path, "path_error_rel": path / true_path - 1.0,
        "path_inside_1sigma": bool(abs(path - true_path) <= sd_path),
        "path_without_estimate_share": summary.get("path_without_estimate_share"),
        "path_beside_wall_share": summary.get("path_beside_wall_share"),
        "path_loss_half_length_r": summary.get("path_loss_half_length_r"),
        "steps_estimated": motion["coverage"], "step_distance_error_cm": motion["all"]["mae_distance_cm"],
        "steps_beside_wall": float(np.mean(beside)) if beside else 0.0,
        "lumen_facing_called_fl": float(np.mean(ft == "FL")) if len(ft) else None,
        "wall_facing_found": float(np.mean(fl == "FL")) if len(fl) else None,
        "fused_mean_error_cm": 100.0 * float(np.mean(np.linalg.norm(err, axis=1))),
        "fused_inside_68": float(np.mean(inside)),
        "trajectory": summary.get("trajectory"),
        "steps_rotation": status["rotation"], "steps_rotation_slow": status["rotation_slow"],
        "steps_lost": status["lost"],
    }


def landmark_frames(n: int) -> tuple[int, int, list[int]]:
    """The landmarks (5% and 95% of ``n`` frames) and the marks (every 10 frames strictly between them)."""
    a, b = round(0.05 * (n - 1)), round(0.95 * (n - 1))
    return a, b, list(range(a + 10, b, 10))


def score_fractions(seq: Path, ex: Path, a: int, b: int) -> dict:
    """``marks.csv``'s fractions between landmarks ``a`` and ``b`` against the truth (module docstring)."""
    s = {int(r["frame"]): float(r["s_m"]) for r in csv.DictReader(open(seq / "labels.csv", newline=""))}
    step = {int(r["frame"]): abs(float(r["distance_m"]))
            for r in csv.DictReader(open(seq / "motion_truth.csv", newline=""))}
    odo = np.r_[0.0, np.cumsum([step.get(k, 0.0) for k in range(1, max(s) + 1)])]
    rows = list(csv.DictReader(open(ex / "marks.csv", newline="")))
    k = np.array([int(r["frame"]) for r in rows])
    f_true = np.array([(s[i] - s[a]) / (s[b] - s[a]) for i in k])
    f = np.array([float(r[f"fraction_{a}_{b}"]) for r in rows])
    sd = np.array([float(r[f"sd_fraction_{a}_{b}"]) for r in rows])
    ft = np.array([float(r[f"time_fraction_{a}_{b}"]) for r in rows])
    fo = (odo[k] - odo[a]) / (odo[b] - odo[a])
    e, et, eo = np.abs(f - f_true), np.abs(ft - f_true), np.abs(fo - f_true)
    return {"fraction_error": float(np.mean(e)), "fraction_error_p90": float(np.percentile(e, 90)),
            "fraction_inside_1sigma": float(np.mean(e <= sd)), "fraction_sd": float(np.mean(sd)),
            "time_fraction_error": float(np.mean(et)), "time_fraction_error_p90": float(np.percentile(et, 90)),
            "odometer_fraction_error": float(np.mean(eo)), "marks": len(rows)}


def fmt(r: dict) -> str:
    fl = "--" if r["wall_facing_found"] is None else f"{r['wall_facing_found']:.2f}"
    ft = "--" if r["lumen_facing_called_fl"] is None else f"{r['lumen_facing_called_fl']:.3f}"
    return (f"path {100 * r['path_error_rel']:+.1f}% ({100 * r['path_m']:.1f} +- {100 * r['sd_path_m']:.1f} cm of "
            f"{100 * r['true_path_m']:.1f}{', inside 1-sigma' if r['path_inside_1sigma'] else ''}; "
            f"{100 * (r['path_without_estimate_share'] or 0.0):.0f}% of it without an estimate, "
            f"{100 * (r['path_beside_wall_share'] or 0.0):.0f}% in fits beside the wall; half the steps lost at "
            f"{r['path_loss_half_length_r'] or float('nan'):g} radii); steps "
            f"{r['steps_estimated']:.3f} estimated, {r['step_distance_error_cm']:.4f} cm, beside the wall "
            f"{r['steps_beside_wall']:.2f}, rotation {r['steps_rotation']} (+{r['steps_rotation_slow']} slow), lost "
            f"{r['steps_lost']}; lumen-facing called FL {ft}, wall-facing found {fl}; fused "
            f"{r['fused_mean_error_cm']:.2f} cm, inside 68% {r['fused_inside_68']:.2f}; between the landmarks by the "
            f"path {100 * r['fraction_error']:.1f} points (p90 {100 * r['fraction_error_p90']:.1f}, inside 1-sigma "
            f"{r['fraction_inside_1sigma']:.2f}), by the time {100 * r['time_fraction_error']:.1f} (p90 "
            f"{100 * r['time_fraction_error_p90']:.1f}), a perfect odometer {100 * r['odometer_fraction_error']:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", required=True, help="A-B, a,b,c or N (seeds 0..N-1), as testbed evaluate")
    ap.add_argument("--scenario", default="realistic_exam")
    ap.add_argument("--frames", type=int, default=None, help="frames a run (default: the scenario's)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a scenario field, as testbed simulate's --set (repeatable)")
    ap.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the renders and batch outputs here")
    ap.add_argument("--json", type=Path, default=None, help="write the per-seed scores and their means here")
    args = ap.parse_args()
    try:
        seeds = parse_seeds(args.seeds)
        scn = load_scenario(args.scenario, args.overrides)
        if args.frames is not None and args.frames < 2:
            raise BodySlamError(f"--frames must be at least 2, got {args.frames}")
    except BodySlamError as e:
        raise SystemExit(str(e)) from None
    # renders of other frames or overrides keep to their own folders
    variant = ("" if args.frames is None and not args.overrides else "_" + hashlib.sha1(
        json.dumps([args.frames, args.overrides]).encode()).hexdigest()[:8])
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_batch_acc_"))
    root.mkdir(parents=True, exist_ok=True)
    rows = {}
    for seed in seeds:
        seq = root / f"{args.scenario}{variant}_{seed}"
        if not (seq / "meta.json").exists():
            simulate(scn, seed, seq, n_frames=args.frames, force=True)
        out = root / f"out_{args.scenario}{variant}_{seed}"
        n = json.loads((seq / "truth.json").read_text())["n_frames"]
        a, b, marks = landmark_frames(n)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "batch", str(seq), "--out", str(out), "--force",
                            "--landmark", f"{a},{b}", "--mark", ",".join(map(str, marks))],
                           capture_output=True, text=True)
        el = time.perf_counter() - t0
        ex = out / seq.name
        if not (ex / "summary.json").exists():
            raise SystemExit(f"bodyslam batch failed on {seq} (exit {p.returncode}): {p.stderr.strip()[-500:]}")
        rows[seed] = dict(score_exam(seq, ex), **score_fractions(seq, ex, a, b), batch_s=el, exit=p.returncode)
        print(f"{args.scenario} {seed}: {fmt(rows[seed])} ({el:.0f} s)", flush=True)
    errs = np.array([r["path_error_rel"] for r in rows.values()])
    keys = ("path_inside_1sigma", "path_without_estimate_share", "path_beside_wall_share", "steps_estimated",
            "step_distance_error_cm", "steps_beside_wall", "lumen_facing_called_fl", "wall_facing_found",
            "fused_mean_error_cm", "fused_inside_68", "fraction_error", "fraction_error_p90",
            "fraction_inside_1sigma", "fraction_sd", "time_fraction_error", "time_fraction_error_p90",
            "odometer_fraction_error")
    mean = {k: float(np.mean([r[k] for r in rows.values() if r[k] is not None])) for k in keys}
    mean.update(path_error_rel=float(np.mean(errs)), path_error_median=float(np.median(errs)),
                path_error_abs=float(np.mean(np.abs(errs))), path_error_worst=float(np.max(np.abs(errs))))
    total = {k: int(sum(r[k] for r in rows.values())) for k in ("steps_rotation", "steps_rotation_slow", "steps_lost")}
    print(f"mean over {len(rows)} seeds: path {100 * mean['path_error_rel']:+.1f}% (median "
          f"{100 * mean['path_error_median']:+.1f}%, mean absolute "
          f"{100 * mean['path_error_abs']:.1f}%, worst {100 * mean['path_error_worst']:.1f}%; ends inside 1-sigma "
          f"{mean['path_inside_1sigma']:.2f}; {100 * mean['path_without_estimate_share']:.0f}% of it without an "
          f"estimate, {100 * mean.get('path_beside_wall_share', 0.0):.0f}% in fits beside the wall); steps "
          f"{mean['steps_estimated']:.3f} estimated, "
          f"{mean['step_distance_error_cm']:.4f} cm, beside the wall {mean['steps_beside_wall']:.2f}, in all rotation "
          f"{total['steps_rotation']} (+{total['steps_rotation_slow']} slow), lost {total['steps_lost']}; lumen-facing "
          f"called FL {mean['lumen_facing_called_fl']:.3f}, wall-facing found {mean['wall_facing_found']:.2f}; fused "
          f"{mean['fused_mean_error_cm']:.2f} cm, inside 68% {mean['fused_inside_68']:.2f}; between the landmarks "
          f"by the path {100 * mean['fraction_error']:.1f} points (p90 {100 * mean['fraction_error_p90']:.1f}, inside "
          f"1-sigma {mean['fraction_inside_1sigma']:.2f}, 1-sigma {100 * mean['fraction_sd']:.1f}), by the time "
          f"{100 * mean['time_fraction_error']:.1f} (p90 {100 * mean['time_fraction_error_p90']:.1f}), a perfect "
          f"odometer {100 * mean['odometer_fraction_error']:.1f}")
    if args.json:
        args.json.write_text(json.dumps({"scenario": args.scenario, "frames": args.frames, "overrides": args.overrides,
                                         "seeds": rows, "mean": mean, "total": total}, indent=1))


if __name__ == "__main__":
    main()

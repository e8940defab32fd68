"""Per-step motion accuracy over many `thesis` seeds (Table 4.1), and `bodyslam motion` throughput.

Accuracy: for each seed, render `testbed simulate thesis --seed S --frames 200`, match every consecutive pair
once (matcher mode as given), run both estimators (tube: the project's; thesis: the dissertation's equations)
on the same matches, write each as motion.csv and score it with the code behind `testbed score-motion`.
Prints per-seed lines, the mean over seeds, and the same errors restricted to off-centre steps (the capsule
more than 0.3 radii from the centre line, from the truth; scoring only).

Throughput: the whole `bodyslam motion` process (spawned as a user would run it) on 320x320 sequences (``--size
576``: a PillCam COLON frame's size): thesis motion (0.41 cm, 7.8 deg roll per frame) in every matcher mode,
whole-exam motion (`exam`: 0.06 cm, 3 deg) in fast and ASIFT mode.

    .venv/bin/python benchmarks/bench_motion.py --seeds 100-119 [--mode sift] [--frames 200] [--keep DIR]
    .venv/bin/python benchmarks/bench_motion.py --speed-only      (or --accuracy-only) [--size 576]

Seeds 100+ are used by no test (tests use the demo sequence and seeds 11-13).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bodyslam.io import read_tum, write_motion_csv
from bodyslam.vision.matching import Matcher
from bodyslam.vision.motion import estimate_thesis, estimate_tube
from bodyslam.vision.odometry import Sequence
from bodyslam.vision.unroll import Unroller
from testbed.centerline import Centerline
from testbed.scenario import load_scenario
from testbed.score import score_motion
from testbed.simulate import simulate

from machine import machine_info, machine_line  # benchmarks/machine.py, beside this script

KEYS = ("mae_distance_cm", "mae_roll_deg", "mae_tilt_deg", "mae_tilt_vector_deg")


def parse_seeds(s: str) -> list[int]:
    if "-" in s:
        a, b = s.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in s.split(",")]


def off_centre_steps(seq: Path, radius_m: float) -> np.ndarray:
    """Step k (frames k-1 -> k) is off-centre when frame k-1's camera is > 0.3 r from the centre line (truth)."""
    _, pos, _ = read_tum(seq / "groundtruth.tum")
    cl = Centerline.read_csv(seq / "centerline.csv")
    s = np.loadtxt(seq / "labels.csv", delimiter=",", skiprows=1, usecols=4)
    c, _, _ = cl.frame_at(s)
    off = np.linalg.norm(pos - c, axis=1) > 0.3 * radius_m
    return off[:-1]


def accuracy(seeds: list[int], mode: str, frames: int, keep: Path | None) -> dict:
    scn = load_scenario("thesis")
    per_seed = {"tube": [], "thesis": []}
    off_err = {"tube": [], "thesis": []}
    root = keep or Path(tempfile.mkdtemp(prefix="bench_motion_"))
    for seed in seeds:
        d = root / f"thesis_{seed}"
        t0 = time.perf_counter()
        meta = d / "meta.json"
        if not (keep and meta.exists() and json.loads(meta.read_text()).get("n_frames") == frames):
            simulate(scn, seed, d, n_frames=frames, force=True)  # (a kept sequence of that length is reused)
        t_sim = time.perf_counter() - t0
        seq = Sequence.open(d)
        matcher = Matcher(seq.camera, mode)
        un = Unroller(seq.camera)
        steps = {"tube": [], "thesis": []}
        prev = matcher.features(seq.frame(0))
        t0 = time.perf_counter()
        for k in range(1, seq.n_frames):
            f = matcher.features(seq.frame(k))
            for m in matcher.cascade(prev, f):  # as bodyslam.vision.odometry.VisualOdometry.estimate_pair
                tube = estimate_tube(m, seq.camera, seq.radius_m)
                if tube.ok:
                    break
            prev = f
            steps["tube"].append(tube)
            steps["thesis"].append(estimate_thesis(m, un, seq.radius_m))
        t_mot = time.perf_counter() - t0
        off = off_centre_steps(d, seq.radius_m)
        line = [f"seed {seed}: render {t_sim:.0f} s, motion {t_mot:.0f} s, off-centre steps {off.sum()}"]
        for est, st in steps.items():
            csv_path = d / f"motion_{est}.csv"
            write_motion_csv(csv_path, range(1, len(st) + 1), [k / seq.frame_rate_hz for k in range(1, len(st) + 1)], st)
            rep = score_motion(d, csv_path)
            (d / f"motion_{est}.score.json").write_text(json.dumps(rep, indent=1))
            per_seed[est].append(rep)
            a = rep["all"]
            line.append(f"{est}: dist {a['mae_distance_cm']:.4f} cm roll {a['mae_roll_deg']:.3f} deg "
                        f"tilt {a['mae_tilt_deg']:.3f} deg cov {rep['coverage']:.3f}")
            true_d = np.loadtxt(d / "motion_truth.csv", delimiter=",", skiprows=1, usecols=(2, 3, 6))
            e = np.array([[s.distance_m, s.roll_rad, s.tilt_rad] for s in st])
            err = np.abs(e - true_d)
            err[:, 1] = np.abs((e[:, 1] - true_d[:, 1] + np.pi) % (2 * np.pi) - np.pi)
            off_err[est].append(err[off & np.isfinite(err).all(axis=1)])
        print("  ".join(line), flush=True)
    out = {"seeds": seeds, "mode": mode, "frames": frames, "estimators": {}}
    for est in per_seed:
        reps = per_seed[est]
        mean = {k: float(np.mean([r["all"][k] for r in reps])) for k in KEYS}
        mean["coverage"] = float(np.mean([r["coverage"] for r in reps]))
        mean["mean_true_distance_cm"] = float(np.mean([r["all"]["mean_true_distance_cm"] for r in reps]))
        mean["mean_true_roll_deg"] = float(np.mean([r["all"]["mean_true_roll_deg"] for r in reps]))
        mean["mean_true_tilt_deg"] = float(np.mean([r["all"]["mean_true_tilt_deg"] for r in reps]))
        oe = np.concatenate(off_err[est]) if off_err[est] else np.zeros((0, 3))
        mean["off_centre_steps"] = int(len(oe))
        if len(oe):
            mean["off_centre_mae_distance_cm"] = float(oe[:, 0].mean() * 100)
            mean["off_centre_mae_roll_deg"] = float(np.degrees(oe[:, 1].mean()))
            mean["off_centre_mae_tilt_deg"] = float(np.degrees(oe[:, 2].mean()))
        out["estimators"][est] = mean
    return out


def speed(runs: list[tuple[str, str, int]], px: int = 320) -> dict:
    """``bodyslam motion`` as a user runs it, per ``(scenario, mode, frames)``: ``px`` x ``px`` frames (default
    320: ``thesis`` is rendered at that size; ``exam`` is 320x320 PillCam-SB-sized already; 576 is a PillCam COLON
    frame's size), seed 7, classifier on. Enough frames that the workers' start (~1.5 s) is a small part, as on a
    real exam of 50,000 frames."""
    res = {}
    size = [f"camera.width={px}", f"camera.height={px}"]
    with tempfile.TemporaryDirectory() as tmp:
        for scenario, mode, frames in runs:
            d = Path(tmp) / f"{scenario}_{frames}"
            if not d.exists():  # one sequence per scenario and length, shared by the modes
                simulate(load_scenario(scenario, size), 7, d, n_frames=frames, force=True)
            out = Path(tmp) / f"m_{scenario}_{mode}_{frames}.csv"
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "motion", str(d), "--out", str(out),
                                "--mode", mode], capture_output=True, text=True)
            el = time.perf_counter() - t0
            if p.returncode:
                print(p.stderr)
            rep = score_motion(d, out)
            res[f"{scenario}/{mode}"] = {"frames": frames, "frames_per_s": frames / el, "seconds": el,
                                         "coverage": rep["coverage"], **{k: rep["all"][k] for k in KEYS[:3]}}
            print(f"bodyslam motion --mode {mode} on {scenario} motion: {frames} frames {px}x{px} in {el:.1f} s = "
                  f"{frames / el:.1f} frames/s (whole process, 2 cores); dist {rep['all']['mae_distance_cm']:.4f} cm "
                  f"roll {rep['all']['mae_roll_deg']:.3f} deg tilt {rep['all']['mae_tilt_deg']:.3f} deg, coverage "
                  f"{rep['coverage']:.3f}", flush=True)
    return res


SPEED_RUNS = [("thesis", "asift", 300), ("thesis", "sift", 300), ("thesis", "fast", 300), ("exam", "fast", 2000),
              ("exam", "asift", 300)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="100-119")
    ap.add_argument("--mode", default="sift")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--keep", type=Path, default=None, help="keep the rendered sequences here")
    ap.add_argument("--speed-only", action="store_true")
    ap.add_argument("--accuracy-only", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--size", type=int, default=320, metavar="PX",
                    help="throughput runs' frame size, PX x PX (default 320; a PillCam COLON frame is 576)")
    ap.add_argument("--speed-runs", default=None,
                    help="SCENARIO/MODE/FRAMES,... (default: " + ",".join("/".join(map(str, r)) for r in SPEED_RUNS) + ")")
    args = ap.parse_args()
    if args.size < 64:
        raise SystemExit(f"--size {args.size}: frames must be at least 64 px")
    runs = SPEED_RUNS
    if args.speed_runs:
        try:
            runs = [(a, b, int(c)) for a, b, c in (r.split("/") for r in args.speed_runs.split(","))]
        except ValueError:
            raise SystemExit(f"--speed-runs {args.speed_runs!r}: expected SCENARIO/MODE/FRAMES,...") from None
    report = {"machine": machine_info()}  # before the benchmark's own work
    print(machine_line(report["machine"]), flush=True)
    if not args.speed_only:
        report["accuracy"] = acc = accuracy(parse_seeds(args.seeds), args.mode, args.frames, args.keep)
        print(f"\nTable 4.1 over {len(acc['seeds'])} thesis seeds ({args.frames} frames, matcher {args.mode}):")
        print(f"{'':8s} {'dist MAE cm':>12s} {'roll MAE deg':>13s} {'tilt MAE deg':>13s} {'tilt vec deg':>13s} "
              f"{'coverage':>9s}")
        print(f"{'thesis*':8s} {0.04:12.4f} {1.8:13.3f} {3.0:13.3f} {'':>13s} {'':>9s}   (* as reported, Table 4.1)")
        for est, m in acc["estimators"].items():
            print(f"{est:8s} {m['mae_distance_cm']:12.4f} {m['mae_roll_deg']:13.3f} {m['mae_tilt_deg']:13.3f} "
                  f"{m['mae_tilt_vector_deg']:13.3f} {m['coverage']:9.3f}")
            if m.get("off_centre_steps"):
                print(f"{'':8s} off-centre steps ({m['off_centre_steps']}): dist {m['off_centre_mae_distance_cm']:.4f}"
                      f" cm roll {m['off_centre_mae_roll_deg']:.3f} deg tilt {m['off_centre_mae_tilt_deg']:.3f} deg")
        m0 = acc["estimators"]["tube"]
        print(f"mean true per step: distance {m0['mean_true_distance_cm']:.3f} cm, roll "
              f"{m0['mean_true_roll_deg']:.2f} deg, tilt {m0['mean_true_tilt_deg']:.2f} deg")
    if not args.accuracy_only:
        report["speed"] = speed(runs, args.size)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

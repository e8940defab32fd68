"""Memory and time of the RF fusion (`bodyslam.fusion.localize`, what `bodyslam batch` runs on an exam with RF)
against exam length, on whole-exam stand-ins that need no rendering.

Each length runs in a fresh process: the `exam` scenario's capsule motion (6 m of small bowel; beyond its 10,000
frames at a slower pace, as benchmarks/bench_batch.py renders it) and its emulated RF readings, the visual steps the
truth's with noise (0.3 mm and 0.2 deg per axis, stated as their 1-sigma). The process builds its inputs, then
runs `localize` with its defaults (raw RSS, the whole-exam solve, the covariances scaled by the readings' measured
correlation). Printed per length: the fusion's seconds, the resident memory before it (imports and inputs) and at
its peak (Linux VmHWM), their difference per frame, and with ``--trace`` the fusion's peak of Python-traced
allocations (tracemalloc; slower). The process frees large arrays as `bodyslam batch`'s workers do
(:func:`bodyslam.parallel.return_large_frees`); ``--malloc-default`` measures it with glibc's own threshold. Issue
17: the fusion's memory should not be what limits an exam's length (bodyslam batch with RF: <= 1 GB for the whole
process tree at 55,000 frames; real exams run to 100,000).

    .venv/bin/python benchmarks/bench_fusion_memory.py [--frames 10000,55000,100000] [--trace] [--rss-bias-states]
        [--malloc-default]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _status_mib(field: str) -> float:
    """A line of /proc/self/status in MiB (VmRSS: resident now; VmHWM: its peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"/proc/self/status has no {field}")


def child(n: int, seed: int, trace: bool, bias_states: bool, malloc_default: bool = False) -> dict:
    """One length in this process: inputs, then the fusion; what it measured."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from bench_batch import long_exam_settings
    from bodyslam.fusion.localize import RfInput, localize
    from bodyslam.steps import motion_from_transform
    from testbed.motion import generate_motion
    from testbed.rf import emulate_rf
    from testbed.scenario import build_world, load_scenario

    if not malloc_default:
        from bodyslam.parallel import return_large_frees

        if not return_large_frees():
            raise SystemExit("cannot fix the C library's mmap threshold here (not glibc, or MALLOC_MMAP_THRESHOLD_ "
                             "set): run with --malloc-default")
    world = build_world(load_scenario("exam", long_exam_settings(n)[1::2]), seed, n)
    traj = generate_motion(world.tube, n, world.motion, world.rngs["motion"])
    rf = world.rf
    meas = emulate_rf(traj.positions_w_m, rf["layout"], rf["pathloss"], rf["toa"], world.rngs["rf"], rf["channel"])
    R_w_c, p_w_m = traj.rotations_w_c, traj.positions_w_m
    rng = np.random.default_rng(seed)
    R_steps = (R_w_c[:-1].inv() * R_w_c[1:]) * Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (n - 1, 3)))
    t_steps = R_w_c[:-1].inv().apply(p_w_m[1:] - p_w_m[:-1]) + rng.normal(0, 3e-4, (n - 1, 3))
    steps = [motion_from_transform(R_steps[k], t_steps[k], 100, 3e-4, np.radians(0.2)) for k in range(n - 1)]
    del R_steps, t_steps
    inputs = RfInput(tuple(rf["layout"].names), rf["layout"].positions_w_m, rf["layout"].normals_w,
                     traj.stamps_s, meas["rss_dbm"], rf["pathloss"])
    radius_m = float(np.mean(world.tube.centerline.radius_m))
    truth, stamps = p_w_m.copy(), traj.stamps_s.copy()
    del traj, meas, world
    if trace:
        import tracemalloc

        tracemalloc.start()
    import ctypes
    import gc

    gc.collect()
    try:  # what building the inputs freed goes back to the system (glibc), so "before" is what is held
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:  # the peak from here on (Linux: "5" resets VmHWM to the resident memory now)
        Path("/proc/self/clear_refs").write_text("5")
    except OSError as exc:
        raise SystemExit(f"cannot reset the peak resident memory (/proc/self/clear_refs): {exc}") from None
    before = _status_mib("VmRSS")
    t0 = time.perf_counter()
    loc = localize(steps, stamps, inputs, float(1.0 / np.median(np.diff(stamps))), radius_m=radius_m,
                   bias_states=bias_states)
    seconds = time.perf_counter() - t0
    out = {"frames": n, "seconds": seconds, "rss_before_mib": before, "rss_peak_mib": _status_mib("VmHWM"),
           "mean_error_cm": float(np.mean(np.linalg.norm(loc.smoothed.positions_w_m - truth, axis=1)) * 100)}
    if trace:
        out["traced_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", default="10000,55000,100000")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trace", action="store_true", help="also the fusion's peak of traced allocations (slower)")
    ap.add_argument("--rss-bias-states", action="store_true", help="the fusion with the per-sensor RSS bias states")
    ap.add_argument("--malloc-default", action="store_true",
                    help="glibc's own mmap threshold, not the one bodyslam's processes set (what that changes)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child, args.seed, args.trace, args.rss_bias_states, args.malloc_default)))
        return
    try:
        lengths = [int(x) for x in args.frames.split(",")]
    except ValueError:
        raise SystemExit(f"--frames {args.frames}: give exam lengths in frames, e.g. 10000,55000") from None
    if min(lengths) < 100:
        raise SystemExit(f"--frames {args.frames}: an exam stand-in needs at least 100 frames")
    print(f"{'frames':>8s} {'fusion s':>9s} {'RSS before':>11s} {'RSS peak':>9s} {'growth/frame':>13s}"
          + (f" {'traced peak':>12s}" if args.trace else "") + f" {'mean error':>11s}", flush=True)
    rows = []
    for n in lengths:
        cmd = [sys.executable, __file__, "--child", str(n), "--seed", str(args.seed),
               *(["--trace"] if args.trace else []), *(["--rss-bias-states"] if args.rss_bias_states else []),
               *(["--malloc-default"] if args.malloc_default else [])]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"the {n}-frame run failed (exit {proc.returncode}):\n{proc.stderr.strip()[-2000:]}")
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(r)
        grow = (r["rss_peak_mib"] - r["rss_before_mib"]) * 2**20 / n
        print(f"{n:8d} {r['seconds']:9.1f} {r['rss_before_mib']:9.0f} MiB {r['rss_peak_mib']:5.0f} MiB {grow:8.0f} B"
              + (f" {r['traced_peak_mib']:8.0f} MiB" if args.trace else "") + f" {r['mean_error_cm']:8.2f} cm",
              flush=True)
    if len(rows) > 1:
        a, b = rows[0], rows[-1]
        slope = ((b["rss_peak_mib"] - b["rss_before_mib"]) - (a["rss_peak_mib"] - a["rss_before_mib"])) \
            / (b["frames"] - a["frames"]) * 2**20
        print(f"the fusion's resident growth from {a['frames']} to {b['frames']} frames: {slope:.0f} bytes a frame")


if __name__ == "__main__":
    main()

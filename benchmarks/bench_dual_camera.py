"""Dual-camera check (dissertation Sec. 4.1.1, PillCam COLON 2): speeds from the front and rear cameras.

Renders a testbed sequence with a rear camera (`--set rear_camera.enabled=true`, 26 mm behind the front lens,
looking backward), runs `bodyslam motion` on each camera (the rear one reported in the capsule body frame) and
prints the correlation of the two speed series over the steps where both have an estimate, each camera's
coverage and its correlation with the truth.

    .venv/bin/python benchmarks/bench_dual_camera.py [--scenario demo] [--seeds 1,2,3] [--frames 60]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bodyslam.io import read_motion_csv
from bodyslam.steps import MEASURED


def run(*args) -> None:
    p = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(p.stderr)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="demo")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    allf, allr = [], []
    for seed in [int(s) for s in args.seeds.split(",")]:
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp) / "seq"
            # start 35 cm in, so the rear camera does not look out of the open start of the tube;
            # light control on (a lens near the wall would otherwise saturate)
            run("testbed.cli", "simulate", args.scenario, "--seed", str(seed), "--frames", str(args.frames),
                "--out", str(d), "--set", "rear_camera.enabled=true", "--set", "motion.start_s_m=0.35",
                "--set", "lighting.auto_exposure_percentile=95")
            for cam in ("front", "rear"):
                run("bodyslam.cli", "motion", str(d), "--out", str(d / f"{cam}.csv"), "--camera", cam)
            f = read_motion_csv(d / "front.csv")
            r = read_motion_csv(d / "rear.csv")
            t = read_motion_csv(d / "motion_truth.csv")
            ks = sorted(t)
            fv = np.array([f[k]["distance_m"] if f[k]["status"] in MEASURED else np.nan for k in ks])
            rv = np.array([r[k]["distance_m"] if r[k]["status"] in MEASURED else np.nan for k in ks])
            tv = np.array([t[k]["distance_m"] for k in ks])
            both = np.isfinite(fv) & np.isfinite(rv)
            c = np.corrcoef(fv[both], rv[both])[0, 1] if both.sum() > 2 else np.nan
            print(f"seed {seed}: front coverage {np.isfinite(fv).mean():.2f}, rear {np.isfinite(rv).mean():.2f}; "
                  f"corr(front, rear) {c:.3f} over {both.sum()} steps; corr(rear, truth) "
                  f"{np.corrcoef(rv[np.isfinite(rv)], tv[np.isfinite(rv)])[0, 1]:.3f}", flush=True)
            allf.append(fv[both])
            allr.append(rv[both])
    fa, ra = np.concatenate(allf), np.concatenate(allr)
    print(f"all seeds: corr(front, rear speed) = {np.corrcoef(fa, ra)[0, 1]:.3f} over {len(fa)} steps; "
          f"mean |front - rear| = {np.mean(np.abs(fa - ra)) * 100:.4f} cm per step")


if __name__ == "__main__":
    main()

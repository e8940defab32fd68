"""Localization error per algorithm on `thesis` sequences (a first evaluation; `testbed evaluate` is to come).

For each seed: render `thesis` (200 frames, RF emulated), run `bodyslam motion` (frames only, classifier on),
then on the same RF draws: RF-only ML and NLS fixes, dead reckoning (aligned to the RF fixes like the filters'
initialisation, then vision only), the dissertation's KF on NLS fixes, EKF on ML fixes, EKF on raw RSS, and the
RTS-smoothed EKF on RSS. Errors are Euclidean,
per frame, against groundtruth.tum (scoring only).

    .venv/bin/python benchmarks/bench_fusion.py --seeds 200-204
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bodyslam.fusion import align_to_fixes, fuse, kf_thesis, process_noise, rts_smooth, steps_from_motion_rows
from testbed.bound import pcrb_positions
from bodyslam.io import read_json, read_motion_csv, read_tum
from bodyslam.rf import PathLossModel, locate_ml, locate_nls, read_rf, read_sensors
from testbed.scenario import load_scenario
from testbed.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="200-204")
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    a, b = (int(x) for x in args.seeds.split("-"))
    table: dict[str, list[np.ndarray]] = {}
    for seed in range(a, b + 1):
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp) / "seq"
            simulate(load_scenario("thesis"), seed, d, n_frames=args.frames)
            r = subprocess.run([sys.executable, "-m", "bodyslam.cli", "motion", str(d), "--out", str(d / "m.csv")],
                               capture_output=True, text=True)
            if r.returncode:
                raise SystemExit(r.stderr)
            names, pos, nrm = read_sensors(d / "sensors.csv")
            _, rss, _ = read_rf(d / "rf.csv", names)
            pl = PathLossModel.from_dict(read_json(d / "meta.json")["rf"]["pathloss"])
            _, gt, grot = read_tum(d / "groundtruth.tum")
            steps = steps_from_motion_rows(read_motion_csv(d / "m.csv"), len(gt))
            fixes = [locate_ml(pos, nrm, x, pl) for x in rss]
            dr = np.zeros((len(gt), 3))
            from scipy.spatial.transform import Rotation

            Rk = Rotation.identity()
            for k, s in enumerate(steps, start=1):
                dr[k] = dr[k - 1] + Rk.apply(s.t)
                Rk = Rk * s.R
            ekf = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss")
            R0, p0 = ekf.passes["init"]
            nls = [locate_nls(pos, x, pl) for x in rss]
            est = {
                "RF only (ML)": np.array([f.position_w_m for f in fixes]),
                "RF only (NLS, Eq. 3.36)": np.array([f.position_w_m for f in nls]),
                "dead reckoning": p0 + R0.apply(dr),
                "thesis KF (NLS fixes)": kf_thesis(steps, nls, (R0, p0)),
                "EKF on ML fixes": fuse(steps, fixes, rss, pos, nrm, pl, mode="fix").positions_w_m,
            }
            est["EKF on RSS"] = ekf.positions_w_m
            est["EKF on RSS + RTS"] = rts_smooth(ekf).positions_w_m
            _, sig_t, sig_r = process_noise(steps)
            pcrb = pcrb_positions(gt, grot, sig_t, sig_r, pos, nrm, pl, ekf.passes["P0"])
            table.setdefault("_pcrb", []).append(pcrb)
            line = [f"seed {seed}: sqrt(mean PCRB) {np.sqrt(pcrb.mean()) * 100:.2f} cm"]
            for name, p in est.items():
                e = np.linalg.norm(p - gt, axis=1)
                table.setdefault(name, []).append(e)
                line.append(f"{name} {e.mean() * 100:.2f}")
            print(" | ".join(line) + " (mean error, cm)", flush=True)
    print(f"\nover seeds {args.seeds} ({args.frames} frames each; errors per frame, cm):")
    print(f"{'algorithm':24s} {'mean':>7s} {'rmse':>7s} {'median':>7s} {'p90':>7s} {'max':>7s}")
    print(f"{'thesis Fig. 4.22*':24s} RF-only 6.8, hybrid 2.3 (* as reported)")
    pcrb_all = np.concatenate(table.pop("_pcrb"))
    print(f"sqrt(mean PCRB) of causal filtering (paper 000 Eq. 28-29, this model): "
          f"{np.sqrt(pcrb_all.mean()) * 100:.2f} cm")
    for name, es in table.items():
        e = np.concatenate(es) * 100
        ratio = np.sqrt(np.mean(e**2)) / (np.sqrt(pcrb_all.mean()) * 100)
        print(f"{name:24s} {e.mean():7.2f} {np.sqrt(np.mean(e**2)):7.2f} {np.median(e):7.2f} "
              f"{np.percentile(e, 90):7.2f} {e.max():7.2f}   RMSE/sqrt(PCRB) {ratio:5.2f}")


if __name__ == "__main__":
    main()

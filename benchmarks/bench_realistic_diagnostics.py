"""Where the realistic testbed's error comes from, one departure at a time, on *tuning* seeds (500-599: choosing
and trying things happens here, reporting on 700-799 -- README "Seed sets").

For each seed: render `realistic` (kept under --keep), then
1. vision: `bodyslam motion` as shipped, with `--mask auto`, and told the gut's true mean radius (the pipeline
   gets a 1.25 cm prior), each scored by `testbed score-motion`'s code (Table 4.1, coverage);
2. RF: the fusion (`bodyslam.fusion.localize`) on the shipped motion, and on the *true* steps (what vision could
   give at best), against RF only;
3. the per-sensor RSS bias states (`FusionSettings.bias_corr_m`, `bias_sd_db`) over a small grid;
4. what limits the fusion, with the truth handed in one piece at a time (oracles: no pipeline can do this):
   the true path's best rigid fit to every RF fix, and to the raw readings with per-sensor PL(d0) and exponent
   offsets estimated (the floor of any estimator that knows the path's shape exactly); the EKF/RTS on the true
   steps with the searched start and with the true start, with and without bias states; the estimated steps
   with the true start; and the estimated steps with the true motion put into the steps vision missed;
5. the RSS residuals' measured correlation (kappa, bodyslam.fusion.channel) and the 1-sigma coverage it gives.

    .venv/bin/python benchmarks/bench_realistic_diagnostics.py [--seeds 500-502] [--keep /tmp/bench_realistic]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import align_to_fixes, fuse, rts_smooth
from bodyslam.fusion.localize import RfInput, localize
from bodyslam.io import read_motion_steps, read_tum
from bodyslam.meta import read_meta
from bodyslam.steps import motion_from_transform
from testbed.cli import parse_seeds
from testbed.evaluate import consistency
from testbed.scenario import build_world, load_scenario
from testbed.score import score_motion
from testbed.simulate import simulate

BIAS_GRID = ((0.0, 4.0), (0.03, 4.0), (0.03, 6.0), (0.1, 4.0), (0.1, 6.0), (1.0, 4.0))


def mean_error_cm(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.linalg.norm(est - gt, axis=1).mean() * 100)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="500-502")
    ap.add_argument("--scenario", default="realistic")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--keep", type=Path, default=Path("/tmp/bench_realistic"))
    args = ap.parse_args()
    scn = load_scenario(args.scenario)
    bias_rows = {g: [] for g in BIAS_GRID}
    oracle_rows: dict[str, list] = {}
    for seed in parse_seeds(args.seeds):
        d = args.keep / f"{args.scenario}_{seed}"
        if not (d / "meta.json").is_file():
            simulate(scn, seed, d, n_frames=args.frames, force=True)
        true_r = float(build_world(scn, seed, args.frames).tube.centerline.radius_m.mean())
        for name, opts in (("shipped", []), ("mask_auto", ["--mask", "auto"]),
                           ("true_mean_radius", ["--radius-m", f"{true_r}"])):
            out = d / f"motion_{name}.csv"
            if not out.is_file():
                p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "motion", str(d), "--out", str(out), *opts],
                                   capture_output=True, text=True)
                if p.returncode not in (0, 3):
                    sys.exit(p.stderr)
            a = score_motion(d, out)
            print(f"seed {seed} vision {name:17s} distance {a['all']['mae_distance_cm']:.4f} cm, roll "
                  f"{a['all']['mae_roll_deg']:.3f} deg, tilt {a['all']['mae_tilt_deg']:.3f} deg, coverage "
                  f"{a['coverage']:.3f}", flush=True)
        meta = read_meta(d)
        _, gt, grot = read_tum(d / "groundtruth.tum")
        n = len(gt)
        t = np.arange(n) / meta.frame_rate_hz
        rf = RfInput.read(d / meta.rf.file, d / meta.rf.sensors, meta.rf.pathloss)
        est = read_motion_steps(d / "motion_shipped.csv", range(1, n))
        true = [motion_from_transform(grot[k].inv() * grot[k + 1], grot[k].inv().apply(gt[k + 1] - gt[k]), 100,
                                      3e-4, np.radians(0.2)) for k in range(n - 1)]
        locs = {}
        for name, steps in (("estimated steps", est), ("true steps", true)):
            loc = locs[name] = localize(steps, t, rf, meta.frame_rate_hz)
            fixes = np.array([f.position_w_m for f in loc.fixes])
            ok = np.isfinite(fixes).all(axis=1)
            print(f"seed {seed} RF {name:15s} EKF {mean_error_cm(loc.filtered.positions_w_m, gt):.2f} cm, RTS "
                  f"{mean_error_cm(loc.smoothed.positions_w_m, gt):.2f} cm, RF only "
                  f"{mean_error_cm(fixes[ok], gt[ok]):.2f} cm", flush=True)
        for corr, sd in BIAS_GRID:
            e = fuse(est, loc.fixes, loc.rss_dbm, rf.sensors_w_m, rf.normals_w, rf.pathloss, mode="rss",
                     bias_corr_m=corr, bias_sd_db=sd)
            bias_rows[(corr, sd)].append((mean_error_cm(e.positions_w_m, gt),
                                          mean_error_cm(rts_smooth(e).positions_w_m, gt),
                                          float(consistency(e.positions_w_m, e.cov[:, :3, :3], gt)["nees"].mean())))
        for name, v in oracles(est, true, locs["estimated steps"], rf, gt, grot).items():
            oracle_rows.setdefault(name, []).append(v)
            print(f"seed {seed} oracle {name}: " + ", ".join(f"{x:.2f}" for x in v), flush=True)
    print("\nWhat limits the fusion (oracles), mean over the seeds: EKF cm, RTS cm, EKF inside-68%, RTS inside-68%")
    for name, rows in oracle_rows.items():
        print(f"  {name:44s}: " + ", ".join(f"{x:.2f}" for x in np.mean(rows, axis=0)))
    print("\nRSS bias states (estimated steps), mean over the seeds: EKF cm, RTS cm, mean NEES")
    for (corr, sd), rows in bias_rows.items():
        a = np.mean(rows, axis=0)
        print(f"  corr {corr:5.2f} m, sd {sd:.0f} dB: {a[0]:.2f}, {a[1]:.2f}, {a[2]:.1f}")


def rigid_floor(q_c0: np.ndarray, gt: np.ndarray, loc, rf, with_offsets: bool) -> float:
    """Mean error (cm) of the true path's shape ``q`` (first camera frame) placed by its best rigid fit: to the ML
    fixes, then (robust least squares) to the raw readings, with per-sensor PL(d0) and exponent offsets (priors
    3 dB and 0.5) when ``with_offsets``."""
    R0, p0, _ = align_to_fixes(q_c0, loc.fixes)
    if not with_offsets:
        return mean_error_cm(p0 + R0.apply(q_c0), gt)
    S, N, pl, rss = rf.sensors_w_m, rf.normals_w, rf.pathloss, loc.rss_dbm
    m = len(S)
    kk, jj = np.nonzero(np.isfinite(rss))
    y = rss[kk, jj]

    def place(x):
        return x[3:6] + (Rotation.from_rotvec(x[:3]) * R0).apply(q_c0)

    def residuals(x):
        P = place(x)
        diff = S[jj] - P[kk]
        d = np.linalg.norm(diff, axis=1)
        depth = np.maximum(np.sum(diff * N[jj], axis=1), 0.0)
        a, b = x[6:6 + m], x[6 + m:]
        r = (y - pl.mean_rss_dbm(d, depth) - a[jj] + b[jj] * 10 * np.log10(d / pl.d0_m)) / pl.params(depth)[2]
        return np.r_[r, a / 3.0, b / 0.5]

    x = least_squares(residuals, np.r_[np.zeros(3), p0, np.zeros(2 * m)], loss="soft_l1", f_scale=2.0).x
    return mean_error_cm(place(x), gt)


def oracles(est, true, loc, rf, gt, grot) -> dict[str, tuple]:
    """The rows of item 4 (module docstring) for one sequence."""
    q = grot[0].inv().apply(gt - gt[0])
    out = {"true path, rigid fit to the RF fixes": (rigid_floor(q, gt, loc, rf, False),) * 2 + (np.nan,) * 2,
           "true path, rigid fit to RSS + sensor offsets": (rigid_floor(q, gt, loc, rf, True),) * 2 + (np.nan,) * 2}
    missing = [motion_from_transform(grot[k].inv() * grot[k + 1], grot[k].inv().apply(gt[k + 1] - gt[k]), 100,
                                     max(3e-3, 0.3 * float(np.linalg.norm(gt[k + 1] - gt[k]))), np.radians(5.0))
               if not s.has_estimate else s for k, s in enumerate(est)]
    true_start = (grot[0], gt[0])
    for name, steps, init, kw in (("true steps, searched start", true, None, {}),
                                  ("true steps, true start", true, true_start, {}),
                                  ("true steps, true start, bias states", true, true_start,
                                   {"bias_corr_m": 0.03, "bias_sd_db": 4.0}),
                                  ("estimated steps, true start", est, true_start, {}),
                                  ("estimated steps + true motion in their gaps", missing, None, {})):
        f = fuse(steps, loc.fixes, loc.rss_dbm, rf.sensors_w_m, rf.normals_w, rf.pathloss, mode="rss", init=init, **kw)
        s = rts_smooth(f)
        out[name] = (mean_error_cm(f.positions_w_m, gt), mean_error_cm(s.positions_w_m, gt),
                     float(consistency(f.positions_w_m, f.cov[:, :3, :3], gt)["inside_68"].mean()),
                     float(consistency(s.positions_w_m, s.cov[:, :3, :3], gt)["inside_68"].mean()))
    out["shipped (kappa-scaled covariance)"] = (
        mean_error_cm(loc.filtered.positions_w_m, gt), mean_error_cm(loc.smoothed.positions_w_m, gt),
        float(consistency(loc.filtered.positions_w_m, loc.filtered.cov[:, :3, :3], gt)["inside_68"].mean()),
        float(consistency(loc.smoothed.positions_w_m, loc.smoothed.cov[:, :3, :3], gt)["inside_68"].mean()))
    return out


if __name__ == "__main__":
    main()

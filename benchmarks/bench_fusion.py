"""Localization error per algorithm on `thesis` runs, with RMSE / sqrt(PCRB): a thin wrapper around
`testbed evaluate` (testbed/evaluate.py) that prints the table and the wall time of the run and its stages
(render, motion from the frames, filters and scoring: summed over seeds, which run in parallel with --jobs).

    .venv/bin/python benchmarks/bench_fusion.py --seeds 200-219 [--jobs 2] [--out DIR]

Seeds 200+ are used by no test.
"""

from __future__ import annotations

import argparse
import tempfile

from testbed.cli import parse_seeds
from testbed.evaluate import LABELS as NAMES, evaluate, main_report_line
from testbed.scenario import load_scenario



def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="200-209")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--out", default=None)
    ap.add_argument("--jobs", type=int, default=None, help="seeds in parallel (default: one per core)")
    args = ap.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="bench_fusion_")
    rep = evaluate(load_scenario("thesis"), parse_seeds(args.seeds), out, n_frames=args.frames, force=True,
                   progress=lambda m: print(m, flush=True), jobs=args.jobs)
    print(f"\nover seeds {args.seeds} ({args.frames} frames each; errors per frame, cm); report: {out}/report.json")
    print(f"{'algorithm':24s} {'mean':>7s} {'rmse':>7s} {'median':>7s} {'p90':>7s} {'max':>7s}  RMSE/sqrt(PCRB)")
    print(f"{'thesis Fig. 4.22*':24s} RF-only 6.8, hybrid 2.3 (* as reported)")
    for key, a in rep["algorithms"].items():
        print(f"{NAMES[key]:24s} {a['mean_error_cm']:7.2f} {a['rmse_cm']:7.2f} {a['median_error_cm']:7.2f} "
              f"{a['p90_error_cm']:7.2f} {a['max_error_cm']:7.2f}  {a['rmse_over_sqrt_pcrb']:5.2f}")
    print(f"sqrt(mean PCRB) {rep['sqrt_mean_pcrb_cm']:.2f} cm; mean error of a causal filter attaining the bound "
          f"{rep['pcrb_mean_error_cm']:.2f} cm")
    sb = rep["smoothing_bound"]
    print(f"smoothing bound: sqrt(mean) {sb['sqrt_mean_cm']:.2f} cm, mean error of a smoother attaining it "
          f"{sb['mean_error_cm']:.2f} cm; RTS RMSE / sqrt(smoothing bound) {sb['rts_rmse_over_sqrt_bound']:.2f}")
    print(main_report_line(rep))
    sec = rep["seconds"]
    print(f"wall time {sec['wall']:.0f} s with {sec['jobs']} job(s); stage totals over seeds: render "
          f"{sec['render_total']:.0f} s, motion {sec['motion_total']:.0f} s, filters + scoring "
          f"{sec['filters_and_scoring_total']:.0f} s")


if __name__ == "__main__":
    main()

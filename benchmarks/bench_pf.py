"""Particle-filter speed: steps per second of each RF tracking filter with 20,000 particles (issue 6 goal:
>= 200 steps/s on this 2-core machine), on one `ito2016` run (8 receivers, 0.1 s steps), one process.

    .venv/bin/python benchmarks/bench_pf.py [--particles 20000] [--steps 1000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from testbed.rf_tracking import RF_TRACKING_ALGORITHMS, _world, run_algorithm
from testbed.scenario import load_scenario


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--particles", type=int, default=20000)
    ap.add_argument("--steps", type=int, default=1000)
    args = ap.parse_args()
    scn = load_scenario("ito2016", [f"filter.particles={args.particles}",
                                    f"sequence.duration_s={args.steps * 0.1:.1f}"])
    lo, hi, t, pos, wps, rx, meas = _world(scn, 1)
    for name in RF_TRACKING_ALGORITHMS:
        t0 = time.perf_counter()
        est, _ = run_algorithm(name, scn, lo, hi, t, rx, meas, np.random.default_rng(0))
        el = time.perf_counter() - t0
        print(f"{name:16s} {args.particles} particles: {len(t) / el:6.0f} steps/s ({1000 * el / len(t):.2f} ms per "
              f"step: predict, likelihood of 8 receivers, update, resampling when due, estimate)", flush=True)


if __name__ == "__main__":
    main()

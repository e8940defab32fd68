"""What each departure of a real RF channel costs the localization bound (issue 15, "the bound under the
realistic model"; scoring only: the truth is read).

For kept evaluation sequences (``testbed evaluate SCENARIO --out D`` keeps ``D/sequences/seed_*`` with motion.csv),
the mean error of a causal filter and of a smoother that attain the bound (:func:`testbed.bound.channel_bounds`,
:func:`testbed.bound.efficient_mean_error`), with the channel's departures one at a time and all together, taken
from the scenario's ``[rf.channel]``: correlated shadowing, the per-sensor PL(d0) and exponent offsets, sensor
placement. The motion side is the vision's measured step errors on each run, as ``testbed evaluate`` builds it,
or with ``--perfect-steps SD_M SD_DEG`` a vision whose every step errs by that 1-sigma per axis (what better vision
could reach at most).

    .venv/bin/python benchmarks/bench_channel_bound.py D/sequences --scenario realistic [--perfect-steps 1e-4 0.1]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from bodyslam.errors import BodySlamError
from bodyslam.fusion.localize import RfInput
from bodyslam.io import read_motion_steps, read_tum
from bodyslam.meta import read_meta
from testbed.bound import channel_bounds, efficient_mean_error
from testbed.evaluate import _measured_step_noise
from testbed.rf import ChannelModel
from testbed.scenario import load_scenario, rf_channel

# the bound's prior, as testbed evaluate's: no information beyond the abdomen (10 cm, 45 deg)
P0 = np.diag([0.10**2] * 3 + [np.radians(45.0) ** 2] * 3)
PARTS = {"correlated shadowing": ("shadowing_corr_m",), "PL(d0) offsets": ("pl0_sd_db",),
         "exponent offsets": ("alpha_sd",), "placement": ("placement_sd_m",)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", type=Path, help="D/sequences of a testbed evaluate run (seed_* directories)")
    ap.add_argument("--scenario", default="realistic", help="the scenario whose [rf.channel] is the truth")
    ap.add_argument("--perfect-steps", nargs=2, type=float, metavar=("SD_M", "SD_DEG"),
                    help="every step's 1-sigma per axis instead of the vision's measured errors")
    args = ap.parse_args()
    try:
        full = rf_channel(load_scenario(args.scenario))
    except BodySlamError as exc:  # an unknown scenario or a bad [rf.channel]: one line, not a traceback
        raise SystemExit(f"error: {exc}") from None
    cases = {"calibration's model (ideal)": ChannelModel()}
    for name, keys in PARTS.items():
        cases[f"{name} only"] = ChannelModel(**{k: getattr(full, k) for k in keys})
    cases["all (the scenario's channel)"] = dataclasses.replace(full, dropout_prob=0.0, outlier_prob=0.0)
    seqs = sorted(p for p in args.sequences.glob("seed_*") if (p / "motion.csv").is_file())
    if not seqs:
        raise SystemExit(f"no seed_*/motion.csv under {args.sequences}")
    out = {c: ([], [], [], []) for c in cases}
    for d in seqs:
        meta = read_meta(d)
        rf = RfInput.read(d / meta.rf.file, d / meta.rf.sensors, meta.rf.pathloss)
        _, gt, grot = read_tum(d / "groundtruth.tum")
        sig_t, sig_r = _measured_step_noise(read_motion_steps(d / "motion.csv", range(1, len(gt))), gt, grot)
        if args.perfect_steps:
            sig_t = np.full_like(sig_t, args.perfect_steps[0])
            sig_r = np.full_like(sig_r, np.radians(args.perfect_steps[1]))
        for name, ch in cases.items():
            f, s = channel_bounds(gt, grot, sig_t, sig_r, rf.sensors_w_m, rf.normals_w, rf.pathloss, P0, ch,
                                  full_state=True)
            for i, b in enumerate((f[:, :3, :3], s[:, :3, :3])):
                out[name][i].append(efficient_mean_error(b).mean() * 100)
            for i, b in enumerate((f[:, 3:, 3:], s[:, 3:, 3:])):  # the orientation's small-angle error vector
                out[name][2 + i].append(np.degrees(efficient_mean_error(b).mean()))
        print(f"{d.name}: all {out[name][0][-1]:.2f} / {out[name][1][-1]:.2f} cm", flush=True)
    steps = (f"every step {args.perfect_steps[0] * 1000:g} mm / {args.perfect_steps[1]:g} deg per axis"
             if args.perfect_steps else "the vision's measured step errors")
    print(f"\n{len(seqs)} runs ({seqs[0].name} .. {seqs[-1].name}), {steps}; mean error of an estimator at the "
          "bound: position (cm), orientation (deg)")
    print(f"{'channel':34s} {'causal cm':>10s} {'smoother cm':>12s} {'causal deg':>11s} {'smoother deg':>13s}")
    for name, (f, s, fo, so) in out.items():
        print(f"{name:34s} {np.mean(f):10.2f} {np.mean(s):12.2f} {np.mean(fo):11.1f} {np.mean(so):13.1f}")


if __name__ == "__main__":
    main()

"""The per-step fit's own 1-sigma against the truth, with the lumen radius's share taken out (issue 16 item 3).

For every estimated step of kept sequences (``testbed evaluate ... --out D`` keeps ``D/sequences/seed_*`` with
motion.csv): the 1-sigma distance less the radius prior's share ``sd/r |d|`` (what the fusion applies: the fit's
own and the lumen-shape share ``lumen_shape_sd_rel |d|`` where meta.json states one) against the error of the
distance rescaled by the true local radius over the told one (the radius error is what the prior's share covers;
what is left is the fit's and the shape's). An honest 1-sigma puts ~68% / 95% of ``|z|`` within 1 / 2. Printed
for all estimated steps and for each status (``ok``; ``wall``: a frame of the pair faces the wall, 1-sigma
inflated; ``bridged``: a share of a gap).

    .venv/bin/python benchmarks/bench_step_sigma.py D/sequences [--ahead-m 0.02]

The local radius is the centre line's at the step's midpoint plus ``--ahead-m`` (the wall the camera sees most of
lies ahead): an approximation, so the rescaled error is an upper bound of the fit's own on a varying lumen.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from bodyslam.io import read_motion_csv
from bodyslam.meta import read_meta
from bodyslam.steps import StepStatus

STATUSES = (StepStatus.OK, StepStatus.WALL, StepStatus.BRIDGED)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("sequences", type=Path)
    ap.add_argument("--ahead-m", type=float, default=0.02)
    args = ap.parse_args()
    rows, status = [], []
    for d in sorted(args.sequences.glob("seed_*")):
        if not (d / "motion.csv").exists():
            continue
        truth = read_motion_csv(d / "motion_truth.csv")
        s_at = {int(r["frame"]): float(r["s_m"]) for r in csv.DictReader(open(d / "labels.csv"))}
        cl = np.loadtxt(d / "centerline.csv", delimiter=",", skiprows=1)
        meta = read_meta(d)
        r_told, sd, shape = meta.tube_radius_m, meta.tube_radius_sd_m, meta.lumen_shape_sd_rel
        for k, r in read_motion_csv(d / "motion.csv").items():
            if r["status"] not in STATUSES:
                continue
            de, sig = r["distance_m"], r["sigma_distance_m"]
            sig_fs = np.sqrt(max(sig**2 - (sd / r_told * de) ** 2, 1e-18))  # the fit's and the shape's
            r_loc = np.interp(0.5 * (s_at[k] + s_at[k - 1]) + args.ahead_m, cl[:, 0], cl[:, 4])
            rows.append((de * r_loc / r_told - truth[k]["distance_m"], de - truth[k]["distance_m"], sig_fs, sig,
                         np.sqrt(max(sig_fs**2 - (shape * de) ** 2, 1e-18))))
            status.append(r["status"])
    if not rows:
        raise SystemExit(f"{args.sequences}: no seed_*/motion.csv with estimated steps (give a `testbed evaluate` "
                         "run's sequences/ folder)")
    a, status = np.array(rows), np.array(status)
    print(f"{len(a)} estimated steps in {args.sequences}")
    for name in ("all", *STATUSES):
        sel = np.ones(len(a), bool) if name == "all" else status == name
        if sel.any():
            report(a[sel], f"{name} ({sel.sum()} steps)")


def report(a: np.ndarray, title: str) -> None:
    print(f"-- {title}")
    z_fs, z_fit, z_all = np.abs(a[:, 0] / a[:, 2]), np.abs(a[:, 0] / a[:, 4]), np.abs(a[:, 1] / a[:, 3])
    print(f"fit's own 1-sigma vs radius-rescaled error: within 1 / 2 sigma {np.mean(z_fit <= 1):.3f} / "
          f"{np.mean(z_fit <= 2):.3f}, median |z| {np.median(z_fit):.2f}; median 1-sigma "
          f"{np.median(a[:, 4]) * 1e3:.3f} mm, median |error| {np.median(np.abs(a[:, 0])) * 1e3:.3f} mm")
    print(f"fit + lumen-shape 1-sigma (what the fusion applies) vs radius-rescaled error: within 1 / 2 sigma "
          f"{np.mean(z_fs <= 1):.3f} / {np.mean(z_fs <= 2):.3f}; median 1-sigma {np.median(a[:, 2]) * 1e3:.3f} mm")
    print(f"stated 1-sigma (radius share included) vs raw error: within 1 / 2 sigma {np.mean(z_all <= 1):.3f} / "
          f"{np.mean(z_all <= 2):.3f}; median |error| {np.median(np.abs(a[:, 1])) * 1e3:.3f} mm")


if __name__ == "__main__":
    main()

"""Centre line extracted from the real CT gut mesh, scored against the expert mid-line (mm).

    .venv/bin/python benchmarks/bench_centerline.py [--anatomy ../shared/data/anatomy] [--pitch-mm 1.0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from testbed.anatomy import extract_centerline, load_reference_csv, score_centerline

VOXEL_MM = (0.832031, 0.832031, 1.0)  # EdinGCA_3D_00090_1_1.json "voxel_size"
SI_PROPER = 2610  # expert path index of the gastro-duodenal junction: 0..2610 is the small intestine proper


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--anatomy", default=str(Path(__file__).resolve().parents[2] / "shared/data/anatomy"))
    ap.add_argument("--mesh", default="small_intestine_20k.obj")
    ap.add_argument("--pitch-mm", type=float, default=1.0)
    args = ap.parse_args()
    conv = Path(args.anatomy) / "EdinGCA_3D_00090" / "converted"
    t = time.perf_counter()
    cl = extract_centerline(conv / args.mesh, VOXEL_MM, pitch_mm=args.pitch_mm)
    el = time.perf_counter() - t
    ref = load_reference_csv(conv / "small_intestine_path_centerline.csv", VOXEL_MM)
    ours = cl.points_w * 1000.0
    print(f"{args.mesh} at {args.pitch_mm} mm: {el:.1f} s, centre line {cl.length_m:.3f} m "
          f"(expert path {np.sum(np.linalg.norm(np.diff(ref, axis=0), axis=1)) / 1000:.3f} m)")
    for name, r in (("whole path (ICV..POL)", ref), ("small intestine proper (ICV..GDJ)", ref[: SI_PROPER + 1])):
        sc = score_centerline(ours, r)
        print(f"  {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in sc.items()))


if __name__ == "__main__":
    main()

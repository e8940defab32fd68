"""Real capsule frames moved through a lumen of known shape: issue 16's clip checks on real texture and optics.

Each clip is made by :func:`testbed.real_clip.make_clip` (`testbed real-clip`; its docstring says how): one real
frame seen from a camera that advances ``--step-mm`` a frame along a lumen's axis and rolls ``--roll-deg``, the
lumen a cylinder of ``--radius-cm`` (default: the 1.25 cm `bodyslam batch` assumes) or folded (``--lobes``,
``--lobe-depth``), the camera on its axis or ``--offset-frac`` radii off it, the light moving with the camera
(``--light capsule``) or the frame's shading moving with the wall (``baked``). The texture, the colour, the specular
spots, the field stop and the logo are real; the geometry is known. The default (a centred camera in the assumed
cylinder) is the easiest real clip there is for the pipeline's lumen model: what fails there fails for a reason
other than the shape. The other shapes show what a lumen that is not the assumed cylinder does to the same frames.

Each clip is handed to `bodyslam batch` as a plain folder of PNGs with its defaults (assumed lens, frame rate and
radius, as a user runs it), forwards and reversed, and scored as `bench_clips.py` scores testbed clips: steps with
a full estimate, the share of those pointing forward (+z), the path forwards against reversed (issue 16: within
15%), the path against the true one (and against the true one in units of the assumed radius, which is what a
monocular step can measure at best), and Table 4.1 of the forward clip (`testbed score-motion`'s).

    .venv/bin/python benchmarks/bench_real_warp.py FRAME.png [FRAME.png ...] --out DIR [--step-mm 0.5,1,2]
        [--roll-deg 0,5] [--radius-cm R] [--lobes K --lobe-depth A] [--offset-frac F] [--light capsule|baked]
        [--axis dark|centre] [--fov-deg 156] [--frames-per-clip 18] [--max-magnification 2] [--mode fast]
        [--json FILE]

The five real frames in ../shared/data/real are for seeing how the pipeline behaves, not for tuning (their
README): report what this prints; do not choose parameters by it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_clips import both_ways, full_and_forward  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bodyslam.errors import InputError  # noqa: E402
from testbed.real_clip import PRIOR_RADIUS_M, make_clip  # noqa: E402
from testbed.score import score_motion  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames", nargs="+", type=Path, help="real frames (PNG/JPEG)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--step-mm", default="0.5,1,2", help="advance per frame, mm (comma list; default 0.5,1,2)")
    ap.add_argument("--roll-deg", default="0", help="roll per frame, degrees (comma list; default 0)")
    ap.add_argument("--axis", choices=("centre", "dark"), default="dark",
                    help="the lumen's axis: toward the frame's darkest area (default) or the optical axis")
    ap.add_argument("--radius-cm", type=float, default=100 * PRIOR_RADIUS_M,
                    help="the lumen's true (mean) radius, cm (default 1.25, the radius batch assumes)")
    ap.add_argument("--lobes", type=int, default=0, help="folds of the cross-section (0: a circle)")
    ap.add_argument("--lobe-depth", type=float, default=0.0,
                    help="r(phi) = R (1 + depth cos(lobes phi)); 0.3 with 4 lobes: a folded lumen")
    ap.add_argument("--offset-frac", type=float, default=0.0,
                    help="the camera's distance from the lumen's axis, in radii (default 0: centred)")
    ap.add_argument("--light", choices=("capsule", "baked"), default="capsule",
                    help="capsule: the light moves with the camera (default); baked: the frame's shading moves "
                         "with the wall")
    ap.add_argument("--fov-deg", type=float, default=156.0,
                    help="the lens the clips are made with (batch assumes 156 for a plain folder: another value "
                         "shows a wrong lens assumption)")
    ap.add_argument("--frames-per-clip", type=int, default=18, help="at most (default 18, a real clip's length)")
    ap.add_argument("--max-magnification", type=float, default=2.0,
                    help="a clip ends before the first frame that enlarges the real frame more than this (default 2: "
                         "past it the texture is the real pixels interpolated, not real texture)")
    ap.add_argument("--noise", type=float, default=2.0, help="sensor noise, grey levels (default 2)")
    ap.add_argument("--jpeg", type=int, default=85, help="JPEG quality of each frame's round trip (default 85)")
    ap.add_argument("--mode", default=None, help="`bodyslam batch --mode` (default: batch's own)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    try:
        steps = [float(x) for x in args.step_mm.split(",")]
        rolls = [float(x) for x in args.roll_deg.split(",")]
    except ValueError as exc:
        raise SystemExit(f"--step-mm / --roll-deg: comma lists of numbers ({exc})") from None
    L = args.frames_per_clip
    extra = ["--mode", args.mode] if args.mode else []
    results = []
    for fpath in args.frames:
        for step_mm in steps:
            for roll_deg in rolls:
                name = f"{fpath.stem}_s{step_mm:g}_r{roll_deg:g}"
                d = args.out / name
                try:
                    tr = make_clip(fpath, d / "seq", n_frames=L, step_m=step_mm / 1000.0,
                                   roll_rad=math.radians(roll_deg), radius_m=args.radius_cm / 100.0,
                                   lobes=args.lobes, lobe_depth=args.lobe_depth, offset_frac=args.offset_frac,
                                   light=args.light, axis=args.axis, noise=args.noise, jpeg_quality=args.jpeg,
                                   seed=args.seed, fov_deg=args.fov_deg, max_magnification=args.max_magnification,
                                   force=True)
                except InputError as exc:
                    raise SystemExit(f"{fpath}: {exc}") from None
                frames = sorted((d / "seq" / "frames").iterdir())
                n = len(frames)  # plain folders (no meta.json): batch's defaults, as on a real clip
                (rc_f, sf, mf), (rc_r, sr, mr) = both_ways(frames, d, extra)
                true_m = tr["advance_m"]
                read_m = (n - 1) * tr["step_in_prior_radius_m"]  # the true path in units of the assumed radius
                pf, pr = sf["path_travelled_m"], sr["path_travelled_m"]
                full_f, fwd_f = full_and_forward(mf)
                full_r, fwd_r = full_and_forward(mr)
                table = score_motion(d / "seq", d / "out_forward" / "forward" / "motion.csv")["all"]
                r = {"clip": name, "frames": n, "magnification_max": max(tr["magnification"]),
                     "axis_deg_off_optical": tr["axis_deg_off_optical"], "exit": [rc_f, rc_r],
                     "true_path_cm": 100 * true_m, "path_forward_cm": 100 * pf,
                     "sd_forward_cm": 100 * sf["sd_path_travelled_m"], "path_reversed_cm": 100 * pr,
                     "disagreement": abs(pf - pr) / max(pf, pr, 1e-12), "end_error_rel": (pf - true_m) / true_m,
                     "end_error_rel_in_assumed_radius": pf / read_m - 1,
                     "inside_1sigma": abs(pf - true_m) <= sf["sd_path_travelled_m"],
                     "full_estimate_frac": full_f, "forward_frac": fwd_f, "full_estimate_frac_reversed": full_r,
                     "forward_frac_reversed": fwd_r, "ft_frames": sf["classes"]["FT"],
                     "fl_frames": sf["classes"]["FL"], "steps": sf["steps"], "steps_reversed": sr["steps"],
                     "table_4_1": table}
                results.append(r)
                print(f"{name} ({n} frames, up to {r['magnification_max']:.2f}x): path {r['path_forward_cm']:.2f} "
                      f"+- {r['sd_forward_cm']:.2f} cm forwards, "
                      f"{r['path_reversed_cm']:.2f} reversed ({r['disagreement']:.0%} apart), "
                      f"{r['true_path_cm']:.2f} true; {full_f:.0%} of steps estimated ({full_r:.0%} reversed), "
                      f"{fwd_f:.0%} of them forward ({fwd_r:.0%} reversed, where backward is right); FT/FL "
                      f"{r['ft_frames']}/{r['fl_frames']}", flush=True)
    dis = np.array([r["disagreement"] for r in results])
    err = np.array([r["end_error_rel"] for r in results])
    summary = {"clips": len(results), "frames_per_clip_at_most": L,
               "frames_per_clip_mean": float(np.mean([r["frames"] for r in results])),
               "agree_within_15pct": float(np.mean(dis <= 0.15)), "median_disagreement": float(np.median(dis)),
               "end_error_mean": float(np.mean(err)), "end_error_median_abs": float(np.median(np.abs(err))),
               "end_error_in_assumed_radius_mean": float(np.mean([r["end_error_rel_in_assumed_radius"]
                                                                  for r in results])),
               "full_estimate_frac_mean": float(np.mean([r["full_estimate_frac"] for r in results])),
               "forward_frac_mean": float(np.nanmean([r["forward_frac"] for r in results])),
               "inside_1sigma": float(np.mean([r["inside_1sigma"] for r in results])),
               "fl_frames": int(sum(r["fl_frames"] for r in results))}
    scored = [r["table_4_1"] for r in results if r["table_4_1"].get("n_steps_scored")]
    for key in ("mae_distance_cm", "mae_distance_scale_aligned_cm", "mae_roll_deg", "mae_tilt_deg"):
        summary[key] = (float(np.average([t[key] for t in scored], weights=[t["n_steps_scored"] for t in scored]))
                        if scored else float("nan"))  # step-weighted over the clips
    print(f"\n{len(results)} clips of {summary['frames_per_clip_mean']:.1f} frames on average (at most {L}): "
          f"{summary['full_estimate_frac_mean']:.0%} of steps estimated, "
          f"{summary['forward_frac_mean']:.0%} of them forward; forwards and reversed within 15% on "
          f"{summary['agree_within_15pct']:.0%} (median {summary['median_disagreement']:.1%} apart); path at the end "
          f"{summary['end_error_mean']:+.1%} on average ({summary['end_error_median_abs']:.1%} median absolute; "
          f"{summary['end_error_in_assumed_radius_mean']:+.1%} against the true path in units of the assumed "
          f"radius), inside its 1-sigma on {summary['inside_1sigma']:.0%}; per step (Table 4.1, full estimates) "
          f"distance {summary['mae_distance_cm']:.4f} cm (scale-aligned "
          f"{summary['mae_distance_scale_aligned_cm']:.4f}),"
          f" roll {summary['mae_roll_deg']:.3f} deg, tilt {summary['mae_tilt_deg']:.3f} deg; "
          f"{summary['fl_frames']} frames called FL")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "clips": results}, indent=1))


if __name__ == "__main__":
    main()

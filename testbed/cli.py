"""The ``testbed`` command: simulate sequences, look at them, extract centre lines from anatomy.

Subcommands
-----------
simulate SCENARIO --seed N [--frames K] --out DIR [--set k=v ...] [--jobs J] [--force]
contact-sheet SEQDIR --out sheet.png [--count N] [--cols C]
centerline MESH [MESH ...] --out centerline.csv [--voxel-size X Y Z | --model-config JSON] [--pitch-mm P]
           [--reference CSV|JSN]
real-clip FRAME --out DIR [--frames K] [--step-mm S] [--roll-deg R] [--radius-cm C] [--lobes N --lobe-depth A]
          [--offset-frac F] [--light capsule|baked]   a clip of known motion made from one real frame
score-motion SEQDIR motion.csv [--json report.json]   Table 4.1 and the path travelled against the truth
evaluate SCENARIO --seeds N|A-B|a,b --out DIR [--frames K] [--jobs J]   every algorithm on the same runs: report.json + report.html
scenarios      list the shipped scenarios
"""

from __future__ import annotations

import argparse
import math
import sys

from bodyslam.cliutil import Progress, jobs_count, run_cli


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="testbed", description="Virtual intestine testbed with exact ground truth")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("simulate", help="render a scenario into a sequence directory")
    s.add_argument("scenario", help="shipped scenario name (see 'testbed scenarios') or a .toml path")
    s.add_argument("--seed", type=int, required=True)
    s.add_argument("--frames", type=int, default=None, help="number of frames (default: the scenario's)")
    s.add_argument("--out", required=True, help="output sequence directory (must be empty unless --force)")
    s.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a scenario field, e.g. --set tube.radius_m=0.0125 (repeatable)")
    s.add_argument("--jobs", type=jobs_count, default=None,
                   help="render processes (default: one per core for 60+ frames, else 1: starting workers "
                        "costs ~2 s)")
    s.add_argument("--force", action="store_true", help="write into a non-empty directory")
    s.add_argument("--speed-model", default=None,
                   help="drive the capsule with a speed model fitted from video (bodyslam speed-stats)")

    c = sub.add_parser("contact-sheet", help="write a PNG grid of a sequence's frames")
    c.add_argument("seqdir")
    c.add_argument("--out", required=True)
    c.add_argument("--count", type=int, default=24, help="frames shown, evenly spaced (default 24)")
    c.add_argument("--cols", type=int, default=6)

    rc = sub.add_parser("real-clip", help="a clip of known motion made from one real capsule frame (testbed.real_clip)")
    rc.add_argument("frame", help="a real capsule frame (PNG/JPEG)")
    rc.add_argument("--out", required=True, help="output sequence directory (must be empty unless --force)")
    rc.add_argument("--frames", type=int, default=18, help="frames in the clip (default 18)")
    rc.add_argument("--step-mm", type=float, default=1.0, help="advance along the lumen per frame, mm (default 1)")
    rc.add_argument("--roll-deg", type=float, default=0.0, help="roll per frame about the optical axis, deg")
    rc.add_argument("--radius-cm", type=float, default=1.25,
                    help="the lumen's true (mean) radius, cm (default 1.25, the prior meta.json states)")
    rc.add_argument("--lobes", type=int, default=0, help="folds of the cross-section (default 0: a circle)")
    rc.add_argument("--lobe-depth", type=float, default=0.0, help="r(phi) = R (1 + depth cos(lobes phi))")
    rc.add_argument("--offset-frac", type=float, default=0.0, help="the camera's distance from the axis, in radii")
    rc.add_argument("--light", choices=("capsule", "baked"), default="capsule",
                    help="capsule: the light moves with the camera (default); baked: the frame's shading moves "
                         "with the wall")
    rc.add_argument("--axis", choices=("dark", "centre"), default="dark",
                    help="the lumen's axis toward the frame's darkest area (default) or along the optical axis")
    rc.add_argument("--noise", type=float, default=2.0, help="sensor noise, grey levels (default 2)")
    rc.add_argument("--jpeg", type=int, default=85, help="JPEG quality of each frame's round trip (0: none)")
    rc.add_argument("--frame-rate", type=float, default=2.0, help="frames per second (default 2)")
    rc.add_argument("--fov-deg", type=float, default=156.0,
                    help="the lens the clip is made with, equidistant, degrees across the shorter side (default 156: "
                         "what bodyslam batch assumes for a plain folder)")
    rc.add_argument("--label", choices=("FT", "FL", ""), default="",
                    help="the frame's class, written into the truth (default: none)")
    rc.add_argument("--seed", type=int, default=0, help="the noise's seed")
    rc.add_argument("--max-magnification", type=float, default=None,
                    help="end the clip before the first frame that enlarges the real frame more than this (e.g. 2: "
                         "past it the texture is the real pixels interpolated); default: every frame, with a warning")
    rc.add_argument("--force", action="store_true", help="write into a non-empty directory")

    sm = sub.add_parser("score-motion", help="score a motion.csv against the sequence's truth (Table 4.1)")
    sm.add_argument("seqdir")
    sm.add_argument("motion_csv")
    sm.add_argument("--json", default=None, help="write the report as JSON (default: next to motion.csv)")

    ev = sub.add_parser("evaluate", help="run every localization algorithm on the same rendered runs and score")
    ev.add_argument("scenario")
    ev.add_argument("--seeds", required=True, help="N (seeds 0..N-1), A-B, or a,b,c")
    ev.add_argument("--out", required=True)
    ev.add_argument("--frames", type=int, default=None)
    ev.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ev.add_argument("--keep-frames", action="store_true", help="keep the rendered frames (default: deleted)")
    ev.add_argument("--force", action="store_true")
    ev.add_argument("--reuse", action="store_true",
                    help="score again the sequences of an earlier run in --out (their motion.csv, RF and truth): no "
                         "rendering, no motion; for re-scoring after a change to the filters (a seed without an "
                         "earlier run is rendered and run, and said; no earlier run of any seed is an error)")
    ev.add_argument("--jobs", type=jobs_count, default=None,
                    help="seeds run in parallel, one per core by default (1: one seed at a time on every core)")

    e = sub.add_parser("centerline", help="extract the centre line of an anatomical mesh (OBJ/STL/PLY/OFF/GLB, or "
                                          "legacy VTK as the GCA gut models ship their surfaces)")
    e.add_argument("mesh", nargs="+", help="mesh file; several: one mesh in pieces (a model's segmented surfaces, "
                                           "one file per region), in the same units")
    e.add_argument("--out", required=True, help="centre line CSV (s_m,x_m,y_m,z_m,radius_m)")
    units = e.add_mutually_exclusive_group()
    units.add_argument("--voxel-size", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                       help="mm per mesh unit along x, y, z (the CT voxel size when the mesh is in grid units; "
                            "default 1 1 1: a mesh in mm)")
    units.add_argument("--model-config", metavar="JSON",
                       help="a GCA model's config (EdinGCA_3D_*.json): its voxel_size is the mm per mesh unit")
    e.add_argument("--pitch-mm", type=float, default=1.0, help="voxelisation pitch in mm (default 1)")
    e.add_argument("--reference", help="expert mid-line to score against, in mesh units: a CSV with x,y,z columns "
                                       "or a GCA path file (Paths/*.jsn)")
    e.add_argument("--repair", action="store_true",
                   help="fill a mesh's small holes first (trimesh fill_holes); without it, and for what stays open, "
                        "every open boundary is capped and the pieces' centre lines chained (testbed.anatomy)")

    sub.add_parser("scenarios", help="list the shipped scenarios")
    return p


def _paper_system(scn: dict):
    """The module that simulates and evaluates a scenario without frames (``[system] kind``), or None."""
    import importlib

    from bodyslam.errors import ConfigError

    kind = scn.get("system", {}).get("kind", "body_slam")
    modules = {"rf_tracking": "testbed.rf_tracking", "hybrid_imu": "testbed.jeong", "magnetic": "testbed.popek"}
    if kind == "body_slam":
        return None
    if kind not in modules:
        raise ConfigError(f"[system] kind must be one of {['body_slam', *modules]}, got {kind!r}")
    return importlib.import_module(modules[kind])


def _simulate(args) -> int:
    from testbed.scenario import load_scenario
    from testbed.simulate import simulate

    scn = load_scenario(args.scenario, args.overrides)
    system = _paper_system(scn)
    if system is not None:  # papers 000-003: RF (and IMU) readings, no frames
        from pathlib import Path

        from testbed.simulate import prepare_output_dir

        prepare_output_dir(Path(args.out), args.force)
        print(f"{args.out}: {system.simulate_scenario(scn, args.seed, args.out)}")
        return 0
    if args.speed_model:
        from bodyslam.vision.speed import load_speed_model

        # the fitted model replaces the scenario's motion statistics (frame rate stays the scenario's)
        fitted = {k: v for k, v in load_speed_model(args.speed_model).items() if k != "frame_rate_hz"}
        scn["motion"] = {**scn.get("motion", {}), **fitted}
    truth = simulate(scn, args.seed, args.out, n_frames=args.frames, jobs=args.jobs, force=args.force,
                     progress=Progress(f"render {scn.get('name')}"),
                     label_progress=Progress(f"label {scn.get('name')} (FT/FL, moving wall)"))
    print(f"{args.out}: {truth['n_frames']} frames; mean step {truth['mean_step_cm']:.3f} cm, "
          f"roll {truth['mean_roll_deg']:.2f} deg, tilt {truth['mean_tilt_deg']:.2f} deg per step; "
          f"advances {100 * truth['advance_m']:.1f} cm along the centre line; {truth['n_ft']} FT / {truth['n_fl']} FL")
    return 0


def _real_clip(args) -> int:
    from testbed.real_clip import make_clip

    tr = make_clip(args.frame, args.out, n_frames=args.frames, step_m=args.step_mm / 1000.0,
                   roll_rad=math.radians(args.roll_deg), radius_m=args.radius_cm / 100.0, lobes=args.lobes,
                   lobe_depth=args.lobe_depth, offset_frac=args.offset_frac, light=args.light, axis=args.axis,
                   noise=args.noise, jpeg_quality=args.jpeg, seed=args.seed, frame_rate_hz=args.frame_rate,
                   fov_deg=args.fov_deg,
                   label=args.label, max_magnification=args.max_magnification, force=args.force,
                   progress=Progress("real-clip"))
    if tr["n_frames"] < args.frames:
        print(f"note: the clip ends at {tr['n_frames']} frames: the next would enlarge the real frame more than "
              f"{args.max_magnification:g}x")
    print(f"{args.out}: {tr['n_frames']} frames from {args.frame}; advances {100 * tr['advance_m']:.2f} cm along a "
          f"lumen of {100 * tr['radius_m']:g} cm whose axis is {tr['axis_deg_off_optical']:.0f} deg off the optical "
          f"axis (a step reads {1000 * tr['step_in_prior_radius_m']:.3f} mm in the prior's radius)")
    if tr["frames_past_2x"]:
        first = next(i for i, x in enumerate(tr["magnification"]) if x > 2.0)
        print(f"warning: {tr['frames_past_2x']} frame(s) from frame {first} on enlarge the real frame more than 2x "
              f"(up to {max(tr['magnification']):.1f}x): their texture is its pixels interpolated, not real texture; "
              "use a shorter advance (--frames x --step-mm) for figures about real frames")
    return 0


def _contact(args) -> int:
    from testbed.contact import contact_sheet

    n = contact_sheet(args.seqdir, args.out, count=args.count, cols=args.cols)
    print(f"{args.out}: {n} frames")
    return 0


def parse_seeds(text: str) -> list[int]:
    """``--seeds``: ``N`` (a count: seeds 0..N-1), ``A-B`` (A to B, both included) or ``a,b,c``; one that names no
    seed (``0``, ``5-3``) is refused."""
    from bodyslam.errors import ConfigError

    try:
        if "," in text:
            seeds = [int(x) for x in text.split(",")]
        elif "-" in text:
            a, b = (int(x) for x in text.split("-"))
            seeds = list(range(a, b + 1))
        else:
            seeds = list(range(int(text)))
    except ValueError:
        raise ConfigError(f"--seeds must be N, A-B or a,b,c; got {text!r}") from None
    if not seeds:
        raise ConfigError(f"--seeds {text!r} names no seed (N counts seeds 0..N-1; A-B needs A <= B)")
    return seeds


def _seeds_said(text: str, seeds: list[int]) -> list[int]:
    """The seeds of ``--seeds``, with a line where a count was given: ``--seeds 700`` is seeds 0-699, not seed 700."""
    if text.strip().isdigit() and len(seeds) > 1:
        print(f"--seeds {text.strip()}: {len(seeds)} runs, seeds 0-{seeds[-1]} (one seed alone: --seeds "
              f"{text.strip()}-{text.strip()})", flush=True)
    return seeds


def _evaluate(args) -> int:
    from testbed.evaluate import evaluate, main_report_line
    from testbed.scenario import load_scenario

    scn = load_scenario(args.scenario, args.overrides)
    seeds = _seeds_said(args.seeds, parse_seeds(args.seeds))  # before any work: a count is not a seed
    system = _paper_system(scn)
    if system is not None:
        from pathlib import Path

        from testbed.simulate import prepare_output_dir

        prepare_output_dir(Path(args.out), args.force)
        rep = system.evaluate_scenario(scn, seeds, args.out, jobs=args.jobs,
                                       progress=lambda msg: print(msg, flush=True))
        print(system.report_line(rep))
        print(f"wrote {args.out}/report.json, report.html and plots")
        return 0
    report = evaluate(scn, seeds, args.out, n_frames=args.frames, force=args.force or args.reuse,
                      keep=args.keep_frames, progress=lambda msg: print(msg, flush=True), jobs=args.jobs,
                      reuse=args.reuse)
    print(main_report_line(report))
    print(f"wrote {args.out}/report.json and plots")
    return 0


def _score_motion(args) -> int:
    from pathlib import Path

    from bodyslam.io import write_json
    from bodyslam.meta import read_meta
    from testbed.score import format_table, score_motion, score_path

    rep = score_motion(args.seqdir, args.motion_csv)
    if (Path(args.seqdir) / "meta.json").exists():
        from bodyslam.io import read_motion_steps
        from bodyslam.vision.lumen_scale import radius_sd_rel_after, scale_of_steps
        from bodyslam.vision.odometry import MotionSettings, lumen_scale_measured

        meta = read_meta(args.seqdir)
        # the radius's 1-sigma the steps carry: the lumen scale's where the motion stage applied one (its ring ratios
        # in motion.csv), else the prior's -- as testbed evaluate and bodyslam localize --motion take it
        steps = read_motion_steps(args.motion_csv, range(1, meta.n_frames))
        lumen = scale_of_steps(steps, lumen_scale_measured(MotionSettings(), meta.radius_sd_rel))
        rel, radius_m = radius_sd_rel_after(lumen, meta.radius_sd_rel), meta.tube_radius_m
    else:  # Table 4.1 needs only the truth; the path's 1-sigma then leaves out the radius prior's spread
        rel, radius_m = 0.0, None
        print(f"note: {args.seqdir}: no meta.json, so the path's 1-sigma has no lumen-radius share and a step lost "
              f"to motion no least length")
    rep["path_travelled"] = p = score_path(args.seqdir, args.motion_csv, rel, radius_m)
    out = Path(args.json) if args.json else Path(args.motion_csv).with_suffix(".score.json")
    write_json(out, rep)
    print(format_table(rep))
    print(f"path travelled (vision only): {p['estimated_m'] * 100:.1f} +- {p['sigma_m'] * 100:.1f} cm against "
          f"{p['true_m'] * 100:.1f} true ({p['error_rel']:+.1%}, {p['z']:+.1f} sigma; frames inside 1-sigma "
          f"{p['frames_inside_1sigma']:.0%})")
    print(f"wrote {out}")
    return 0


def _centerline(args) -> int:
    from testbed.anatomy import extract_centerline, load_reference, score_centerline, voxel_size_from_config

    if args.model_config:
        voxel_mm = voxel_size_from_config(args.model_config)
        print(f"mesh units: {' x '.join(f'{v:g}' for v in voxel_mm)} mm (voxel_size of {args.model_config})")
    else:
        voxel_mm = tuple(args.voxel_size) if args.voxel_size else (1.0, 1.0, 1.0)
    if args.reference:  # read before the minutes of extraction, so a bad file is told at once
        ref_mm = load_reference(args.reference, voxel_mm)
    cl = extract_centerline(args.mesh, voxel_size_mm=voxel_mm, pitch_mm=args.pitch_mm, repair=args.repair)
    cl.write_csv(args.out)
    print(f"{args.out}: {cl.length_m:.3f} m, {len(cl.s_m)} points, radius "
          f"{cl.radius_m.min() * 1000:.1f}-{cl.radius_m.max() * 1000:.1f} mm")
    if args.reference:
        sc = score_centerline(cl.points_w * 1000.0, ref_mm)
        print("score vs reference: " + ", ".join(f"{k} {v:.2f}" for k, v in sc.items()))
    return 0


def _scenarios(args) -> int:
    from testbed.scenario import load_scenario, scenario_names

    for name in scenario_names():
        print(f"{name}: {load_scenario(name).get('description', '')}")
    return 0


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    return {"evaluate": _evaluate, "score-motion": _score_motion, "simulate": _simulate, "contact-sheet": _contact,
            "real-clip": _real_clip, "centerline": _centerline, "scenarios": _scenarios}[args.cmd](args)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_cli(_main, argv, verbose="-v" in argv or "--verbose" in argv)


if __name__ == "__main__":
    sys.exit(main())

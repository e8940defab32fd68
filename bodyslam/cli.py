"""The ``bodyslam`` command: the pipeline's stages for users, one subcommand per stage.

Every subcommand is thin: it parses, calls one library function and prints. ``bodyslam <cmd> --help`` shows a
one-line description and an example. The option lists come from :mod:`bodyslam.choices` (no OpenCV or SciPy at
start-up, so ``--help`` is quick).

Exit status, the same for every subcommand: 0 done; 3 done, with problems listed (bad frames, skipped RF
lines, a bad exam of a study); 1 unusable input (one line on stderr naming the file, line and field); 130
interrupted (Ctrl-C: finished outputs and checkpoints are kept, nothing half-written is left).
"""

from __future__ import annotations

import argparse
import sys

from bodyslam.choices import CAMERAS, ESTIMATORS, FUSION_MODES, MATCH_MODES, SCHEMES, TRACKERS, UNROLL_MODES
from bodyslam.cliutil import Progress, jobs_count, run_cli

DONE, UNUSABLE, PROBLEMS = 0, 1, 3

# name: (one-line description, example)
COMMANDS = {
    "check": ("validate a sequence directory: meta.json and every frame",
              "bodyslam check runs/thesis_7"),
    "match": ("match two frames; draw the motion vectors in the image and unrolled",
              "bodyslam match A.png B.png --meta runs/thesis_7 --out vis.png"),
    "unroll": ("unroll a frame (inverse cylindrical projection, Eq. 3.11 or exact)",
               "bodyslam unroll A.png --meta runs/thesis_7 --out unrolled.png"),
    "motion": ("per-step motion of a sequence (distance, roll, pitch, yaw, tilt) -> motion.csv",
               "bodyslam motion runs/thesis_7 --out runs/thesis_7/motion.csv"),
    "track": ("dead-reckoned trajectory of a sequence -> TUM (world = the first frame's camera)",
              "bodyslam track runs/thesis_7 --out trajectory.tum"),
    "speed-stats": ("speed PDF/CDF and a speed model for 'testbed simulate' from a motion.csv",
                    "bodyslam speed-stats runs/thesis_7/motion.csv --out runs/speed"),
    "segment": ("SRM segmentation of a frame, regions in their mean colours (Fig. 3.3)",
                "bodyslam segment A.png --out seg.png"),
    "train-classifier": ("train the FT/FL kernel SVM on testbed sequences (labels.csv)",
                         "bodyslam train-classifier runs/cls_1 runs/cls_2 --out model.npz"),
    "classify": ("FT/FL per frame with the kernel SVM -> classes.csv",
                 "bodyslam classify runs/thesis_7 --out classes.csv"),
    "rf-localize": ("RF-only position per reading time (LLS Eq. 2.12, NLS Eq. 3.36, ML) -> fixes.csv",
                    "bodyslam rf-localize --rf rf.csv --sensors sensors.csv --out fixes.csv"),
    "localize": ("Body-SLAM: motion from the frames fused with RF (EKF + RTS smoother) -> DIR",
                 "bodyslam localize runs/thesis_7 --out runs/thesis_7/localize"),
    "batch": ("whole exams (frame folders, videos, manifests): resumable, parallel, with marked frames",
              "bodyslam batch exam.mp4 --calib calib.yaml --out runs/exam --mark 1200,4410"),
    "hybrid-localize": ("TOA/DOA at two URAs + IMU (paper 000): EKF of Algorithm 1 or a reference scheme",
                        "bodyslam hybrid-localize runs/jeong_1 --out runs/jeong_1/est"),
    "rf-track": ("particle-filter RF tracking (papers 002/003): UWB TOA + permittivity, or MICS RSSI",
                 "bodyslam rf-track runs/ito_1 --method toa_rssi_pf --out runs/ito_1/est"),
    "magnetic-localize": ("magnetic capsule (paper 001): 6-DOF EKF on recorded Hall readings",
                          "bodyslam magnetic-localize runs/popek_1 --out runs/popek_1/est"),
}


FOV_HELP = ("valid field of view: 'auto' (default: detected from the frame(s), or the image circle where they agree), "
            "'circle', or a PNG (non-zero = valid)")
RSS_BIAS_HELP = ("rss fusion: estimate a slowly varying bias per sensor (3 cm correlation along the path, 2 dB), for "
                 "sensors whose calibration is in doubt; realistic testbed smoothed 3.69 -> 3.56 cm, ideal 0.62 -> "
                 "0.61, a conservative online 1-sigma, ~3x slower fusion (docs/RESULTS.md)")


# bodyslam.vision.classify.PHOTOMETRIC_MODES, written out here: `--help` imports neither OpenCV nor scipy (a test says
# they agree)
PHOTOMETRIC_CHOICES = ("none", "channel_p90", "exposure_p90")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bodyslam", description="Body-SLAM capsule localization toolkit. Exit "
                                "status: 0 done, 3 done with problems listed, 1 unusable input, 130 interrupted.")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    def cmd(name):
        desc, example = COMMANDS[name]
        q = sub.add_parser(name, help=desc, description=f"{desc}.", epilog=f"example: {example}",
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        q.add_argument("-v", "--verbose", action="store_true", help=argparse.SUPPRESS)  # also after the command
        return q

    c = cmd("check")
    c.add_argument("seqdir")

    def motion_opts(q, estimator=True, default_mode="sift"):
        q.add_argument("--mode", default=default_mode, choices=MATCH_MODES,
                       help=f"feature matcher: asift (thesis), sift, fast (default: {default_mode})")
        if estimator:
            q.add_argument("--estimator", default="tube", choices=ESTIMATORS,
                           help="tube: 6-DOF tube-constrained solve (default); thesis: Eq. 3.14-3.22")
            q.add_argument("--unroll-mode", default="exact", choices=UNROLL_MODES,
                           help="angular depth for the thesis estimator: camera model or linear Eq. 3.11")
            q.add_argument("--radius-m", type=float, default=None,
                           help="lumen radius in metres (default: meta.json tube_radius_m)")
            q.add_argument("--radius-from", default=None, metavar="SUMMARY",
                           help="take the lumen radius an earlier batch run measured for its exam, with its 1-sigma "
                                "(its summary.json, or its output directory): for a clip cut from that exam, too "
                                "short to measure its own; instead of --radius-m")

    def frame_opts(q):
        q.add_argument("--jobs", type=jobs_count, default=None, help="worker processes (default: one per core)")
        q.add_argument("--mask", default="auto",
                       help=FOV_HELP + "; the one used is written next to the output (*_mask.png, mask.png)")
        q.add_argument("--no-classify", action="store_true",
                       help="do not classify frames FT/FL (every step is estimated as if facing the tunnel)")
        q.add_argument("--drop-wall-steps", action="store_true",
                       help="give a step touching a facing-the-wall frame no estimate (status no_lumen), as the "
                            "dissertation does; by default the tube fit estimates it (status wall, 1-sigma inflated)")
        q.add_argument("--no-rotation-steps", action="store_true",
                       help="do not measure the rotation alone of a step the tube fit fails on (fast steps; by "
                            "default guided matching measures it: status rotation, or rotation_slow where short "
                            "steps match best; distance unknown)")
        q.add_argument("--no-rescue", action="store_true",
                       help="fast mode: do not try SIFT on the full frame where tracking and the smaller detections "
                            "fail (faster on fast motion, fewer steps estimated)")
        q.add_argument("--no-lumen-scale", action="store_true",
                       help="tube estimator: keep the radius prior's scale instead of rescaling the steps by the "
                            "lumen's scale seen in a sample of them (a tube with one contraction ring; README); "
                            "the scale chain goes off with it")
        q.add_argument("--no-scale-chain", action="store_true",
                       help="tube estimator, radius a prior: do not tie each step's scale to its neighbours' by "
                            "the depths of the points they share (README)")
        q.add_argument("--model", default=None, help="FT/FL classifier model (default: the shipped one)")
        q.add_argument("--bridge-gaps", type=int, default=15, metavar="N",
                       help="measure runs of up to N steps without an estimate end to end (0: off; default 15)")

    m = cmd("match")
    m.add_argument("a")
    m.add_argument("b")
    m.add_argument("--out", required=True)
    m.add_argument("--meta", default=None, help="meta.json (or its sequence directory) with the camera")
    m.add_argument("--mask", default="auto", help=FOV_HELP)
    motion_opts(m, estimator=False)
    u = cmd("unroll")
    u.add_argument("frame")
    u.add_argument("--out", required=True)
    u.add_argument("--meta", default=None, help="meta.json (or its sequence directory) with the camera")
    u.add_argument("--size", type=int, nargs=2, default=(500, 300), metavar=("L", "H"))
    u.add_argument("--unroll-mode", default="exact", choices=UNROLL_MODES)
    for name, out in (("motion", "motion.csv"), ("track", "trajectory.tum")):
        q = cmd(name)
        q.add_argument("seqdir")
        q.add_argument("--out", required=True, help=f"output {out}")
        q.add_argument("--camera", default="front", choices=CAMERAS,
                       help="which camera of a dual-camera capsule (rear: reported in the capsule body frame)")
        frame_opts(q)
        motion_opts(q)
    sg = cmd("segment")
    sg.add_argument("frame")
    sg.add_argument("--out", required=True)
    sg.add_argument("--meta", default=None, help="meta.json (or its sequence directory) with the camera")
    sg.add_argument("--q", type=float, default=16.0, help="SRM coarseness Q (dissertation: 16)")
    sg.add_argument("--full", action="store_true", help="segment at full resolution (slow) instead of 96 px")
    sg.add_argument("--mask", default="auto", help=FOV_HELP)
    sg.add_argument("--photometric", default="none", choices=PHOTOMETRIC_CHOICES,
                    help="normalise the frame before segmenting it, as a classifier model records (the shipped one: "
                         "channel_p90, so this shows the regions it reads); default none: the frame as it is")
    tc = cmd("train-classifier")
    tc.add_argument("seqdirs", nargs="+")
    tc.add_argument("--out", required=True, help="model file (.npz)")
    tc.add_argument("--features", default="rich", choices=("nine", "rich"),
                    help="nine: the dissertation's features; rich: nine + five (default)")
    tc.add_argument("--work-px", type=int, default=96,
                    help="SRM working size (px) of the features, recorded in the model and used wherever it classifies")
    tc.add_argument("--photometric", default="channel_p90", choices=PHOTOMETRIC_CHOICES,
                    help="normalisation before segmentation, recorded in the model and applied wherever it classifies: "
                         "channel_p90 (default, as the shipped model: each colour channel's 90th percentile in the "
                         "field of view scaled to 200, so exposure and colour cast do not move the features), "
                         "exposure_p90 (each pixel's brightest channel's, one factor: exposure does not) or none (the "
                         "frames as they are)")
    tc.add_argument("--jobs", type=jobs_count, default=None)
    cl = cmd("classify")
    cl.add_argument("input", help="a sequence directory (meta.json), a folder of frames, or one image")
    cl.add_argument("--out", required=True, help="classes.csv")
    cl.add_argument("--model", default=None, help="model file (default: the shipped model)")
    cl.add_argument("--meta", default=None, help="meta.json with the camera, for a plain folder of frames")
    cl.add_argument("--jobs", type=jobs_count, default=None)
    cl.add_argument("--mask", default="auto", help=FOV_HELP + "; written next to --out as *_mask.png")
    rl = cmd("rf-localize")
    rl.add_argument("--rf", required=True, help="rf.csv (t,sensor,rss_dbm)")
    rl.add_argument("--sensors", required=True, help="sensors.csv (sensor,x,y,z[,nx,ny,nz])")
    rl.add_argument("--meta", default=None, help="meta.json with the path-loss model (default: Table 2.2, -16 dBm)")
    rl.add_argument("--method", default="ml", choices=("lls", "nls", "ml"))
    rl.add_argument("--out", required=True, help="fixes.csv: t,x_m,y_m,z_m,cov_xx..cov_zz,n_sensors,status")
    hy = cmd("hybrid-localize")
    hy.add_argument("seqdir", help="recording: meta.json (arrays, radio, IMU, initial state), rf.csv, imu.csv")
    hy.add_argument("--scheme", default="toa_doa_imu", choices=SCHEMES)
    hy.add_argument("--q-model", default="eq15", choices=("eq15", "discrete"),
                    help="process noise: Eq. 15 (paper) or the IMU's exact sigma^2 B B^T")
    hy.add_argument("--out", required=True, help="output directory: trajectory.tum, uncertainty.csv")
    hy.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    rt = cmd("rf-track")
    rt.add_argument("seqdir", help="recording: rf.csv (t,sensor,rss_dbm[,toa_s,uwb_field_db]), sensors.csv, "
                                   "meta.json (area_min_m, area_max_m; uwb and mics models)")
    rt.add_argument("--method", default="toa_rssi_pf", choices=TRACKERS)
    rt.add_argument("--particles", type=int, default=20000)
    rt.add_argument("--eps", type=float, default=None, help="known permittivity for toa_pf_true_eps (default: "
                                                              "meta.json's uwb.eps_r)")
    rt.add_argument("--seed", type=int, default=0, help="the particle filter's random seed")
    rt.add_argument("--out", required=True, help="output directory: trajectory.tum (+ permittivity.csv)")
    rt.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    mgl = cmd("magnetic-localize")
    mgl.add_argument("seqdir", help="recording: meta.json (sensors, filter calibration), hall.csv, actuator.csv")
    mgl.add_argument("--out", required=True, help="output directory: trajectory.tum, uncertainty.csv")
    mgl.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    lo = cmd("localize")
    lo.add_argument("seqdir")
    lo.add_argument("--rf", default=None, help="rf.csv (default: the sequence's rf.csv)")
    lo.add_argument("--sensors", default=None, help="sensors.csv (default: the sequence's sensors.csv)")
    lo.add_argument("--out", required=True, help="output directory")
    lo.add_argument("--motion", default=None, help="reuse a motion.csv instead of estimating motion again (the "
                    "frames are then not read: meta.json and the RF files suffice)")
    lo.add_argument("--fusion", default="rss", choices=FUSION_MODES,
                    help="rss: EKF on the raw RSS readings (default); fix: EKF on ML position fixes")
    lo.add_argument("--no-refine", action="store_true", help="smoothed output: the RTS smoother alone, without the "
                    "whole-exam refinement (bodyslam.fusion.refine; rss fusion only), to compare")
    lo.add_argument("--rss-bias-states", action="store_true", help=RSS_BIAS_HELP)
    lo.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    frame_opts(lo)
    motion_opts(lo)
    ba = cmd("batch")
    ba.add_argument("inputs", nargs="+", help="frame folders, sequence directories, videos, or manifests (.csv/.json)")
    ba.add_argument("--out", required=True, help="output directory (resumed when it holds the same run)")
    ba.add_argument("--calib", default=None, help="camera calibration (JSON or OpenCV YAML with cv2.fisheye K, D)")
    ba.add_argument("--fps", type=float, default=None, help="frame rate (default: meta.json / the video's / 2)")
    ba.add_argument("--rf", default=None, help="rf.csv to fuse (default: a sequence directory's own)")
    ba.add_argument("--sensors", default=None, help="sensors.csv for --rf")
    ba.add_argument("--mark", default=None, help="frames to locate, e.g. 120,455,1000-1002")
    ba.add_argument("--mark-file", default=None, help="CSV of marked frames: frame[,label][,exam]")
    ba.add_argument("--landmark", default=None,
                    help="landmark frames (e.g. 310 = pylorus): path from each; with two or more, how far each mark "
                         "lies from the first to the last (0-1) by the path and by the time")
    ba.add_argument("--frame-range", default=None, metavar="FIRST-LAST",
                    help="process frames FIRST..LAST of each exam only (frame numbers, both kept; FIRST- to the end), "
                         "e.g. the small bowel between its first duodenal and first caecal frame; they keep their "
                         "numbers and times")
    ba.add_argument("--chunk-frames", type=int, default=None,
                    help="frames per checkpointed chunk, all equal (default: guided chunks of 20-500 frames that "
                         "shrink toward the study's end, sized for the workers, so all stay busy to it; recorded in "
                         "batch.json; results do not depend on it)")
    ba.add_argument("--scheduler", default=None, help="address of a Dask distributed scheduler (tcp://host:8786)")
    ba.add_argument("--fusion", default="rss", choices=FUSION_MODES, help="with RF: EKF on RSS (default) or fixes")
    ba.add_argument("--rss-bias-states", action="store_true", help=RSS_BIAS_HELP)
    ba.add_argument("--force", action="store_true", help="overwrite an output directory holding another run")
    frame_opts(ba)
    motion_opts(ba, default_mode="fast")
    ss = cmd("speed-stats")
    ss.add_argument("motion_csv")
    ss.add_argument("--out", required=True, help="output directory (speed_pdf.png, speed_cdf.png, speed_model.json)")
    ss.add_argument("--frame-rate", type=float, default=None, help="frames/s (default: from the t column)")
    ss.add_argument("--force", action="store_true", help="write into a non-empty output directory")
    return p


def _motion_settings(args):
    """The visual engine's settings from the common options (bodyslam.vision.odometry.MotionSettings)."""
    from bodyslam.vision.odometry import MotionSettings

    return MotionSettings(args.mode, args.estimator, args.unroll_mode,
                          mask=getattr(args, "mask", None) if args.cmd != "batch" else None,
                          classify=not args.no_classify, model=args.model, bridge_gaps=args.bridge_gaps,
                          wall_steps="drop" if args.drop_wall_steps else "estimate",
                          rotation_steps=not args.no_rotation_steps, rescue=not args.no_rescue,
                          lumen_scale=not args.no_lumen_scale, scale_chain=not args.no_scale_chain)


def _print_problems(problems: list, limit: int = 20) -> int:
    """Print problems (``[file, frame, severity, reason]`` lists, or ``file:line: reason`` strings), the first
    ``limit``; returns the exit status: PROBLEMS when there were any, else DONE."""
    for pr in problems[:limit]:
        if isinstance(pr, str):
            print(f"  {pr}")
        elif len(pr) == 3:
            print(f"  {pr[0]}:{pr[1]}: {pr[2]}")
        else:
            print(f"  {pr[2]}: {pr[0]}{f' (frame {pr[1]})' if pr[1] != '' else ''}: {pr[3]}")
    if len(problems) > limit:
        print(f"  ... and {len(problems) - limit} more")
    return PROBLEMS if problems else DONE


def _frames_of(inp):
    """Frame paths and camera of a sequence directory (its validated meta.json), of a folder of images, or of one
    image (camera None)."""
    from pathlib import Path

    from bodyslam.errors import InputError
    from bodyslam.frames import IMAGE_EXTS, list_frames
    from bodyslam.io import frame_name
    from bodyslam.meta import read_meta

    p = Path(inp)
    if (p / "meta.json").exists():
        meta = read_meta(p)
        d = p / meta.frames_dir
        return [d / frame_name(k) for k in range(meta.n_frames)], meta.camera_model()
    if p.is_file() and p.suffix.lower() in IMAGE_EXTS:
        return [p], None
    if not p.is_dir():
        raise InputError(f"{p}: {'file not found' if not p.exists() else 'not an image'}: give a sequence "
                         "directory, a folder of frames or an image")
    frames, _ = list_frames(p)
    if not frames:
        raise InputError(f"{p}: no image files")
    return [p / name for _, name in frames], None


def _fov_of(images: list, cam, mask: str):
    """The field of view for a command on a few frames, as a bool mask (the image circle filled in):
    :func:`bodyslam.vision.odometry.fov_from_frames`."""
    from bodyslam.vision.odometry import fov_from_frames

    m = fov_from_frames([im for im in images if im.shape[:2] == (cam.height, cam.width)], cam, mask)
    return cam.fov_mask() if m is None else m


def _sample_frames(paths: list, n: int = 30) -> list:
    """Up to ``n`` readable frames spread over ``paths`` (for the field-of-view detection)."""
    import numpy as np

    from bodyslam.errors import InputError
    from bodyslam.io import read_image

    out = []
    for k in np.unique(np.linspace(0, len(paths) - 1, min(n, len(paths))).astype(int)):
        try:
            out.append(read_image(paths[int(k)]))
        except InputError:
            pass  # unreadable frames are listed by the classification itself
    return out


def _segment(args) -> int:
    from bodyslam.io import read_image, write_image
    from bodyslam.vision.classify import normalise_photometric
    from bodyslam.vision.segmentation import paint_regions, srm

    img = read_image(args.frame)
    cam = _camera_for(img, args.meta)
    fov = _fov_of([img], cam, args.mask)
    seg = srm(normalise_photometric(img, fov, args.photometric), fov, Q=args.q, work_px=None if args.full else 96)
    write_image(args.out, paint_regions(seg, img.shape[:2]))
    print(f"{seg.n_regions} regions (Q = {args.q:g}); wrote {args.out}")
    return 0


def _train_classifier(args) -> int:
    import numpy as np

    from bodyslam.vision.classify import FEATURES_9, FEATURES_RICH, features_of_frames, train
    from bodyslam.errors import ConfigError, InputError
    from bodyslam.io import read_labels

    if not 16 <= args.work_px <= 1024:
        raise ConfigError(f"--work-px must be 16-1024 px, got {args.work_px}")
    X, y, names = [], [], []
    for sd in args.seqdirs:
        paths, cam = _frames_of(sd)
        lab_path = __import__("pathlib").Path(sd) / "labels.csv"
        if not lab_path.exists():
            raise InputError(f"{sd}: no labels.csv (training needs testbed sequences with FT/FL labels)")
        labels = read_labels(lab_path)
        fov = _fov_of(_sample_frames(paths), cam, "auto")  # the field the pipeline will use on such frames
        res = features_of_frames(paths, fov, work_px=args.work_px, jobs=args.jobs, progress=Progress(f"features {sd}"),
                                 photometric=args.photometric)
        for k, (st, _, f) in enumerate(res):
            if st == "ok" and k in labels:
                X.append(f)
                y.append(labels[k])
        names.append(str(sd))
    model = train(np.array(X), np.array(y), FEATURES_9 if args.features == "nine" else FEATURES_RICH,
                  info={"trained_on": names, "work_px": args.work_px, "photometric": args.photometric})
    model.save(args.out)
    print(f"{args.out}: {args.features} features, {len(y)} frames ({model.info['n_train_ft']} FT, "
          f"{model.info['n_train_fl']} FL), cross-validated accuracy {model.info['cv_accuracy']:.4f}, "
          f"C {model.info['C']:g}, gamma {model.gamma:g}, {len(model.support_vectors)} support vectors")
    return 0


def _classify(args) -> int:
    from collections import Counter

    from pathlib import Path

    import numpy as np

    from bodyslam.errors import InputError
    from bodyslam.io import check_writable, read_image, write_csv, write_image
    from bodyslam.vision.classify import TunnelClassifier, features_of_frames
    from bodyslam.vision.odometry import MotionSettings, classify_work_px

    check_writable(args.out)
    paths, cam = _frames_of(args.input)
    n_sample = 30  # frames spread over the input, for the field of view (and the size, where no camera is given)
    sample = _sample_frames(paths, n_sample)
    if cam is None and not args.meta and not sample:
        if len(paths) == 1:
            read_image(paths[0])  # says why it cannot be read
        raise InputError(f"{args.input}: none of the {min(len(paths), n_sample)} frames sampled from its {len(paths)} "
                         "can be decoded; give the camera with --meta")
    if cam is None:  # the frames' size from the first that decodes: a corrupt first frame is listed, not fatal
        cam = _camera_for(sample[0] if sample else None, args.meta)
    model = TunnelClassifier.load(args.model) if args.model else TunnelClassifier.default()
    fov = _fov_of(sample, cam, args.mask)
    work_px = classify_work_px(MotionSettings(), model)  # the pipeline's rule: the size the model was trained at
    res = features_of_frames(paths, fov, work_px=work_px, jobs=args.jobs, progress=Progress("classify"),
                             photometric=model.photometric)
    rows = []
    for p, (st, msg, f) in zip(paths, res):
        if st == "ok":
            d = float(model.decision(f[None])[0])
            rows.append([p.name, "FT" if d > 0 else "FL", d, st])
        else:
            rows.append([p.name, "", float("nan"), st])
            if msg:
                print(f"  {msg}")
    write_csv(args.out, ["frame", "label", "decision", "status"], rows)
    out = Path(args.out)
    write_image(out.with_name(out.stem + "_mask.png"), (fov * 255).astype(np.uint8))  # the field of view used
    c = Counter(r[1] or r[3] for r in rows)
    print(f"{args.out}: {len(rows)} frames: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    # dark and saturated frames are answers (no lumen visible); unreadable or wrong-size files are problems
    return PROBLEMS if any(r[3] in ("unreadable", "bad_size") for r in rows) else DONE


def _rf_localize(args) -> int:
    from pathlib import Path

    import numpy as np

    from bodyslam.errors import InputError
    from bodyslam.io import read_json, write_csv
    from bodyslam.fusion.rf import (PathLossModel, check_rss_units, locate_lls, locate_ml_frames, locate_nls, read_rf,
                                    read_sensors)

    names, pos, nrm = read_sensors(args.sensors)
    stamps, rss, problems = read_rf(args.rf, names)
    if len(stamps) == 0:  # nothing to locate (a header alone, or every line skipped): no empty fixes.csv
        raise InputError(f"{args.rf}: no usable RSS reading"
                         + (f" ({len(problems)} problem(s) in it; the first: {problems[0]})" if problems else ""))
    pl = PathLossModel()
    if args.meta:
        p = Path(args.meta)
        meta = read_json(p / "meta.json" if p.is_dir() else p)
        if isinstance(meta.get("rf"), dict) and "pathloss" in meta["rf"]:
            pl = PathLossModel.from_dict(meta["rf"]["pathloss"])
    check_rss_units(args.rf, rss, pl)
    rows = []
    # per-frame solves report progress; ML solves all frames at once before the loop, which then only tabulates
    prog = Progress("rf-localize") if args.method != "ml" else None
    ml = locate_ml_frames(pos, nrm, rss, pl) if args.method == "ml" else None  # all frames in one solve
    for k, t in enumerate(stamps):
        if args.method == "lls":
            fx = locate_lls(pos, rss[k], pl)
        elif args.method == "nls":
            fx = locate_nls(pos, rss[k], pl)
        else:
            fx = ml[k]
        c = fx.cov_m2
        rows.append([t, *fx.position_w_m, c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2], fx.n_sensors,
                     fx.status])
        if prog:
            prog(k + 1, len(stamps))
    write_csv(args.out, ["t", "x_m", "y_m", "z_m", "cov_xx_m2", "cov_xy_m2", "cov_xz_m2", "cov_yy_m2", "cov_yz_m2",
                         "cov_zz_m2", "n_sensors", "status"], rows)
    _print_problems(problems)
    ok = sum(r[-1] == "ok" for r in rows)
    sd = np.nanmedian([np.sqrt(r[4] + r[7] + r[9]) for r in rows]) if rows else float("nan")
    print(f"{args.out}: {len(rows)} fixes ({ok} ok, {args.method}); median predicted 1-sigma {sd * 100:.1f} cm; "
          f"{len(problems)} RF problem(s) (lines skipped)")
    return PROBLEMS if problems else DONE


def _write_position_track(out, t, pos, quat_wxyz, cov):
    """``trajectory.tum`` and ``uncertainty.csv`` (bodyslam.fusion.localize's schema) of a localization run; returns
    the per-axis 1-sigma ``(n, 3)``."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from bodyslam.io import write_tum
    from bodyslam.fusion.localize import write_uncertainty

    rot = Rotation.identity(len(pos)) if quat_wxyz is None else Rotation.from_quat(quat_wxyz[:, [1, 2, 3, 0]])
    write_tum(out / "trajectory.tum", t, pos, rot)
    cov = np.asarray(cov)[:, :3, :3]
    write_uncertainty(out / "uncertainty.csv", np.arange(len(t)), t, cov)
    return np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))


def _rf_track(args) -> int:
    from pathlib import Path

    import numpy as np
    from scipy.spatial.transform import Rotation

    from bodyslam.errors import InputError
    from bodyslam.io import read_json, write_csv, write_tum
    from bodyslam.systems.pf import TrackSettings, track
    from bodyslam.fusion.rf import read_rf_columns, read_sensors

    d = Path(args.seqdir)
    meta = read_json(d / "meta.json")
    try:
        lo, hi = np.asarray(meta["area_min_m"], float), np.asarray(meta["area_max_m"], float)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{d / 'meta.json'}: needs area_min_m and area_max_m (the analysis area, m)") from None
    settings = TrackSettings.from_tables(meta.get("uwb", {}), meta.get("mics", {}), particles=args.particles,
                                         **({"eps_known": args.eps} if args.eps else {}))
    names, rx, _ = read_sensors(d / "sensors.csv")
    cols = ("rss_dbm",) if args.method == "rssi_pf" else ("toa_s", "uwb_field_db")
    stamps, readings, problems = read_rf_columns(d / "rf.csv", names, cols)
    if len(stamps) == 0:  # nothing to track (a header alone, or every line skipped)
        raise InputError(f"{d / 'rf.csv'}: no usable reading of {', '.join(cols)}"
                         + (f" ({len(problems)} problem(s) in it; the first: {problems[0]})" if problems else ""))
    if "rss_dbm" in readings:
        readings["rss_db"] = readings.pop("rss_dbm")
    from bodyslam.io import prepare_output_dir

    out = prepare_output_dir(args.out, args.force)
    est, eps, _ = track(args.method, stamps, rx, readings, lo, hi, settings, np.random.default_rng(args.seed),
                        progress=Progress(f"rf-track {args.method}"))
    write_tum(out / "trajectory.tum", stamps, est, Rotation.identity(len(est)))  # position only
    if eps is not None:
        write_csv(out / "permittivity.csv", ["t", "eps_r"], [[float(a), float(b)] for a, b in zip(stamps, eps)])
    print(f"{out}/trajectory.tum: {len(est)} positions ({args.method}, {args.particles} particles)"
          + (f"; permittivity at the end {eps[-1]:.1f}" if eps is not None else "")
          + f"; {len(problems)} RF problem(s) (lines skipped)")
    return _print_problems(problems)


def _magnetic_localize(args) -> int:
    import numpy as np

    from bodyslam.systems.magnetic import load_recording, replay

    from bodyslam.io import prepare_output_dir

    prepare_output_dir(args.out, args.force, create=False)  # refused now; created only once there is a result
    rec = load_recording(args.seqdir)
    t, states, cov = replay(rec)
    out = prepare_output_dir(args.out, args.force)
    _write_position_track(out, t, states[:, :3], states[:, 3:] / np.linalg.norm(states[:, 3:], axis=1, keepdims=True),
                          cov)
    status = _print_problems(rec["problems"])
    print(f"{out}/trajectory.tum: {len(t)} poses over {t[-1]:.1f} s; final predicted 1-sigma "
          f"{np.sqrt(np.trace(cov[-1])) * 1000:.1f} mm; {len(rec['problems'])} problem(s)")
    return status


def _hybrid_localize(args) -> int:
    import numpy as np

    from bodyslam.systems.toa_doa import load_recording, run_scheme

    from bodyslam.io import prepare_output_dir

    prepare_output_dir(args.out, args.force, create=False)  # refused now; created only once there is a result
    rec = load_recording(args.seqdir)
    est, cov = run_scheme(args.scheme, rec["x0"], rec["P0"], rec["y"], rec["snr"], rec["imu"], rec["arrays"],
                          rec["radio"], rec["sigma_acc"], rec["delta_s"], args.q_model)
    out = prepare_output_dir(args.out, args.force)
    sd = _write_position_track(out, rec["t"], est, None, cov)
    status = _print_problems(rec["problems"])
    print(f"{out}/trajectory.tum: {len(est)} positions ({args.scheme}); median predicted 1-sigma "
          f"{np.median(np.sqrt(np.sum(sd[1:] ** 2, axis=1))) * 100:.2f} cm; {len(rec['problems'])} problem(s)")
    return status


def _check_bias_states(args) -> None:
    """The RSS bias states are states of the raw-RSS filter: refused with ``--fusion fix``, not ignored."""
    from bodyslam.errors import ConfigError

    if args.rss_bias_states and args.fusion != "rss":
        raise ConfigError(f"--rss-bias-states is for --fusion rss (per-sensor biases of the raw readings), got "
                          f"--fusion {args.fusion}")


def _path_filled_text(path_m, steps) -> str:
    """The printed path's share in steps without an estimate and in fits beside the wall
    (bodyslam.vision.tracking.path_share_text), or ""."""
    from bodyslam.vision.tracking import path_share_text, share_beside_wall, share_without_estimate, step_length

    length = [step_length(s)[0] for s in steps]
    return path_share_text(share_without_estimate(path_m, length),
                           share_beside_wall(path_m, length, [s.beside_wall for s in steps]))


def _localize(args) -> int:
    from pathlib import Path

    import numpy as np

    from bodyslam.io import prepare_output_dir, read_motion_steps, write_motion_csv
    from bodyslam.fusion.localize import RfInput, localize, write_localization
    from bodyslam.meta import read_meta
    from bodyslam.vision.lumen_scale import radius_sd_rel_after, scale_of_steps
    from bodyslam.vision.odometry import Sequence, lumen_scale_measured, sequence_motion

    _check_bias_states(args)
    radius_sd_m = _given_radius(args)
    seq_dir = Path(args.seqdir)
    meta = read_meta(seq_dir)
    rf_meta = meta.rf
    rf_path = Path(args.rf) if args.rf else seq_dir / (rf_meta.file if rf_meta else "rf.csv")
    sensors_path = Path(args.sensors) if args.sensors else seq_dir / (rf_meta.sensors if rf_meta else "sensors.csv")
    rf = RfInput.read(rf_path, sensors_path, rf_meta.pathloss if rf_meta else None)
    prepare_output_dir(args.out, args.force, create=False)  # refused now, not after the work
    problems: list = []
    fov: list = []
    scale: list = []
    if args.motion:  # the steps are given: meta.json is all that is read of the sequence (no frames needed)
        n, rate = meta.n_frames, meta.frame_rate_hz
        radius_m = meta.tube_radius_m if args.radius_m is None else args.radius_m
        # a radius on the command line has no spread, unless --radius-from gave one
        radius_sd_rel = meta.radius_sd_rel if args.radius_m is None else (radius_sd_m or 0.0) / args.radius_m
        steps = read_motion_steps(args.motion, range(1, n))
        # the lumen scale the motion stage applied, from the steps' ring ratios: its 1-sigma is the radius's now
        applied = scale_of_steps(steps, lumen_scale_measured(_motion_settings(args), radius_sd_rel))
    else:
        seq = Sequence.open(seq_dir, args.radius_m, radius_sd_m=radius_sd_m)
        n, rate, radius_sd_rel, radius_m = seq.n_frames, seq.frame_rate_hz, seq.radius_sd_rel, seq.radius_m
        steps = sequence_motion(seq_dir, _motion_settings(args), jobs=args.jobs, radius_m=args.radius_m,
                                radius_sd_m=radius_sd_m,
                                progress=Progress("motion"), problems=problems, fov_used=fov,
                                lumen_scale_used=scale)
        applied = scale[0]
    radius_sd_rel = radius_sd_rel_after(applied, radius_sd_rel)
    frames = np.arange(n)
    stamps = frames / rate
    loc = localize(steps, stamps, rf, rate, frames, mode=args.fusion, radius_sd_rel=radius_sd_rel,
                   refine=not args.no_refine, radius_m=radius_m, bias_states=args.rss_bias_states)
    out = prepare_output_dir(args.out, args.force)
    if not args.motion:
        from bodyslam.vision.odometry import write_mask

        write_motion_csv(out / "motion.csv", frames[1:], stamps[1:], steps)
        write_mask(out / "mask.png", fov[0], seq.camera)  # the field of view the motion used
    write_localization(out, loc)
    res = loc.smoothed
    sd = np.sqrt(np.trace(res.cov[:, :3, :3], axis1=1, axis2=2))
    filled = _path_filled_text(loc.path_m, steps)
    print(f"{out}: {n} poses; path travelled {loc.path_m[-1] * 100:.1f} +- {np.sqrt(loc.path_var_m2[-1]) * 100:.1f} cm"
          + (f" ({filled})" if filled else "") + "; "
          f"position 1-sigma median {np.median(sd) * 100:.2f} cm (max {sd.max() * 100:.2f}; RSS errors correlated "
          f"x{loc.channel.kappa:.1f} over the exam, x{np.mean(loc.kappa_smoothed):.1f} over the smoother's window, "
          "bodyslam.fusion.channel); "
          f"{loc.filtered.n_updates} RF updates, {loc.filtered.n_rejected} readings rejected by the gate; "
          f"{sum(not s.has_estimate for s in steps)} steps without a visual estimate "
          f"({sum(s.has_rotation and not s.has_estimate for s in steps)} of them with their rotation); "
          f"{len(loc.rf_problems)} RF problem(s) (lines skipped)")
    if scale:
        print(f"  {_lumen_scale_text(scale[0])}")
    if loc.rss_bias_db is not None:
        mean = loc.rss_bias_db.mean(axis=0)
        j = int(np.argmax(np.abs(mean)))
        print(f"RSS bias states: sensor {loc.sensor_names[j]} read {mean[j]:+.1f} dB off the calibration on average, "
              f"the largest of {len(mean)}; {np.mean(np.abs(mean) > 1.0):.0%} of the sensors more than 1 dB "
              f"({out / 'rss_bias.csv'})")
    return _print_problems(problems + loc.rf_problems)


def _given_radius(args) -> float | None:
    """``--radius-from``: sets ``args.radius_m`` to the radius an earlier batch run measured (it refuses both options
    at once) and returns its 1-sigma (m; None where the summary states none: the radius is then taken as known, as
    with ``--radius-m``)."""
    from bodyslam.errors import ConfigError
    from bodyslam.exam.batch import radius_from_summary

    if getattr(args, "radius_from", None) is None:
        return None
    if args.radius_m is not None:
        raise ConfigError("give the lumen radius by --radius-m or by --radius-from, not both")
    args.radius_m, radius_sd_m = radius_from_summary(args.radius_from)
    pm = f" +- {radius_sd_m * 100:.3f}" if radius_sd_m is not None else ""
    print(f"lumen radius {args.radius_m * 100:.3f}{pm} cm, as {args.radius_from} measured it")
    return radius_sd_m


def _batch(args) -> int:
    from bodyslam.errors import ConfigError
    from bodyslam.exam.batch import (BatchSettings, open_exams, parse_frame_list, parse_frame_range, read_marks,
                                     run_batch, unlit_text)
    from bodyslam.vision.tracking import path_share_text
    from bodyslam.steps import WITH_ESTIMATE

    _check_bias_states(args)
    radius_sd_m = _given_radius(args)
    marks = [(f, "") for f in parse_frame_list(args.mark)] if args.mark else []
    landmarks = parse_frame_list(args.landmark) if args.landmark else []
    frame_range = parse_frame_range(args.frame_range) if args.frame_range else None
    skipped: list = []  # exams of a study that cannot be opened: listed, the others go on
    exams = open_exams(args.inputs, calib=args.calib, fps=args.fps, radius_m=args.radius_m, mask=args.mask,
                       rf=args.rf, sensors=args.sensors, marks=marks, landmarks=landmarks, problems=skipped,
                       frame_range=frame_range, radius_sd_m=radius_sd_m)
    for p in skipped:
        print(f"  {p[3]}")  # "exam not processed: <file>: why"
    if args.mark_file:
        read_marks(args.mark_file, exams)
    settings = BatchSettings(_motion_settings(args), chunk_frames=args.chunk_frames, fusion=args.fusion,
                             rss_bias_states=args.rss_bias_states)
    total_frames = sum(e.n_positions for e in exams)
    print(f"{len(exams)} exam(s), {total_frames} frames -> {args.out}", flush=True)
    rep = run_batch(exams, args.out, settings, jobs=args.jobs, scheduler=args.scheduler, force=args.force,
                    progress=Progress("batch"), problems=skipped,
                    stage=lambda line: print(line, file=sys.stderr, flush=True))
    for s in rep.exams:
        steps = s["steps"]
        c = s["classes"]
        classes = f"{c['FT']} FT, {c['FL']} FL" + unlit_text(c, ", {}") if isinstance(c, dict) else c
        n_est = sum(steps.get(k, 0) for k in WITH_ESTIMATE)
        filled = path_share_text(s.get("path_without_estimate_share", 0.0), s.get("path_beside_wall_share", 0.0))
        print(f"{s['exam']}: {s['frames']} frames ({classes}), {n_est}/{sum(steps.values())} steps estimated "
              f"({steps.get('wall', 0)} facing the wall, "
              + (f"{s['steps_beside_wall']} fitted beside the wall, " if s["steps_beside_wall"] else "")
              + f"{steps.get('bridged', 0)} bridged; "
              f"{steps.get('rotation', 0) + steps.get('rotation_slow', 0)} more with only their rotation"
              + (f" ({steps['rotation_slow']} of them slow)" if steps.get("rotation_slow") else "")
              + f"; {steps.get('lost', 0)} lost to fast "
              f"motion), path "
              f"{s['path_travelled_m'] * 100:.1f} +- {s['sd_path_travelled_m'] * 100:.1f} cm"
              + (f" ({filled})" if filled else "") + f", {s['trajectory']}; "
              f"{s['problems']} problem(s)")
        print(f"  {_lumen_scale_text(s['lumen_scale'])}")
        for a in s["assumed"]:
            print(f"  assumed {a}")
        if s.get("video_ended_at") is not None:
            print(f"  the video ends after {s['video_ended_at']} decodable frames (its container said "
                  f"{s['frames_expected']}: a container's count is an estimate)")
    print(f"{rep.chunks_computed} chunk(s) computed, {rep.chunks_reused} reused; {rep.n_problems} problem(s) "
          f"({rep.n_errors} error(s)) in {rep.out / 'problems.csv'}")
    return PROBLEMS if rep.n_problems else DONE


def _speed_stats(args) -> int:
    import numpy as np

    from bodyslam.errors import InputError
    from bodyslam.io import prepare_output_dir, read_motion_csv
    from bodyslam.vision.speed import fit_speed_model, speed_statistics, summary_line, write_speed_report

    prepare_output_dir(args.out, args.force, create=False)  # a non-empty directory is refused before the work
    rows = read_motion_csv(args.motion_csv)
    rate = args.frame_rate
    if rate is None:
        ks = sorted(k for k in rows if np.isfinite(rows[k].get("t", np.nan)))
        if len(ks) < 2:
            raise InputError(f"{args.motion_csv}: no t column to infer the frame rate from; give --frame-rate")
        dt = np.diff([rows[k]["t"] for k in ks]) / np.diff(ks)
        rate = 1.0 / float(np.median(dt))
    stats = speed_statistics(rows, rate)
    model = fit_speed_model(stats)
    paths = write_speed_report(stats, model, args.out)
    print(summary_line(model))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _camera_for(image, meta_arg):
    """The camera of ``--meta`` (a meta.json or its sequence directory, validated), else an equidistant
    156-degree fisheye of the image's size."""
    from bodyslam.camera import FisheyeCamera
    from bodyslam.meta import read_meta

    if meta_arg:
        return read_meta(meta_arg).camera_model()
    h, w = image.shape[:2]
    return FisheyeCamera.equidistant(w, h, 156.0)


def _match(args) -> int:
    import cv2
    import numpy as np

    from bodyslam.io import read_image, write_image
    from bodyslam.vision.matching import Matcher
    from bodyslam.vision.unroll import Unroller

    a, b = read_image(args.a), read_image(args.b)
    cam = _camera_for(a, args.meta)
    fov = _fov_of([a, b], cam, args.mask)
    if not args.meta:  # an assumed lens: centred on a field off the frame's centre or small in it (as batch does)
        from bodyslam.camera import equidistant_on_field

        on_field = equidistant_on_field(fov, cam.fov_deg) if args.mask in (None, "auto") else None
        if on_field is not None:
            cam = on_field
            print(f"assumed lens centred on the detected field of view at ({cam.cx:g}, {cam.cy:g})")
    matcher = Matcher(cam, args.mode, mask=fov)
    m = matcher.match(a, b)
    un = Unroller(cam)
    left = a.copy()
    right = un.unroll(a)
    u1, u2 = un.to_unrolled(m.pts1_px), un.to_unrolled(m.pts2_px)
    for p, q in zip(m.pts1_px, m.pts2_px):
        cv2.circle(left, tuple(np.rint(p).astype(int)), 2, (60, 120, 255), -1)
        cv2.line(left, tuple(np.rint(p).astype(int)), tuple(np.rint(q).astype(int)), (255, 40, 40), 1, cv2.LINE_AA)
    for p, q in zip(u1, u2):
        if abs(q[0] - p[0]) > un.L / 2:  # wrapped around the seam: draw to the nearer copy
            q = q + [un.L if p[0] > q[0] else -un.L, 0]
        cv2.circle(right, tuple(np.rint(p).astype(int)), 2, (60, 120, 255), -1)
        cv2.line(right, tuple(np.rint(p).astype(int)), tuple(np.rint(q).astype(int)), (255, 40, 40), 1, cv2.LINE_AA)
    h = max(left.shape[0], right.shape[0])
    pad = lambda im: np.pad(im, ((0, h - im.shape[0]), (0, 0), (0, 0)))  # noqa: E731
    write_image(args.out, np.hstack([pad(left), pad(right)]))
    print(f"{len(m)} verified matches of {m.n_candidates} candidates ({args.mode}); wrote {args.out}")
    return 0 if len(m) else 1


def _unroll(args) -> int:
    from bodyslam.io import read_image, write_image
    from bodyslam.vision.unroll import Unroller

    img = read_image(args.frame)
    un = Unroller(_camera_for(img, args.meta), args.size[0], args.size[1], mode=args.unroll_mode)
    write_image(args.out, un.unroll(img))
    print(f"wrote {args.out} ({args.size[0]}x{args.size[1]}, {args.unroll_mode})")
    return 0


def _motion_or_track(args) -> int:
    from collections import Counter

    import numpy as np

    from pathlib import Path

    from bodyslam.io import check_writable, write_motion_csv, write_tum
    from bodyslam.vision.lumen_scale import radius_sd_rel_after
    from bodyslam.vision.odometry import Sequence, sequence_motion, write_mask
    from bodyslam.vision.tracking import dead_reckon, path_travelled

    settings = _motion_settings(args)
    radius_sd_m = _given_radius(args)
    seq = Sequence.open(args.seqdir, args.radius_m, args.camera, radius_sd_m=radius_sd_m)
    check_writable(args.out)
    problems: list = []
    fov: list = []
    scale: list = []
    steps = sequence_motion(args.seqdir, settings, jobs=args.jobs, radius_m=args.radius_m, radius_sd_m=radius_sd_m,
                            progress=Progress(args.cmd), camera=args.camera, problems=problems, fov_used=fov,
                            lumen_scale_used=scale)
    counts = Counter(str(s.status) for s in steps)
    stamps = np.arange(len(steps) + 1) / seq.frame_rate_hz
    if args.cmd == "motion":
        write_motion_csv(args.out, range(1, len(steps) + 1), stamps[1:], steps)
    else:
        pos, rot = dead_reckon(steps)
        write_tum(args.out, stamps, pos, rot, world="first camera frame")
    out = Path(args.out)
    write_mask(out.with_name(out.stem + "_mask.png"), fov[0], seq.camera)  # the field of view used
    path, var = path_travelled(steps, radius_sd_rel_after(scale[0], seq.radius_sd_rel), seq.radius_m)
    filled = _path_filled_text(path, steps)
    beside = sum(s.beside_wall for s in steps)
    print(f"{args.out}: {len(steps)} steps ({', '.join(f'{k} {v}' for k, v in sorted(counts.items()))}"
          + (f"; {beside} of them fitted beside the wall, wider 1-sigma" if beside else "") + "); "
          f"path travelled {path[-1] * 100:.1f} +- {np.sqrt(var[-1]) * 100:.1f} cm ({args.mode}, {args.estimator}"
          + (f"; {filled}" if filled else "") + ")")
    print(f"  {_lumen_scale_text(scale[0])}")
    return _print_problems(problems)


def _lumen_scale_text(sc: dict | None) -> str:
    """One line on the lumen scale a run applied (bodyslam.vision.lumen_scale)."""
    from bodyslam.vision.lumen_scale import lumen_scale_text

    return f"lumen scale: {lumen_scale_text(sc)}"


def _check(args) -> int:
    """Validate meta.json (bodyslam.meta: what it accepts the pipeline runs) and stream every frame."""
    from pathlib import Path

    from bodyslam.frames import FrameSource
    from bodyslam.meta import read_meta

    seq = Path(args.seqdir)
    meta = read_meta(seq)
    cam = meta.camera_model()
    frames_dir = seq / meta.frames_dir
    if not frames_dir.is_dir():
        from bodyslam.errors import InputError

        raise InputError(f"{frames_dir}: frames directory not found")
    bad = []
    prog = Progress("check")
    src = FrameSource.sequence(frames_dir, meta.n_frames, meta.frame_rate_hz)
    for fr in src.read():
        if fr.image is None:
            bad.append([fr.path, fr.index, "error", fr.notes[-1][1] if fr.notes else "unreadable"])
        elif fr.image.shape[:2] != (cam.height, cam.width):
            bad.append([fr.path, fr.index, "error", f"size {fr.image.shape[1]}x{fr.image.shape[0]} is not the "
                                                    f"camera's {cam.width}x{cam.height}"])
        prog(fr.pos + 1, meta.n_frames)
    radius = (f"lumen radius {meta.tube_radius_m * 100:.2f} cm" if meta.tube_radius_m else
              "no tube_radius_m (motion and localize need --radius-m)")
    print(f"{seq}: {meta.n_frames} frames, {cam.width}x{cam.height}, camera {meta.camera.get('model')} "
          f"fov {cam.fov_deg:.1f} deg, {meta.frame_rate_hz:g} frames/s, {radius}; {len(bad)} bad frame(s)")
    return _print_problems(bad)


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    if getattr(args, "radius_m", None) is not None:  # every command that takes it: a unit mistake stops here
        from bodyslam.errors import ConfigError
        from bodyslam.meta import lumen_radius_problem

        if why := lumen_radius_problem(args.radius_m, "--radius-m"):
            raise ConfigError(why)
    return {"check": _check, "match": _match, "unroll": _unroll, "motion": _motion_or_track,
            "track": _motion_or_track, "speed-stats": _speed_stats, "segment": _segment,
            "train-classifier": _train_classifier, "classify": _classify, "rf-localize": _rf_localize,
            "localize": _localize, "batch": _batch, "hybrid-localize": _hybrid_localize,
            "magnetic-localize": _magnetic_localize, "rf-track": _rf_track}[args.cmd](args)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_cli(_main, argv, verbose="-v" in argv or "--verbose" in argv)


if __name__ == "__main__":
    sys.exit(main())

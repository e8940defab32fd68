"""Where a frame's time goes in the visual motion stage: milliseconds a frame per stage, one process.

Runs :func:`bodyslam.vision.odometry.sequence_motion` on a sequence directory (what `bodyslam motion SEQ --jobs 1`
and each `bodyslam batch` worker run) in this process, OpenCV on one thread as a batch worker sets it, under
cProfile, and prints each stage's time over the frames: decoding, FT/FL classification, tracking, feature
detection and matching, the tube fits (their fitting loop and essential-matrix start apart), guided matching, the
lumen scale's ring fits and gap bridging. Rows marked "of which" lie inside the row above them; the rest of a
frame's time is everything else (verification, bookkeeping, the lumen scale's chain). cProfile slows Python-heavy
code more than compiled code (~10% in all on a 576-px exam), so read the rows against each other, and the whole
run's speed from `bench_batch.py` or `bench_motion.py`. Issue 17: 100 frames/s on 2 cores is ~20 ms a frame and
core, the serial end included; this says which stage to look at next.

    .venv/bin/python benchmarks/bench_stages.py SEQ [--mode fast] [--frames N] [--json FILE] [--top N]

SEQ: a sequence directory (`testbed simulate ...`, or `bench_batch.py --keep DIR`'s exam). ``--frames N``: its first
N frames only (a whole exam's first stretch: a sequence directory of its own, in a temporary folder, with the frames
linked).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine import machine_info, machine_line  # noqa: E402  (benchmarks/machine.py, beside this script)

# (label, file the function is in, function names, the direct caller's (file, names) for an "of which" row, else
# None): an "of which" row lies inside the row above it and counts only the calls from that caller (the ring fits
# run the fitting loop too)
FRAME_FEATURES = ("bodyslam/vision/classify.py", ("frame_features",))
FIT_TUBE = ("bodyslam/vision/motion.py", ("fit_tube",))
STAGES = [
    ("decoding frames", "bodyslam/frames.py", ("decode_frame",), None),
    ("FT/FL classification", "bodyslam/vision/odometry.py", ("classify",), None),
    ("photometric normalisation", "bodyslam/vision/classify.py", ("normalise_photometric",), FRAME_FEATURES),
    ("SRM segmentation", "bodyslam/vision/segmentation.py", ("srm",), FRAME_FEATURES),
    ("tracking (Lucas-Kanade, its check)", "bodyslam/vision/matching.py", ("_track",), None),
    ("feature detection (SIFT / ASIFT)", "bodyslam/vision/matching.py", ("keypoints",), None),
    ("descriptor matching (ratio test)", "bodyslam/vision/matching.py", ("_ratio_matches",), None),
    ("tube fits", "bodyslam/vision/motion.py", ("fit_tube",), None),
    ("the fitting loop", "bodyslam/vision/motion.py", ("lm_compiled", "_lm_soft_l1"), FIT_TUBE),
    ("the essential-matrix start", "bodyslam/vision/motion.py", ("essential_start",), FIT_TUBE),
    ("guided matching (rotation steps)", "bodyslam/vision/guided.py", ("estimate_rotation",), None),
    ("lumen-scale ring fits", "bodyslam/vision/lumen_scale.py", ("ring_distance_ratio",), None),
    ("gap bridging", "bodyslam/vision/odometry.py", ("_follow_gap", "bridge"), None),
]


def _is(key: tuple, path: str, names: tuple[str, ...]) -> bool:
    file, _line, func = key
    return func in names and file.replace("\\", "/").endswith(path)


def stage_seconds(stats: pstats.Stats) -> dict[str, float]:
    """Each stage's cumulative seconds (a function's calls from inside itself counted once, as cProfile does); an
    "of which" row's from its caller only."""
    out = {}
    for label, path, names, caller in STAGES:
        if caller is None:
            out[label] = sum(v[3] for key, v in stats.stats.items() if _is(key, path, names))
        else:
            out[label] = sum(c[3] for key, v in stats.stats.items() if _is(key, path, names)
                             for by, c in v[4].items() if _is(by, *caller))
    return out


def _first_frames(seq: Path, n: int, tmp: str) -> Path:
    """A sequence directory in ``tmp`` holding ``seq``'s first ``n`` frames (its frames folder linked, meta.json's
    frame count cut, its RF left out)."""
    meta = json.loads((seq / "meta.json").read_text())
    sub = Path(tmp) / seq.name
    sub.mkdir()
    frames_dir = meta.get("frames", {}).get("dir", "frames")
    (sub / frames_dir).symlink_to((seq / frames_dir).resolve())
    meta["n_frames"] = min(n, int(meta["n_frames"]))
    meta.pop("rf", None)
    (sub / "meta.json").write_text(json.dumps(meta))
    return sub


def run(a: argparse.Namespace, tmp: str) -> int:
    """The profiled run and its table (``tmp``: where a first stretch is linked)."""
    from bodyslam.errors import BodySlamError
    from bodyslam.vision.odometry import MotionSettings, Sequence, sequence_motion, set_worker_threads

    shown = f"{a.seq} (its first {a.frames} frames)" if a.frames else str(a.seq)
    try:
        settings = MotionSettings(match_mode=a.mode)
        n = Sequence.open(a.seq).n_frames
        if a.frames is not None and a.frames < n:
            a.seq = _first_frames(a.seq, a.frames, tmp)
            n = Sequence.open(a.seq).n_frames
    except BodySlamError as e:
        print(f"bench_stages: {e}", file=sys.stderr)
        return 2
    machine = machine_info()  # before the benchmark's own work
    print(machine_line(machine), flush=True)
    set_worker_threads()
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    steps = sequence_motion(a.seq, settings, jobs=1)
    prof.disable()
    wall = time.perf_counter() - t0
    stats = pstats.Stats(prof)
    secs = stage_seconds(stats)
    print(f"{shown}: {n} frames, {len(steps)} steps, mode {a.mode}: {wall:.1f} s under cProfile, one process, "
          f"OpenCV on one thread ({1e3 * wall / n:.1f} ms a frame)")
    print(f"{'stage':44s} {'ms a frame':>10s} {'share':>6s}")
    for label, _, _, caller in STAGES:
        name = ("  of which " if caller else "") + label
        print(f"{name:44s} {1e3 * secs[label] / n:10.2f} {100 * secs[label] / wall:5.1f}%")
    top_level = sum(secs[label] for label, _, _, caller in STAGES if caller is None)
    print(f"{'everything else':44s} {1e3 * (wall - top_level) / n:10.2f} {100 * (wall - top_level) / wall:5.1f}%")
    if a.top:
        stats.sort_stats("tottime").print_stats(a.top)
    if a.json:
        a.json.write_text(json.dumps({"machine": machine, "seq": shown, "frames": n, "mode": a.mode, "wall_s": wall,
                                      "ms_per_frame": {k: 1e3 * v / n for k, v in secs.items()}}, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path, help="a sequence directory")
    ap.add_argument("--mode", default="fast", help="matcher mode (default fast, as bodyslam batch)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--top", type=int, default=0, help="also print the N functions with the most time of their own")
    ap.add_argument("--frames", type=int, help="the sequence's first N frames only (N >= 2)")
    a = ap.parse_args(argv)
    if a.frames is not None and a.frames < 2:
        ap.error(f"--frames must be at least 2, got {a.frames}")
    with tempfile.TemporaryDirectory(prefix="bench_stages_") as tmp:
        return run(a, tmp)


if __name__ == "__main__":
    sys.exit(main())

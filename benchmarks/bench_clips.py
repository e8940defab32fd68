"""Short clips as a user hands them in: issue 16's checks on testbed proxies of real clips.

Cuts clips of ``--frames`` consecutive frames out of rendered sequences (frames only: copied as a plain folder of
PNGs, no meta.json, so `bodyslam batch` runs on its defaults -- assumed lens, frame rate and lumen radius -- as on
a real clip), runs `bodyslam batch` on each clip and on the same clip reversed, and compares with the truth the
sequence keeps (scoring only):

- the path travelled forwards against reversed (issue 16: "agrees forward and reversed within 15%");
- the path at the clip's end against the true one (summed lengths of the true steps), and whether the error is
  inside the stated 1-sigma;
- the share of steps with a full estimate, and the share of those that point forward (camera +z).

    .venv/bin/python benchmarks/bench_clips.py SEQ_DIR [SEQ_DIR ...] --starts 0,30,60,90,120,150,180 --out DIR
        [--batch-args "--mode asift"]

Use tuning seeds to choose anything and reporting seeds to report (README, "Seeds").
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np


def batch(clip: Path, out: Path, extra: list[str] | None = None) -> tuple[int, dict, list[dict]]:
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "batch", str(clip), "--out", str(out), "--force",
                        *(extra or [])], capture_output=True, text=True)
    ex = out / clip.name
    if not (ex / "summary.json").exists():
        raise SystemExit(f"bodyslam batch failed on {clip} (exit {p.returncode}): {p.stderr.strip()[-500:]}")
    rows = list(csv.DictReader(open(ex / "motion.csv", newline="")))
    return p.returncode, json.loads((ex / "summary.json").read_text()), rows


def both_ways(frames: list[Path], d: Path, extra: list[str] | None = None) -> tuple[tuple, tuple]:
    """A clip's frames copied as plain folders ``d/forward`` and ``d/reversed`` (named 000, 001, ... in each
    order) and each run through :func:`batch` (into ``d/out_forward``, ``d/out_reversed``)."""
    n = len(frames)
    for kind in ("forward", "reversed"):
        c = d / kind
        if c.exists():
            shutil.rmtree(c)
        c.mkdir(parents=True)
        for i, f in enumerate(frames):
            shutil.copy(f, c / f"{(i if kind == 'forward' else n - 1 - i):03d}{f.suffix}")
    return batch(d / "forward", d / "out_forward", extra), batch(d / "reversed", d / "out_reversed", extra)


def full_and_forward(rows: list[dict]) -> tuple[float, float]:
    full = [r for r in rows if r["status"] in ("ok", "wall", "bridged")]
    fwd = [float(r["tz_m"]) > 0 for r in full]
    return len(full) / max(len(rows), 1), (float(np.mean(fwd)) if fwd else float("nan"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdirs", nargs="+", type=Path)
    ap.add_argument("--frames", type=int, default=18, help="frames per clip (default 18, a real clip's length)")
    ap.add_argument("--starts", default="0,30,60,90,120,150,180", help="first frame of each clip")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--batch-args", default="", help="options for every `bodyslam batch` run, as one string "
                    "(e.g. \"--mode asift\"; default: none, batch's defaults)")
    args = ap.parse_args()
    extra = shlex.split(args.batch_args)
    L, starts = args.frames, [int(x) for x in args.starts.split(",")]
    results = []
    for seq in args.seqdirs:
        if not (seq / "motion_truth.csv").is_file() or not (seq / "frames").is_dir():
            raise SystemExit(f"{seq}: not a rendered sequence with its frames (needs frames/ and motion_truth.csv; "
                             f"testbed evaluate --keep-frames or testbed simulate writes them)")
        truth = list(csv.DictReader(open(seq / "motion_truth.csv", newline="")))
        frames = sorted((seq / "frames").iterdir())
        for a in starts:
            if a + L > len(frames):
                continue
            d = args.out / f"{seq.name}_{a}"
            (rc_f, sf, mf), (rc_r, sr, mr) = both_ways(frames[a:a + L], d, extra)
            true_m = sum(abs(float(truth[a + i]["distance_m"])) for i in range(L - 1))
            pf, pr = sf["path_travelled_m"], sr["path_travelled_m"]
            full_f, fwd_f = full_and_forward(mf)
            full_r, fwd_r = full_and_forward(mr)
            r = {"clip": f"{seq.name}_{a}", "exit": [rc_f, rc_r], "true_path_cm": 100 * true_m,
                 "path_forward_cm": 100 * pf, "sd_forward_cm": 100 * sf["sd_path_travelled_m"],
                 "path_reversed_cm": 100 * pr, "disagreement": abs(pf - pr) / max(pf, pr, 1e-12),
                 "end_error_rel": (pf - true_m) / true_m if true_m > 0 else float("nan"),
                 "inside_1sigma": abs(pf - true_m) <= sf["sd_path_travelled_m"],
                 "full_estimate_frac": full_f, "forward_frac": fwd_f, "full_estimate_frac_reversed": full_r,
                 "forward_frac_reversed": fwd_r}
            results.append(r)
            print(f"{r['clip']}: path {r['path_forward_cm']:.2f} +- {r['sd_forward_cm']:.2f} cm forwards, "
                  f"{r['path_reversed_cm']:.2f} reversed ({r['disagreement']:.0%} apart), {r['true_path_cm']:.2f} "
                  f"true; {full_f:.0%} of steps estimated, {fwd_f:.0%} of them forward ({fwd_r:.0%} reversed)",
                  flush=True)
    if not results:
        raise SystemExit("no clip fits: sequences shorter than --frames from every --starts")
    dis = np.array([r["disagreement"] for r in results])
    err = np.array([r["end_error_rel"] for r in results])
    summary = {"clips": len(results), "frames_per_clip": L,
               "agree_within_15pct": float(np.mean(dis <= 0.15)), "median_disagreement": float(np.median(dis)),
               "end_error_mean": float(np.nanmean(err)), "end_error_median_abs": float(np.nanmedian(np.abs(err))),
               "end_error_worst": float(err[np.nanargmax(np.abs(err))]),
               "inside_1sigma": float(np.mean([r["inside_1sigma"] for r in results])),
               "full_estimate_frac_mean": float(np.mean([r["full_estimate_frac"] for r in results]))}
    print(f"\n{len(results)} clips of {L} frames: forwards and reversed within 15% on "
          f"{summary['agree_within_15pct']:.0%} (median {summary['median_disagreement']:.1%} apart); path at the "
          f"end {summary['end_error_mean']:+.1%} on average, {summary['end_error_median_abs']:.1%} median absolute, "
          f"worst {summary['end_error_worst']:+.1%}; inside the stated 1-sigma {summary['inside_1sigma']:.0%}; "
          f"{summary['full_estimate_frac_mean']:.0%} of steps estimated")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "clips": results}, indent=1))


if __name__ == "__main__":
    main()

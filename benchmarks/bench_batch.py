"""`bodyslam batch` on whole-exam stand-ins: frames per second and peak memory against exam length.

Renders the `exam` scenario (320x320, 2 frames/s, 6 m of small bowel) at each length (cached under --keep; beyond
its 10,000 frames at a slower pace over ~5.5 m: :func:`long_exam_settings`),
then runs the whole `bodyslam batch` process as a user would (fast mode, both cores, no RF so the trajectory is
the streaming dead reckoning) and samples the resident memory of its whole process tree (the coordinator and
its workers, from /proc every 0.2 s). Prints frames/s (wall time of the whole process, start-up included) and
the peak tree memory per length, and the ratio of the longest to the shortest.

    .venv/bin/python benchmarks/bench_batch.py [--frames 2000,10000] [--scenario exam|realistic_exam] [--mode fast]
        [--keep /tmp/bench_batch] [--rf] [--size PX]
        [--rss-bias-states] [--jobs 1,2] [--jobs-rf 1,2] [--jobs-only] [--dask 2] [--repeat 3]

``--scenario realistic_exam``: the realistic testbed's look (collapsed, folded, contracting lumen; fluid, debris and
bubbles; capsule optics; its radio channel) at the same pace: what frames like a real exam's cost. Its 2.5 m path
holds ~3,600 frames at that pace; a longer exam gets a longer path and a slower pace
(:func:`long_realistic_exam_settings`).

``--rf``: also the same exam with its RF (the sequence directory: rf.csv, sensors.csv, the path-loss calibration),
so the trajectory is the fused one, and the ratio of the two throughputs (issue 17: >= 0.85). ``--rss-bias-states``:
that run with the opt-in per-sensor RSS bias states.

``--jobs 1,2,4`` / ``--jobs-rf 1,2,4``: frames/s of the whole process against the number of worker processes,
without and with the exam's RF, and whether every count gives byte-identical motion.csv and trajectory.tum (the
chunk size follows the workers: results must not). ``--jobs-only``: those tables alone.

``--repeat N``: each exam N times (with ``--rf`` the runs without and with RF alternated), then the median and
range of frames/s and of the ratio: one run on a machine whose speed drifts is not a measurement of a target.

``--dask N``: also the same frames on a Dask ``LocalCluster`` of N single-threaded worker processes started by
this script (``bodyslam batch --scheduler ADDRESS``): frames/s of the whole batch process, and whether its
motion.csv and trajectory.tum are byte-identical to the local run's. The cluster's workers are not children of
the batch process, so its peak memory is the coordinator's only.

Goal (issue 7): >= 100 frames/s in fast mode on this 2-core machine; peak memory at 10,000 frames no more than
10% above that at 2,000.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from machine import machine_info, machine_line  # benchmarks/machine.py, beside this script


EXAM_FRAMES = 10_000  # the exam scenario's length: its 6 m path at its 0.06 cm mean step
LONG_EXAM_PATH_M = 5.5  # a longer exam covers the same small bowel, at a slower pace


def long_exam_settings(n: int) -> list[str]:
    """``testbed simulate`` overrides for an exam longer than the scenario's: the mean step scaled so the capsule
    covers ~5.5 m whatever the length (at the scenario's step it would leave the path), and the lateral wobble cut to
    0.01 of the radius. The mean step counts the wobble: at the scenario's 0.05 a 0.01 cm step is all wobble and the
    capsule stays put (session 21: 0.5 cm from its start after 55,000 frames, a case no real exam looks like)."""
    if n <= EXAM_FRAMES:
        return []
    return ["--set", f"motion.mean_step_m={LONG_EXAM_PATH_M / n:g}", "--set", "motion.offset_std_frac=0.01"]


REALISTIC_EXAM_FRAMES = 3_600  # realistic_exam's 2.5 m path at its 0.06 cm mean step, with room for the wobble
# beyond that: the longest path its abdomen box holds at the exam scenario's self-distance (1.5 lumen diameters;
# `realistic`'s 2 allow ~3.4 m, this ~4.8 m: `testbed simulate` says so), covered to ~4.0 m at a slower pace
LONG_REALISTIC_PATH_M, LONG_REALISTIC_COVER_M = 4.5, 4.0


def long_realistic_exam_settings(n: int) -> list[str]:
    """``testbed simulate`` overrides for a ``realistic_exam`` longer than its path holds
    (:data:`REALISTIC_EXAM_FRAMES`): a 4.5-m path, the capsule covering ~4 m of it (the mean step 4.0 m / ``n``:
    0.04 cm at 10,000 frames, against the scenario's 0.06) with its lateral wobble scaled down with the step (as
    :func:`long_exam_settings` does: a wobble larger than the step keeps the capsule in place)."""
    if n <= REALISTIC_EXAM_FRAMES:
        return []
    step = LONG_REALISTIC_COVER_M / n
    wobble = 0.05 * min(1.0, step / 0.0006)  # realistic_exam's 0.05 at its 0.06 cm step
    return ["--set", f"path.length_m={LONG_REALISTIC_PATH_M:g}", "--set", "path.min_self_distance_diameters=1.5",
            "--set", f"motion.mean_step_m={step:g}", "--set", f"motion.offset_std_frac={wobble:g}"]


def tree_rss_bytes(pid: int) -> int:
    """Resident memory of ``pid`` and all its descendants (Linux /proc)."""
    children: dict[int, list[int]] = {}
    rss = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
            ppid = int(parts[1])
            rss[int(d)] = int(parts[21]) * os.sysconf("SC_PAGE_SIZE")
            children.setdefault(ppid, []).append(int(d))
        except (OSError, ValueError, IndexError):
            continue
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo.extend(children.get(p, []))
    return total


def run_measured(cmd: list[str]) -> tuple[float, int, int]:
    """``(seconds, peak tree RSS bytes, return code)`` of a command."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = 0
    stop = threading.Event()

    def sample():
        nonlocal peak
        while not stop.is_set():
            peak = max(peak, tree_rss_bytes(p.pid))
            time.sleep(0.2)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out, _ = p.communicate()
    stop.set()
    th.join()
    el = time.perf_counter() - t0
    if p.returncode not in (0, 3):
        print(out)
    return el, peak, p.returncode


def run_on_dask(cmd: list[str], out_local: Path, n_workers: int, n: int, exam: str) -> dict:
    """The batch command ``cmd`` (its ``--out`` is item 6) sent to a Dask LocalCluster of ``n_workers`` processes,
    timed and compared with the local run in ``out_local``."""
    from distributed import LocalCluster

    out = out_local.with_name(out_local.name + f"_dask{n_workers}")
    shutil.rmtree(out, ignore_errors=True)
    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        el, peak, rc = run_measured([*cmd[:6], str(out), *cmd[7:], "--scheduler", cluster.scheduler_address])
    same = all((out / exam / f).read_bytes() == (out_local / exam / f).read_bytes()
               for f in ("motion.csv", "trajectory.tum"))
    print(f"  on a Dask LocalCluster of {n_workers} worker processes: {el:.1f} s = {n / el:.1f} frames/s "
          f"(rc {rc}); motion.csv and trajectory.tum identical to the local run's: {same}", flush=True)
    return {"workers": n_workers, "seconds": el, "frames_per_s": n / el, "rc": rc, "identical_to_local": same,
            "coordinator_peak_rss_mib": peak / 2**20}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", default="2000,10000")
    ap.add_argument("--scenario", choices=("exam", "realistic_exam"), default="exam",
                    help="the stand-in rendered: exam (ideal frames, default) or realistic_exam (the realistic "
                         "testbed's look at the same pace: a real exam's frames are more like these)")
    ap.add_argument("--mode", default="fast")
    ap.add_argument("--size", type=int, default=None, metavar="PX",
                    help="render the frames PX x PX (default: the scenario's 320; a PillCam frame is 576)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=Path("/tmp/bench_batch"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--rf", action="store_true", help="also run the exam with its RF and print the throughput ratio")
    ap.add_argument("--rss-bias-states", action="store_true",
                    help="with --rf: the fusion with per-sensor RSS bias states (bodyslam batch --rss-bias-states)")
    ap.add_argument("--jobs", default=None,
                    help="comma-separated worker counts (e.g. 1,2,4,8,16): frames/s against jobs for each length, "
                         "and whether every count gives byte-identical motion.csv / trajectory.tum")
    ap.add_argument("--jobs-rf", default=None, metavar="LIST",
                    help="comma-separated worker counts run with the exam's RF (the fused trajectory): frames/s against "
                         "jobs with RF, and whether every count gives byte-identical outputs")
    ap.add_argument("--jobs-only", action="store_true",
                    help="only the --jobs / --jobs-rf tables (not the default run with one worker per core): a "
                         "machine lent for minutes")
    ap.add_argument("--repeat", type=int, default=1, metavar="N",
                    help="run each exam N times (with --rf: without and with RF alternated) and print the median and "
                         "range: this machine's speed drifts by 10-20%% between runs")
    ap.add_argument("--dask", type=int, default=0, metavar="N",
                    help="also run on a Dask LocalCluster of N worker processes and compare with the local run")
    args = ap.parse_args()
    if args.rss_bias_states and not args.rf:
        raise SystemExit("--rss-bias-states is a setting of the run with RF: give --rf too")
    if args.repeat < 1:
        raise SystemExit(f"--repeat {args.repeat}: give at least 1 run")
    if args.dask < 0:
        raise SystemExit(f"--dask {args.dask}: give a number of Dask worker processes (0: no Dask run)")
    if args.dask and importlib.util.find_spec("distributed") is None:  # checked before any exam is run
        raise SystemExit("--dask needs Dask distributed (pip install 'dask[distributed]')")
    for name in ("jobs", "jobs_rf"):  # worker counts: checked before any exam is rendered or run
        v = getattr(args, name)
        if v is not None and not all(x.strip().isdigit() and int(x) >= 1 for x in v.split(",")):
            raise SystemExit(f"--{name.replace('_', '-')} {v}: give worker counts (whole numbers >= 1), e.g. 1,2,4")
    if args.jobs_only and not (args.jobs or args.jobs_rf):
        raise SystemExit("--jobs-only: give the counts to run (--jobs and/or --jobs-rf)")
    lengths = [int(x) for x in args.frames.split(",")]
    if args.size is not None and args.size < 64:
        raise SystemExit(f"--size {args.size}: give the frame's width and height in pixels (64 or more)")
    size = ["--set", f"camera.width={args.size}", "--set", f"camera.height={args.size}"] if args.size else []
    px = args.size or 320
    args.keep.mkdir(parents=True, exist_ok=True)
    machine = machine_info()  # before the benchmark's own work
    print(machine_line(machine), flush=True)
    res = {}
    for n in lengths:
        # (the exam's caches keep their names)
        tag = ("" if args.scenario == "exam" else f"{args.scenario}_") + (f"{args.size}px_" if args.size else "")
        seq = args.keep / (f"exam_{args.seed}_{n}" if not tag else f"{tag}{args.seed}_{n}")
        if not (seq / "meta.json").exists():
            t0 = time.perf_counter()
            longer = long_exam_settings(n) if args.scenario == "exam" else long_realistic_exam_settings(n)
            subprocess.run([sys.executable, "-m", "testbed.cli", "simulate", args.scenario, "--seed", str(args.seed),
                            "--frames", str(n), "--out", str(seq), "--force", *longer, *size], check=True)
            print(f"rendered {n} frames in {time.perf_counter() - t0:.0f} s", flush=True)
        meta = json.loads((seq / "meta.json").read_text())
        # the same exam without its RF: a sequence directory whose meta.json is the exam's less its "rf" entry and
        # whose frames are the exam's (a link), so both runs' vision reads the same radius, radius prior, camera and
        # rate and they differ by the RF alone (a plain frame folder took the population radius prior where the
        # exam's meta.json states its own: its runs without RF measured other vision work; session 59)
        folder = args.keep / f"{tag}norf_{args.seed}_{n}"
        folder.mkdir(exist_ok=True)
        if not (folder / "frames").exists():
            (folder / "frames").symlink_to(seq / "frames")
        (folder / "meta.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "rf"}))
        out = args.keep / f"{tag}out_{args.mode}_{n}"
        shutil.rmtree(out, ignore_errors=True)
        cmd = [sys.executable, "-m", "bodyslam.cli", "batch", str(folder), "--out", str(out), "--mode", args.mode]
        # the same exam with its RF (the sequence directory); item 6, the output, is set per run
        cmd_rf = [sys.executable, "-m", "bodyslam.cli", "batch", str(seq), "--out", "OUT", "--mode", args.mode,
                  *(["--rss-bias-states"] if args.rss_bias_states else [])]
        for key, counts, base_cmd, name in (("jobs_rf", args.jobs_rf, cmd_rf, seq.name),
                                             ("jobs", args.jobs, cmd, folder.name)):
            if not counts:
                continue
            scaling, ref = {}, None
            other = res.get(n, {}).get("jobs_rf")  # the table with RF, before this one without
            for j in [int(x) for x in counts.split(",")]:
                out_j = args.keep / f"{tag}out_{args.mode}_{n}_{key}{j}"
                shutil.rmtree(out_j, ignore_errors=True)
                el_j, peak_j, _ = run_measured([*base_cmd[:6], str(out_j), *base_cmd[7:], "--jobs", str(j)])
                files = tuple((out_j / name / f).read_bytes() for f in ("motion.csv", "trajectory.tum"))
                same = ref is None or files == ref
                ref = ref or files
                ph = json.loads((out_j / "summary.json").read_text()).get("phases_end_s", {})
                scaling[j] = {"seconds": el_j, "frames_per_s": n / el_j, "peak_tree_rss_mib": peak_j / 2**20,
                              "identical_to_first": same, "phases_end_s": ph}
                base = scaling[next(iter(scaling))]["frames_per_s"]
                print(f"  {'with RF' if key == 'jobs_rf' else 'without RF'} --jobs {j}: {n / el_j:.1f} frames/s "
                      f"({n / el_j / base:.2f}x the first count), {el_j:.1f} s, peak {peak_j / 2**20:.0f} MiB, "
                      f"outputs identical to the first count's: {same}", flush=True)
                print("    phases ended at (s after the batch started; the process started "
                      f"{el_j - ph.get('exams', el_j):.1f} s before): "
                      + ", ".join(f"{k} {v:.1f}" for k, v in ph.items()), flush=True)
            res.setdefault(n, {})[key] = scaling
            if other is not None:  # the same vision either way: only the RF differs between the two tables
                same_vision = (args.keep / f"{tag}out_{args.mode}_{n}_jobs_rf{next(iter(other))}" / seq.name
                               / "motion.csv").read_bytes() == ref[0]
                res[n]["motion_same_with_and_without_rf"] = same_vision
                print(f"  motion.csv the same with and without RF: {same_vision}", flush=True)
        if args.jobs_only:
            continue
        runs = []  # (seconds without RF, seconds with RF or None), alternated --repeat times
        for rep in range(args.repeat):
            run_tag = f" (run {rep + 1}/{args.repeat})" if args.repeat > 1 else ""
            shutil.rmtree(out, ignore_errors=True)
            el, peak, rc = run_measured(cmd)
            summ = json.loads((out / "summary.json").read_text())["exams"][0]
            if rep == 0:
                res.setdefault(n, {}).update({"seconds": el, "frames_per_s": n / el, "peak_tree_rss_mib": peak / 2**20,
                                              "rc": rc, "steps": summ["steps"], "path_m": summ["path_travelled_m"]})
            print(f"bodyslam batch --mode {args.mode}: {n} frames {px}x{px} in {el:.1f} s = {n / el:.1f} frames/s "
                  f"(whole process, 2 cores){run_tag}; peak memory (process tree) {peak / 2**20:.0f} MiB; steps "
                  f"{summ['steps']}", flush=True)
            if args.dask and rep == 0:
                res[n]["dask"] = run_on_dask(cmd, out, args.dask, n, folder.name)
            el_rf = None
            if args.rf:
                out_rf = args.keep / f"{tag}out_{args.mode}_{n}_rf"  # tag: the scenario's, as the run without RF
                shutil.rmtree(out_rf, ignore_errors=True)
                el_rf, peak_rf, rc_rf = run_measured([*cmd_rf[:6], str(out_rf), *cmd_rf[7:]])
                traj = json.loads((out_rf / "summary.json").read_text())["exams"][0]["trajectory"]
                # a like-for-like ratio: the same vision either way
                same_vision = ((out_rf / seq.name / "motion.csv").read_bytes()
                               == (out / folder.name / "motion.csv").read_bytes())
                if rep == 0:
                    res[n].update(rf_seconds=el_rf, rf_frames_per_s=n / el_rf, rf_peak_tree_rss_mib=peak_rf / 2**20,
                                  rf_rc=rc_rf, rf_over_no_rf=el / el_rf, motion_same_with_and_without_rf=same_vision)
                print(f"  with RF ({traj}){run_tag}: {el_rf:.1f} s = {n / el_rf:.1f} frames/s, peak "
                      f"{peak_rf / 2**20:.0f} MiB; throughput with RF / without: {el / el_rf:.2f}; motion.csv the "
                      f"same with and without RF: {same_vision}", flush=True)
            runs.append((el, el_rf))
        if args.repeat > 1:  # a machine whose speed drifts: the spread says how far one run can be trusted
            fps = np.array([n / a for a, _ in runs])
            line = (f"  {args.repeat} runs without RF: median {np.median(fps):.1f} frames/s "
                    f"({fps.min():.1f}-{fps.max():.1f})")
            res[n]["repeat"] = {"frames_per_s": fps.tolist()}
            if args.rf:
                fps_rf = np.array([n / b for _, b in runs])
                ratio = np.array([a / b for a, b in runs])
                line += (f"; with RF: median {np.median(fps_rf):.1f} ({fps_rf.min():.1f}-{fps_rf.max():.1f}); ratio "
                         f"median {np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f})")
                res[n]["repeat"].update(rf_frames_per_s=fps_rf.tolist(), rf_over_no_rf=ratio.tolist())
            print(line, flush=True)
    if len(lengths) > 1 and not args.jobs_only:
        a, b = res[min(lengths)], res[max(lengths)]
        print(f"peak memory {max(lengths)} vs {min(lengths)} frames: "
              f"{b['peak_tree_rss_mib'] / a['peak_tree_rss_mib']:.3f}x")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine, **res}, indent=1))


if __name__ == "__main__":
    main()

"""Which machine a speed benchmark ran on, and how fast one of its cores does the pipeline's own work (issue 17).

Frames/s say as much about the machine as about the code. The same 10,000-frame `realistic_exam` with RF
(`bench_batch.py --scenario realistic_exam --frames 10000 --rf`) ran at 79 frames/s on session 79's 2-core Intel Xeon
and at 48 on session 80's 2-core AMD EPYC, with the same code; an AMD machine gave 123 on a fast day. So the speed
benchmarks (`bench_batch.py`, `bench_motion.py`, `bench_stages.py`) print this first: the CPU model and its cores,
Python's and OpenCV's versions, and two reference times on one thread, the median of a few repeats, taken in a
fresh Python process (:func:`machine_info`):

- ``sift_ms``: SIFT detection and description (every matcher mode's detector; ``contrastThreshold`` 0.01, as
  :class:`bodyslam.vision.matching.Matcher` creates it) on the first frame of the embedded sample
  (`data_samples/demo_seed0`, 320 x 320);
- ``python_ms``: a plain CPython loop of 10^6 additions (the pipeline's Python bookkeeping).

Read two runs' frames/s with these beside them. The times are taken before the benchmark starts its work, and say
nothing of what else runs on the machine meanwhile.

    .venv/bin/python benchmarks/machine.py      # the line alone (--json: the figures, as the benchmarks take them)
"""

from __future__ import annotations

import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bodyslam.parallel import available_cores  # the cores a worker pool would use

REFERENCE_FRAME = Path(__file__).resolve().parent.parent / "data_samples" / "demo_seed0" / "frames" / "000000.png"
SIFT_REPEATS, PYTHON_REPEATS = 9, 5


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo, Linux), or what :mod:`platform` says elsewhere."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def _sift_ms(repeats: int) -> float | None:
    """Median milliseconds of one SIFT ``detectAndCompute`` on :data:`REFERENCE_FRAME`, OpenCV on one thread
    (its previous thread count restored); None when the frame or OpenCV is missing."""
    try:
        import cv2
    except ImportError:
        return None
    img = cv2.imread(str(REFERENCE_FRAME), cv2.IMREAD_GRAYSCALE)
    if img is None:
        return None
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        sift = cv2.SIFT_create(contrastThreshold=0.01)
        sift.detectAndCompute(img, None)  # warm-up: first-call allocations
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            sift.detectAndCompute(img, None)
            times.append(time.perf_counter() - t)
    finally:
        cv2.setNumThreads(threads)
    return 1e3 * statistics.median(times)


def _python_ms(repeats: int) -> float:
    """Median milliseconds of a CPython loop of 10^6 additions."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        s = 0
        for i in range(1_000_000):
            s += i
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def machine_info() -> dict:
    """The machine and its reference times (module docstring), as a JSON-ready dict, measured in a fresh Python
    process: what a process did before (its imports, its allocations) moves the SIFT time by up to a quarter through
    glibc's malloc state (session 80: 88-95 ms after the pipeline's imports, 111-123 ms in a fresh process, minutes
    apart), so every benchmark takes it the same way."""
    try:
        out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--json"], capture_output=True,
                             text=True, check=True)
        return json.loads(out.stdout)
    except (OSError, subprocess.CalledProcessError, ValueError):  # the benchmark goes on without its reference
        return {"cpu": cpu_model(), "cores": available_cores(), "python": platform.python_version(), "opencv": None,
                "sift_ms": None, "python_ms": None}


def _measure(sift_repeats: int = SIFT_REPEATS, python_repeats: int = PYTHON_REPEATS) -> dict:
    """:func:`machine_info` in this process."""
    try:
        import cv2
        opencv = cv2.__version__
    except ImportError:
        opencv = None
    sift = _sift_ms(sift_repeats)
    return {"cpu": cpu_model(), "cores": available_cores(), "python": platform.python_version(), "opencv": opencv,
            "sift_ms": None if sift is None else round(sift, 2), "python_ms": round(_python_ms(python_repeats), 1)}


def machine_line(info: dict | None = None) -> str:
    """One line for a benchmark's output: :func:`machine_info` (measured now when not given)."""
    info = machine_info() if info is None else info
    sift = ("n/a (no OpenCV, no sample frame, or the measurement failed)" if info["sift_ms"] is None
            else f"{info['sift_ms']:.1f} ms")
    loop = "n/a" if info["python_ms"] is None else f"{info['python_ms']:.0f} ms"
    return (f"machine: {info['cpu']}, {info['cores']} core(s), Python {info['python']}, OpenCV {info['opencv']}; "
            f"one core: SIFT on the sample's 320-px frame {sift}, a 10^6-step Python loop {loop} "
            f"(benchmarks/machine.py: read two machines' frames/s with these)")


if __name__ == "__main__":
    if sys.argv[1:] == ["--json"]:
        print(json.dumps(_measure()))
    else:
        print(machine_line())

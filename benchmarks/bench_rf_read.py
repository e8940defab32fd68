"""Memory and time of reading an exam's RF readings (``rf.csv``, long format: a line per reading), as the fusion
reads them (:meth:`bodyslam.fusion.localize.RfInput.read`), in a fresh process.

A 100,000-frame exam with 32 sensors has 3.2 million lines. Printed: the seconds, the resident memory before the
read and its peak during it (Linux VmHWM, reset before), and what the table holds. ``--bad-line`` reads a copy of
the file with one malformed line appended (the line-by-line path that names it). Measured in session 44 on the
100,000-frame ``exam`` stand-in (``benchmarks/bench_batch.py`` renders it; docs/RESULTS.md, "A 100,000-frame exam
with RF under 1 GB"): peak 341 -> 173 MiB plain, 2,308 -> 332 MiB with a bad line, after the read in blocks.

    .venv/bin/python benchmarks/bench_rf_read.py SEQ [--bad-line]

``SEQ``: a sequence directory with ``rf.csv``, ``sensors.csv`` and ``meta.json`` (its ``rf.pathloss``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _status_mib(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"/proc/self/status has no {field}")


def child(seq: Path, rf_csv: Path) -> dict:
    from bodyslam.fusion.localize import RfInput
    from bodyslam.io import read_json

    pathloss = read_json(seq / "meta.json").get("rf", {}).get("pathloss")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # the peak from here on
    except OSError as exc:
        raise SystemExit(f"cannot reset the peak resident memory (/proc/self/clear_refs): {exc}") from None
    before = _status_mib("VmRSS")
    t0 = time.perf_counter()
    rf = RfInput.read(rf_csv, seq / "sensors.csv", pathloss)
    return {"seconds": time.perf_counter() - t0, "rss_before_mib": before, "rss_peak_mib": _status_mib("VmHWM"),
            "times": int(rf.rss_dbm.shape[0]), "sensors": int(rf.rss_dbm.shape[1]), "problems": len(rf.problems)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--bad-line", action="store_true", help="read a copy with one malformed line appended")
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.seq, args.child)))
        return
    rf_csv = args.seq / "rf.csv"
    if not rf_csv.is_file():
        raise SystemExit(f"{rf_csv}: file not found (give a sequence directory with rf.csv and sensors.csv)")
    with tempfile.TemporaryDirectory() as tmp:
        if args.bad_line:
            bad = Path(tmp) / "rf.csv"
            shutil.copyfile(rf_csv, bad)
            with bad.open("a", encoding="utf-8") as f:
                f.write("12.5,F00,not-a-number\n")
            rf_csv = bad
        lines = sum(1 for _ in rf_csv.open("rb")) - 1
        proc = subprocess.run([sys.executable, __file__, str(args.seq), "--child", str(rf_csv)],
                              capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"the read failed (exit {proc.returncode}):\n{proc.stderr.strip()[-2000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"{lines} lines -> {r['times']} times x {r['sensors']} sensors, {r['problems']} problem line(s): "
          f"{r['seconds']:.1f} s, resident {r['rss_before_mib']:.0f} MiB before, peak {r['rss_peak_mib']:.0f} MiB")


if __name__ == "__main__":
    main()

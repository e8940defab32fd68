"""Device side of the 16-core table: the exam's H.264 copy back into a sequence directory.

    python3 benchmarks/device/unpack_exam.py CARRY/exam.mp4 /tmp/bb/exam_1_10000 [CARRY/side]

Writes ``frames/NNNNNN.png`` (every frame of the video, in order) and the sidecars found in the sidecar folder
(default ``CARRY/side``; ``*.gz`` unzipped: rf.csv travels gzipped) beside them, so ``bench_batch.py --keep
/tmp/bb`` finds the exam as if rendered there. See docs/RESULTS.md, "Whole exams on 16 cores", for how the copy is
made and what it changes.
"""

import gzip
import os
import shutil
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import cv2

if len(sys.argv) not in (3, 4):
    sys.exit("usage: unpack_exam.py VIDEO SEQUENCE_DIR [SIDECAR_DIR]")
SRC, DST = Path(sys.argv[1]), Path(sys.argv[2])
SIDE = Path(sys.argv[3]) if len(sys.argv) > 3 else SRC.parent / "side"


def _put(item):
    k, im = item
    cv2.imwrite(str(DST / "frames" / f"{k:06d}.png"), im)
    return k


def _frames():
    cap = cv2.VideoCapture(str(SRC))
    k = 0
    while True:
        ok, im = cap.read()
        if not ok:
            return
        yield k, im
        k += 1


if __name__ == "__main__":
    if not SRC.is_file() or not SIDE.is_dir():
        sys.exit(f"unpack_exam.py: {SRC if not SRC.is_file() else SIDE} not found")
    (DST / "frames").mkdir(parents=True, exist_ok=True)
    for f in SIDE.iterdir():
        if f.suffix == ".gz":
            with gzip.open(f, "rb") as a, open(DST / f.stem, "wb") as b:
                shutil.copyfileobj(a, b)
        else:
            shutil.copy(f, DST / f.name)
    t0 = time.time()
    with Pool(max(1, (os.cpu_count() or 2) - 1)) as p:
        n = sum(1 for _ in p.imap_unordered(_put, _frames(), chunksize=16))
    if n == 0:  # an empty frames folder would pass for an unpacked exam on the next try
        shutil.rmtree(DST / "frames")
        sys.exit(f"unpack_exam.py: {SRC}: no frame could be decoded")
    print(f"unpacked {n} frames in {time.time() - t0:.1f} s", flush=True)

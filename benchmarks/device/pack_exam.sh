#!/usr/bin/env bash
# Here: the 10,000-frame exam (exam scenario, seed 1) packed for a lent device machine into the ignored folders the
# device tool carries (64 MiB in all): .devrun/exam.mp4 (H.264, crf 30: ~36 MB), .devrun/side/ (meta.json,
# sensors.csv, rf.csv.gz), .devrun/run.sh (benchmarks/device/run_16core.sh), .whl/ (the plotly wheel: the device
# image lacks it). Beside it the realistic testbed's 2,000-frame realistic_exam (seed 1; bench_batch.py's
# --scenario realistic_exam naming) as .devrun/realistic.mp4 (crf 35: ~3 MB; 64 MiB hold no more) and
# .devrun/side_realistic/, so the table is measured on realistic frames too. Then, on the device:
# `bash .devrun/run.sh` with carry [".devrun", ".whl"].
#   bash benchmarks/device/pack_exam.sh [KEEP=/tmp/bb]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
keep="${1:-/tmp/bb}"
seq="$keep/exam_1_10000"
if [ ! -d "$seq/frames" ]; then  # ~8 minutes here
  .venv/bin/testbed simulate exam --seed 1 --frames 10000 --out "$seq"
fi
tools=/tmp/bodyslam-device-tools
[ -d "$tools/imageio_ffmpeg" ] || .venv/bin/python -m pip install -q --target "$tools" imageio-ffmpeg  # ffmpeg with libx264
ffmpeg="$(PYTHONPATH=$tools .venv/bin/python -c 'import imageio_ffmpeg; print(imageio_ffmpeg.get_ffmpeg_exe())')"
mkdir -p .devrun/side .whl
"$ffmpeg" -y -loglevel error -framerate 2 -start_number 0 -i "$seq/frames/%06d.png" -c:v libx264 -preset slow \
  -crf 30 -pix_fmt yuv420p .devrun/exam.mp4
cp "$seq/meta.json" "$seq/sensors.csv" .devrun/side/
gzip -c "$seq/rf.csv" > .devrun/side/rf.csv.gz
real="$keep/realistic_exam_1_2000"
if [ ! -d "$real/frames" ]; then  # ~3 minutes here
  .venv/bin/testbed simulate realistic_exam --seed 1 --frames 2000 --out "$real"
fi
mkdir -p .devrun/side_realistic
"$ffmpeg" -y -loglevel error -framerate 2 -start_number 0 -i "$real/frames/%06d.png" -c:v libx264 -preset slow \
  -crf 35 -pix_fmt yuv420p .devrun/realistic.mp4
cp "$real/meta.json" "$real/sensors.csv" .devrun/side_realistic/
gzip -c "$real/rf.csv" > .devrun/side_realistic/rf.csv.gz
cp benchmarks/device/run_16core.sh .devrun/run.sh
ls .whl/plotly-*.whl >/dev/null 2>&1 || .venv/bin/python -m pip download -q --no-deps -d .whl plotly
du -sh .devrun .whl
mkdir -p .git/info
grep -qs "^.devrun" .git/info/exclude || printf '.devrun/\n.whl/\n' >> .git/info/exclude

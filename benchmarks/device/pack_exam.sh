#!/usr/bin/env bash
# Here: the 10,000-frame exam (exam scenario, seed 1) packed for a lent device machine into the ignored folders the
# device tool carries (64 MiB in all): .devrun/exam.mp4 (H.264, crf 30: ~36 MB), .devrun/side/ (meta.json,
# sensors.csv, rf.csv.gz), .devrun/run.sh (benchmarks/device/run_16core.sh), .whl/ (the plotly wheel: the device
# image lacks it). Then, on the device: `bash .devrun/run.sh` with carry [".devrun", ".whl"].
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
cp benchmarks/device/run_16core.sh .devrun/run.sh
ls .whl/plotly-*.whl >/dev/null 2>&1 || .venv/bin/python -m pip download -q --no-deps -d .whl plotly
du -sh .devrun .whl
mkdir -p .git/info
grep -qs "^.devrun" .git/info/exclude || printf '.devrun/\n.whl/\n' >> .git/info/exclude

#!/usr/bin/env bash
# Here: an exam packed for a lent device machine into the ignored folders the device tool carries (64 MiB in all),
# with .devrun/run.sh (benchmarks/device/run_16core.sh) and .whl/ (the plotly wheel: the device image lacks it).
#   bash benchmarks/device/pack_exam.sh [KEEP=/tmp/bb] [exam|realistic]
# exam (default): the 10,000-frame `exam` (seed 1) as .devrun/exam.mp4 (H.264, crf 30: ~36 MB) and .devrun/side/
# (meta.json, sensors.csv, rf.csv.gz). realistic: the realistic testbed's 2,000-frame `realistic_exam` (seed 1;
# bench_batch.py's --scenario realistic_exam naming) as .devrun/realistic.mp4 (crf 20: ~21 MB) and
# .devrun/side_realistic/. The two do not fit in one call: pack one, run, pack the other (each replaces the other's
# video). Heavier compression of the realistic look is no measurement of it (crf 35 halves fast mode's speed:
# docs/RESULTS.md, session 59). Then, on the device: `bash .devrun/run.sh` with carry [".devrun", ".whl"].
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
keep="${1:-/tmp/bb}"
which="${2:-exam}"
case "$which" in
  exam) seq="$keep/exam_1_10000"; n=10000; scen=exam; video=exam.mp4; side=side; crf=30 ;;  # render ~8-14 minutes
  realistic) seq="$keep/realistic_exam_1_2000"; n=2000; scen=realistic_exam; video=realistic.mp4; side=side_realistic
             crf=20 ;;  # render ~3 minutes
  *) echo "pack_exam.sh: pack 'exam' or 'realistic', not '$which'" >&2; exit 2 ;;
esac
if [ ! -d "$seq/frames" ]; then
  .venv/bin/testbed simulate "$scen" --seed 1 --frames "$n" --out "$seq"
fi
tools=/tmp/bodyslam-device-tools
[ -d "$tools/imageio_ffmpeg" ] || .venv/bin/python -m pip install -q --target "$tools" imageio-ffmpeg  # has libx264
ffmpeg="$(PYTHONPATH=$tools .venv/bin/python -c 'import imageio_ffmpeg; print(imageio_ffmpeg.get_ffmpeg_exe())')"
rm -rf .devrun/exam.mp4 .devrun/realistic.mp4 .devrun/side .devrun/side_realistic  # the other exam's too: 64 MiB
mkdir -p ".devrun/$side" .whl
"$ffmpeg" -y -loglevel error -framerate 2 -start_number 0 -i "$seq/frames/%06d.png" -c:v libx264 -preset slow \
  -crf "$crf" -pix_fmt yuv420p ".devrun/$video"
cp "$seq/meta.json" "$seq/sensors.csv" ".devrun/$side/"
gzip -c "$seq/rf.csv" > ".devrun/$side/rf.csv.gz"
cp benchmarks/device/run_16core.sh .devrun/run.sh
ls .whl/plotly-*.whl >/dev/null 2>&1 || .venv/bin/python -m pip download -q --no-deps -d .whl plotly
du -sh .devrun .whl
mkdir -p .git/info
grep -qs "^.devrun" .git/info/exclude || printf '.devrun/\n.whl/\n' >> .git/info/exclude

#!/usr/bin/env bash
# Device side of the 16-core table (docs/RESULTS.md, "Whole exams on 16 cores"): packed here by
# benchmarks/device/pack_exam.sh into .devrun/ (as .devrun/run.sh) and run there from the checkout:
#   bash .devrun/run.sh   (device tool, carry [".devrun", ".whl"], timeout_s 590; ~8 minutes with the 10,000-frame
#   exam, ~2.5 with the realistic one; BUDGET=S for a shorter timeout_s, JOBS_REAL=16,1,8,4,2 for the whole table)
# pack_exam.sh packs one of the two exams per call (both do not fit in 64 MiB); this runs what is packed, in order,
# each only while time is left (a lease is 15 minutes of device time, its start included): `exam` with RF 16 and 1
# jobs (issue 17's 10x), without RF 16 jobs; `realistic_exam` (2,000 frames) with RF 16 and 1 jobs, without RF 16;
# `exam` with RF 8 and 4 jobs, then 2. Every run's log line, the summaries and the outputs' checksums land in $OUT
# as they finish, so a run cut short still brings back the rest.
# Locally (a test of this script):
#   OUT=/tmp/x JOBS_FIRST=2 JOBS_FIRST_NORF= JOBS_REAL=2 JOBS_REAL_NORF= JOBS_MORE= JOBS_LAST= bash .devrun/run.sh
export PYTHONUNBUFFERED=1
T0=$(date +%s)
BUDGET=${BUDGET:-575}  # seconds this command may take (its timeout_s less a margin)
FIRST=${JOBS_FIRST-16,1}; FIRST_NORF=${JOBS_FIRST_NORF-16}; MORE=${JOBS_MORE-8,4}; LAST=${JOBS_LAST-2}
REAL=${JOBS_REAL-16,1}; REAL_NORF=${JOBS_REAL_NORF-16}
el() { echo $(( $(date +%s) - T0 )); }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
fi
export PYTHONPATH=$PWD:/tmp/site
nproc; lscpu | grep -E "Model name|^CPU\(s\)|Thread|Core|Socket|MHz" | tee $OUT/lscpu.txt
python3 setup.py build_ext --inplace > $OUT/build.log 2>&1
for m in fusion/_ekf_rss fusion/_block_tridiag vision/_tube_fit vision/_srm_merge; do
  if ! ls bodyslam/$m.*.so >/dev/null 2>&1; then
    gcc -O2 -ffp-contract=off -shared -fPIC -I"$(python3 -c 'import sysconfig; print(sysconfig.get_paths()["include"])')" \
      bodyslam/$m.c -o bodyslam/$m$(python3 -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))') -lm >> $OUT/build.log 2>&1
  fi
done
python3 -c "import bodyslam.fusion.ekf as e, bodyslam.fusion.refine as r, bodyslam.vision.motion as m; print('compiled ekf', e._ekf_c is not None, 'marginals', r._bt is not None, 'tube', m._tube_c is not None)"
if [ -f .devrun/exam.mp4 ] && [ ! -d /tmp/bb/exam_1_10000/frames ]; then
  python3 benchmarks/device/unpack_exam.py .devrun/exam.mp4 /tmp/bb/exam_1_10000 || exit 1
fi
[ -d /tmp/bb/exam_1_10000/frames ] || { echo "no exam packed: the realistic one alone"; FIRST=; MORE=; LAST=; }
if [ -f .devrun/realistic.mp4 ] && [ ! -d /tmp/bb/realistic_exam_1_2000/frames ]; then
  python3 benchmarks/device/unpack_exam.py .devrun/realistic.mp4 /tmp/bb/realistic_exam_1_2000 .devrun/side_realistic \
    || exit 1
fi
echo "setup done at +$(el) s"
bench() {  # bench NAME ARGS...: one bench_batch.py call, its log and json in $OUT, checksums of every output
  python3 benchmarks/bench_batch.py --seed 1 --keep /tmp/bb --jobs-only --json $OUT/$1.json \
    "${@:2}" 2>&1 | grep -v "^batch:" | tee -a $OUT/log.txt
  for d in /tmp/bb/out_fast_10000_jobs* /tmp/bb/realistic_exam_out_fast_2000_jobs*; do
    [ -f $d/summary.json ] || continue
    echo "$(basename $d) $(cat $d/*/motion.csv | md5sum | cut -c1-12) $(cat $d/*/trajectory.tum | md5sum | cut -c1-12)"
  done > $OUT/md5.txt
  echo "at +$(el) s" | tee -a $OUT/log.txt
}
[ -n "$FIRST" ] && bench a --frames 10000 --jobs-rf "$FIRST" ${FIRST_NORF:+--jobs "$FIRST_NORF"}
cp /tmp/bb/out_fast_10000_jobs_rf16/exam_1_10000/summary.json $OUT/exam_summary_rf16.json 2>/dev/null
[ -n "$REAL" ] && [ -d /tmp/bb/realistic_exam_1_2000/frames ] && [ $(el) -lt $(( BUDGET - 120 )) ] \
  && bench r --scenario realistic_exam --frames 2000 --jobs-rf "$REAL" ${REAL_NORF:+--jobs "$REAL_NORF"}
[ -n "$MORE" ] && [ $(el) -lt $(( BUDGET - 150 )) ] && bench b --frames 10000 --jobs-rf "$MORE"
[ -n "$LAST" ] && [ $(el) -lt $(( BUDGET - 170 )) ] && bench c --frames 10000 --jobs-rf "$LAST"
echo "end at +$(el) s"

#!/usr/bin/env bash
# Device side of the 16-core table (docs/RESULTS.md, "Whole exams on 16 cores"): packed here by
# benchmarks/device/pack_exam.sh into .devrun/ (as .devrun/run.sh) and run there from the checkout:
#   bash .devrun/run.sh   (device tool, carry [".devrun", ".whl"]; ~7 minutes: 16 jobs with RF, 1 job with RF,
#   16 jobs without, then 16 with RF again if time is left). Results land in $OUT.
export PYTHONUNBUFFERED=1
T0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
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
python3 benchmarks/device/unpack_exam.py .devrun/exam.mp4 /tmp/bb/exam_1_10000 || exit 1
echo "setup done at +$(( $(date +%s) - T0 )) s"
python3 benchmarks/bench_batch.py --frames 10000 --seed 1 --keep /tmp/bb --jobs-rf 16,1 --jobs 16 --jobs-only --json $OUT/a.json 2>&1 | grep -v "^batch:" | tee $OUT/log_a.txt
echo "at +$(( $(date +%s) - T0 )) s"
cp /tmp/bb/out_fast_10000_jobs_rf16/summary.json $OUT/summary_rf16.json 2>/dev/null
cp /tmp/bb/out_fast_10000_jobs_rf1/summary.json $OUT/summary_rf1.json 2>/dev/null
cp /tmp/bb/out_fast_10000_jobs_rf16/exam_1_10000/summary.json $OUT/exam_summary_rf16.json 2>/dev/null
E=$(( $(date +%s) - T0 )); echo "at +$E s"
[ $E -lt 420 ] && python3 benchmarks/bench_batch.py --frames 10000 --seed 1 --keep /tmp/bb --jobs-rf 16 --jobs-only --json $OUT/b.json 2>&1 | grep -v "^batch:" | tee $OUT/log_b.txt
echo "end at +$(( $(date +%s) - T0 )) s"

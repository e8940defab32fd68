#!/usr/bin/env bash
# Set up (idempotently) and run the main job on the embedded default sequence (data_samples/demo_seed0):
#   1. bodyslam check: read meta.json and stream every frame, reporting bad ones;
#   2. regenerate the sample from its scenario and seed and confirm it is reproduced exactly;
#   3. write a contact sheet of the sequence;
#   4. the pipeline: per-step motion from the frames (bodyslam motion), the dead-reckoned trajectory
#      (bodyslam track), matches drawn for one pair (bodyslam match), and the score against the testbed's truth
#      (testbed score-motion, Table 4.1); then Body-SLAM: the motion fused with the RF readings (bodyslam localize);
#   5. the same exam as a whole-exam batch job with a marked frame (bodyslam batch -> out/demo_batch/).
# Outputs go to out/ (ignored by git). As the pipeline grows (classification, fusion), this script runs it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
mkdir -p out
.venv/bin/bodyslam check data_samples/demo_seed0
.venv/bin/testbed simulate demo --seed 0 --out out/demo_seed0_regenerated --force
.venv/bin/python - <<'PY'
import numpy as np
from bodyslam.io import read_image
a, b = "data_samples/demo_seed0", "out/demo_seed0_regenerated"
for name in ("groundtruth.tum", "motion_truth.csv", "labels.csv"):
    assert open(f"{a}/{name}").read() == open(f"{b}/{name}").read(), f"{name} differs"
diff = max(int(np.abs(read_image(f"{a}/frames/{k:06d}.png").astype(int) - read_image(f"{b}/frames/{k:06d}.png")).max())
           for k in range(40))
print(f"regenerated data_samples/demo_seed0: ground truth identical, max frame difference {diff}/255")
PY
.venv/bin/testbed contact-sheet data_samples/demo_seed0 --out out/demo_seed0_contact.png
.venv/bin/bodyslam motion data_samples/demo_seed0 --out out/demo_motion.csv
.venv/bin/bodyslam track data_samples/demo_seed0 --out out/demo_trajectory.tum
.venv/bin/bodyslam match data_samples/demo_seed0/frames/000010.png data_samples/demo_seed0/frames/000011.png \
    --meta data_samples/demo_seed0 --out out/demo_match_10_11.png
.venv/bin/testbed score-motion data_samples/demo_seed0 out/demo_motion.csv --json out/demo_motion_score.json
.venv/bin/bodyslam localize data_samples/demo_seed0 --motion out/demo_motion.csv --out out/demo_localize --force
.venv/bin/bodyslam batch data_samples/demo_seed0 --out out/demo_batch --force --mark 20 --landmark 5

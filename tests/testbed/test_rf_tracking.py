"""RF tracking scenarios (papers 002/003): simulation files and evaluation reports, on short runs."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from testbed.rf_tracking import _world, truth_motion
from testbed.scenario import load_scenario


def test_truth_follows_waypoints_with_stops_inside_the_area():
    scn = load_scenario("ito2016", ["sequence.duration_s=300"])
    t, pos, wps = truth_motion(scn, np.random.default_rng(4))
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert len(t) == 3001 and (step == 0).mean() > 0.1  # it stops at waypoints (U(0, 20) s each)
    moving = step[step > 0] / 0.1
    # per-leg speeds |N(0.05, 0.0707)| cm/s: the mean moving speed lies between 0.03 and 0.15 cm/s
    assert 3e-4 < moving.mean() < 1.5e-3
    lo, hi, *_ = _world(scn, 4)
    assert np.all(pos >= lo) and np.all(pos <= hi)
    # every position lies on a leg between consecutive waypoints (within float error)
    assert all(min(np.linalg.norm(np.cross(b - a, p - a)) / max(np.linalg.norm(b - a), 1e-12)
                   for a, b in zip(wps[:-1], wps[1:])) < 1e-9 for p in pos[::97])


def test_simulate_writes_spec_files(tmp_path):
    out = tmp_path / "ito"
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "simulate", "ito2016", "--seed", "2", "--out", str(out),
                        "--set", "sequence.duration_s=5"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    with (out / "rf.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert set(rows[0]) == {"t", "sensor", "rss_dbm", "toa_s", "uwb_field_db"} and len(rows) == 51 * 8
    with (out / "sensors.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 8
    truth = json.loads((out / "truth.json").read_text())
    assert truth["eps_r"] == 34.25
    # TOA at a receiver: sqrt(eps) d / c within 5 sigma of the sampling error
    toa = float(rows[0]["toa_s"])
    assert 0 < toa < np.sqrt(34.25) * 0.6 / 299_792_458.0


@pytest.mark.parametrize("scenario", ["ito2016", "ito_heading"])
def test_evaluate_reports_each_algorithm_beside_the_paper(tmp_path, scenario):
    out = tmp_path / "ev"
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", scenario, "--seeds", "2", "--out", str(out),
                        "--jobs", "1", "--set", "sequence.duration_s=30", "--set", "filter.particles=3000"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_runs"] == 2 and rep["steps_per_run"] == 301
    for name, a in rep["algorithms"].items():
        assert {"rmse_mm", "rms_last_10pct_mm", "steps_per_s"} <= set(a)
        assert 0 < a["rms_last_10pct_mm"] < 60  # 30 s are enough to be within centimetres of the capsule
    if scenario == "ito2016":
        # TOA (3 mm per range) beats MICS RSSI (5.5 dB shadowing) on the same runs
        assert rep["algorithms"]["toa_pf_true_eps"]["rmse_mm"] < rep["algorithms"]["rssi_pf"]["rmse_mm"]
        assert "permittivity_rms_error_last_10pct" in rep
    else:
        assert {"waypoint_mean_error_cm", "simple_mean_error_cm"} <= set(rep["moving_distance"])
    assert "paper (mm)" in (out / "report.html").read_text()
    assert (out / "error_vs_time.png").stat().st_size > 1000

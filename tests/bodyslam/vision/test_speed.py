"""Capsule speed statistics and the fitted speed model (bodyslam.vision.speed): the dissertation's loop from
motion.csv to a speed model that drives the testbed."""

import json

import pytest

from bodyslam.io import read_image

from tests.bodyslam.vision.test_tracking import DEMO, run


def test_speed_statistics_drive_the_testbed(tmp_path):
    """motion.csv -> speed PDF/CDF + model file -> testbed simulate --speed-model (the thesis's loop)."""
    import shutil

    mcsv = tmp_path / "motion.csv"
    shutil.copy(DEMO / "motion_truth.csv", tmp_path / "truth.csv")
    # a motion.csv from the truth (the speed statistics code only reads the SPEC columns)
    lines = (tmp_path / "truth.csv").read_text().splitlines()
    out = ["frame,t,distance_m,roll_rad,pitch_rad,yaw_rad,tilt_rad,n_matches,status"]
    out += [",".join(ln.split(",")[:7] + ["100", "ok"]) for ln in lines[1:]]
    mcsv.write_text("\n".join(out) + "\n")
    p = run("bodyslam.cli", "speed-stats", str(mcsv), "--out", str(tmp_path / "speed"))
    assert p.returncode == 0, p.stderr
    model = json.loads((tmp_path / "speed" / "speed_model.json").read_text())
    assert model["motion"]["mean_step_m"] == pytest.approx(0.0041, rel=0.01)
    assert abs(sum(model["motion"]["phase_probs"]) - 1) < 1e-9
    for png in ("speed_pdf.png", "speed_cdf.png"):
        assert read_image(tmp_path / "speed" / png).shape == (420, 640, 3)
    # a second run into the same (now non-empty) directory is refused in one line, then allowed with --force
    p = run("bodyslam.cli", "speed-stats", str(mcsv), "--out", str(tmp_path / "speed"))
    assert p.returncode == 1 and "not empty" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert run("bodyslam.cli", "speed-stats", str(mcsv), "--out", str(tmp_path / "speed"), "--force").returncode == 0
    # the model drives a new sequence: its mean step, roll and tilt are the model's
    p = run("testbed.cli", "simulate", "demo", "--seed", "3", "--frames", "12", "--out", str(tmp_path / "sim"),
            "--speed-model", str(tmp_path / "speed" / "speed_model.json"))
    assert p.returncode == 0, p.stderr
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    assert truth["mean_step_cm"] == pytest.approx(model["motion"]["mean_step_m"] * 100, rel=0.02)
    assert truth["mean_roll_deg"] == pytest.approx(model["motion"]["mean_roll_deg"], rel=0.05)

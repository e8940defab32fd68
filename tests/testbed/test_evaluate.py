"""`testbed evaluate`: one short run end to end (render, motion from frames, every algorithm, report, plots)."""

import json
import subprocess
import sys


def test_evaluate_writes_a_report_with_units_and_plots(tmp_path):
    out = tmp_path / "eval"
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", "demo", "--seeds", "1", "--frames", "20",
                        "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_runs"] == 1 and rep["seeds"] == [0] and rep["frames_per_run"] == 20
    for alg in ("rf_ml", "rf_nls", "dead_reckoning", "thesis_kf", "ekf_fixes", "ekf_rss", "ekf_rss_rts"):
        a = rep["algorithms"][alg]
        assert set(a) == {"mean_error_cm", "rmse_cm", "median_error_cm", "p90_error_cm", "max_error_cm",
                          "rmse_over_sqrt_pcrb"}
        assert 0 < a["mean_error_cm"] < 50
    assert rep["algorithms"]["ekf_rss_rts"]["mean_error_cm"] < rep["algorithms"]["rf_ml"]["mean_error_cm"]
    assert "mae_distance_cm" in rep["table_4_1"]
    for png in ("trajectories_xz.png", "trajectories_xy.png", "error_vs_step.png", "error_histogram.png",
                "error_cdf.png"):
        assert (out / png).stat().st_size > 1000
    assert not (out / "sequences" / "seed_0" / "frames").exists()  # frames are not kept by default


def test_seeds_in_parallel_give_the_same_report_and_an_html_page(tmp_path):
    reps = {}
    for jobs in ("1", "2"):
        out = tmp_path / f"eval_{jobs}"
        p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", "demo", "--seeds", "3-4", "--frames", "12",
                            "--out", str(out), "--jobs", jobs], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        reps[jobs] = json.loads((out / "report.json").read_text())
        page = (out / "report.html").read_text()
        assert "RMSE / sqrt(PCRB)" in page and 'src="error_cdf.png"' in page and "seeds 3-4" in page
    assert reps["2"]["seconds"]["jobs"] == 2 and reps["1"]["seeds"] == reps["2"]["seeds"] == [3, 4]
    # each seed is computed the same way whatever the parallelism: identical figures
    assert reps["1"]["algorithms"] == reps["2"]["algorithms"]

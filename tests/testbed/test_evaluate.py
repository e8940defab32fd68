"""`testbed evaluate`: one short run end to end (render, motion from frames, every algorithm, report, plots)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import pytest


def test_evaluate_writes_a_report_with_units_and_plots(tmp_path):
    out = tmp_path / "eval"
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", "demo", "--seeds", "1", "--frames", "20",
                        "--out", str(out), "--keep-frames"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_runs"] == 1 and rep["seeds"] == [0] and rep["frames_per_run"] == 20
    for alg in ("rf_ml", "rf_nls", "dead_reckoning", "thesis_kf", "ekf_fixes", "ekf_rss", "ekf_rss_rts", "ekf_rss_bias",
                "ekf_rss_bias_rts"):
        a = rep["algorithms"][alg]
        assert set(a) == {"mean_error_cm", "rmse_cm", "median_error_cm", "p90_error_cm", "max_error_cm",
                          "rmse_over_sqrt_pcrb"}
        assert 0 < a["mean_error_cm"] < 50
    assert rep["algorithms"]["ekf_rss_rts"]["mean_error_cm"] < rep["algorithms"]["rf_ml"]["mean_error_cm"]
    t41 = rep["table_4_1"]
    # the scale-aligned error (each run's best factor, testbed.score) is never above the raw one
    assert t41["mae_distance_scale_aligned_cm"] <= t41["mae_distance_cm"] and t41["distance_scale"] > 0
    # the demo tells its radius exactly: no lumen scale measured (bodyslam.vision.lumen_scale), said per run too
    assert rep["lumen_scale"] == {"runs": 1, "runs_applied": 0, "factor_mean": None, "factor_min": None,
                                  "factor_max": None, "factor_sd_rel_mean": None, "samples_mean": 0.0,
                                  "steps_chained_mean": 0.0}
    assert rep["per_seed"][0]["lumen_scale"]["factor"] == 1.0
    assert rep["per_seed"][0]["lumen_scale"]["factor_sd_rel"] is None  # nothing applied: no factor's 1-sigma
    assert rep["per_seed"][0]["lumen_scale"]["steps_tried"] == 0  # no ring fitted where the radius is told
    assert rep["per_seed"][0]["lumen_scale"]["steps_chained"] == 0  # nor a scale chain (bodyslam.vision.scale_chain)
    for alg in ("ekf_rss", "ekf_rss_causal", "ekf_rss_rts", "ekf_rss_bias", "ekf_rss_bias_rts"):  # per filter:
        # honest uncertainty and orientation
        c = rep["consistency"][alg]
        assert c["mean_nees"] > 0 and 0 <= c["inside_68pct_ellipsoid"] <= 1 and 0 <= c["axis_inside_1sigma"] <= 1
        assert 0 <= rep["orientation_error_deg"][alg]["mean"] <= rep["orientation_error_deg"][alg]["p90"] <= 180
        # one run: its own figures are the pooled ones (to the 3-4 decimals the per-run entry keeps)
        mine = rep["per_seed"][0]["consistency"][alg]
        assert abs(mine["inside_68pct_ellipsoid"] - c["inside_68pct_ellipsoid"]) < 1e-4
        assert abs(mine["mean_nees"] - c["mean_nees"]) < 1e-3
        # the chi-square test over one run: chi2(3)'s 2.5% and 97.5% points, and every frame in one of three places
        b = c["nees_chi2"]
        assert b["runs"] == 1 and b["band"] == [0.216, 9.348]
        assert b["frames_inside"] + b["frames_below"] + b["frames_above"] == pytest.approx(1.0)
        o = rep["per_seed"][0]["orientation_error_deg"][alg]  # rounded to 0.01 deg
        assert abs(o["mean"] - rep["orientation_error_deg"][alg]["mean"]) < 0.01
    # re-scoring the kept sequences without rendering or motion gives the same figures
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", "demo", "--seeds", "1", "--frames", "20",
                        "--out", str(out), "--reuse"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    # the closing line tells how honest the stated 1-sigma is, with the figures report.json holds
    c = rep["consistency"]["ekf_rss_rts"]
    assert (f"smoothed {c['inside_68pct_ellipsoid']:.0%} inside its 68% ellipsoid, "
            f"{c['nees_chi2']['frames_inside']:.0%} of frames in the NEES's 95% band") in p.stdout + p.stderr
    again = json.loads((out / "report.json").read_text())
    assert again["algorithms"] == rep["algorithms"] and again["seconds"]["render_total"] < 1.0
    for png in ("trajectory.png", "error_vs_time.png", "error_histogram.png", "error_cdf.png"):
        assert (out / png).stat().st_size > 1000
    # every algorithm's trajectory as TUM beside the truth (evo reads them), orientation where it has one
    from bodyslam.io import read_tum

    tdir = out / "sequences" / "seed_0" / "trajectories"
    t, p, _ = read_tum(tdir / "ekf_rss_rts.tum")
    assert len(t) == 20 and sorted(f.stem for f in tdir.glob("*.tum")) == sorted(rep["algorithms"])
    assert "orientation not estimated" in (tdir / "rf_ml.tum").read_text().splitlines()[0]
    # the kept frames survive a re-scoring that did not render them (it used to delete them)
    assert len(list((out / "sequences" / "seed_0" / "frames").iterdir())) == 20


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
        assert 'class="view3d"' in page and "orientation error mean (deg)" in page
        assert "Plotly.newPlot" in page and page.index("plotly.js v") < page.index('class="view3d"')  # its script
        assert all((out / f).stat().st_size > 10000 for f in ("trajectory.png", "error_vs_time.png", "error_cdf.png"))
    assert reps["2"]["seconds"]["jobs"] == 2 and reps["1"]["seeds"] == reps["2"]["seeds"] == [3, 4]
    assert not (tmp_path / "eval_1" / "sequences" / "seed_3" / "frames").exists()  # not kept by default
    # each seed is computed the same way whatever the parallelism: identical figures
    assert reps["1"]["algorithms"] == reps["2"]["algorithms"]


def test_the_runs_lumen_scales_summed_and_said():
    """Where the lumen scale was applied on some runs: the factor over those runs only, the page's line with it;
    where no run measured a ratio, no line."""
    from testbed.evaluate import _lumen_html, _lumen_summary

    sc = _lumen_summary([{"factor": 0.9, "samples": 30, "steps_chained": 100},
                         {"factor": 0.8, "samples": 40, "steps_chained": 80}, {"factor": 1.0, "samples": 20}])
    assert sc["runs"] == 3 and sc["runs_applied"] == 2 and sc["samples_mean"] == pytest.approx(30.0)
    assert (sc["factor_mean"], sc["factor_min"], sc["factor_max"]) == (pytest.approx(0.85), 0.8, 0.9)
    assert sc["steps_chained_mean"] == pytest.approx(60.0)  # a run without the figure (an older one) counts 0
    line = _lumen_html(sc, 1.04)
    assert "applied on 2 of 3 runs" in line and "x0.850 on average (0.800 to 0.900)" in line and "1.040" in line
    assert "60 steps a run had their scale tied" in line
    assert "tied" not in _lumen_html({**sc, "steps_chained_mean": 0.0}, 1.04)
    assert sc["factor_sd_rel_mean"] is None and "stated 1-sigma" not in line  # runs from before session 63
    with_sd = _lumen_summary([{"factor": 0.9, "samples": 30, "factor_sd_rel": 0.07},
                              {"factor": 0.8, "samples": 40, "factor_sd_rel": 0.09}, {"factor": 1.0, "samples": 20}])
    assert with_sd["factor_sd_rel_mean"] == pytest.approx(0.08)
    assert "(0.800 to 0.900; stated 1-sigma 8% on average)" in _lumen_html(with_sd, 1.04)
    assert _lumen_html(_lumen_summary([{"factor": 1.0, "samples": 0}]), 1.0) == "" and _lumen_html(None, 1.0) == ""


def test_consistency_of_an_honest_and_an_overconfident_estimate():
    """NEES ~3 and 68% inside 1-sigma for errors drawn from the stated covariance; far off when the stated
    covariance is 4x too small (the statistics' standard errors at 20,000 frames are below 0.03 and 0.01)."""
    import numpy as np

    from testbed.evaluate import consistency

    rng = np.random.default_rng(0)
    n = 20000
    A = rng.normal(size=(n, 3, 3)) * 0.01
    cov = A @ A.transpose(0, 2, 1) + np.eye(3) * 1e-6
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    c = consistency(e, cov, np.zeros((n, 3)))
    assert abs(c["nees"].mean() - 3) < 0.1 and abs(c["inside_68"].mean() - 0.683) < 0.02
    assert abs(c["axis_inside_1sigma"].mean() - 0.683) < 0.02
    over = consistency(e, cov / 4, np.zeros((n, 3)))
    assert over["nees"].mean() > 10 and over["inside_68"].mean() < 0.3


def test_the_nees_chi_square_band_holds_honest_runs_and_flags_the_others():
    """Bar-Shalom's test over 20 runs: the band is chi2(60)'s 2.5% and 97.5% points over 20; NEES drawn honestly
    (chi-square with 3 degrees of freedom) put the runs' mean inside it on ~95% of 400 frames (measured 0.975 with
    this seed; 0.9 allows the test's own spread), twice too large above it on nearly all, half below it."""
    from testbed.evaluate import nees_band

    rng = np.random.default_rng(0)
    runs = [(rng.normal(size=(400, 3)) ** 2).sum(axis=1) for _ in range(20)]
    b = nees_band(runs)
    assert b["runs"] == 20 and b["band"] == [2.024, 4.165]
    assert b["frames_inside"] > 0.9
    assert nees_band([2 * r for r in runs])["frames_above"] > 0.9
    assert nees_band([0.5 * r for r in runs])["frames_below"] > 0.9
    runs[3] = runs[3][:300]  # a shorter run: the frames every run has
    runs[5][10] = np.nan  # a frame some run lacks is left out
    assert nees_band(runs)["frames_inside"] > 0.9


def test_frames_without_a_position_are_counted_not_averaged():
    import numpy as np

    from testbed.evaluate import _stats

    e = np.array([0.01, np.nan, 0.03, 0.02])  # m; frame 1 had no RF fix
    s = _stats(e, np.full(4, 1e-4))
    assert s["mean_error_cm"] == 2.0 and s["frames_without_position"] == 1 and s["max_error_cm"] == 3.0
    assert "frames_without_position" not in _stats(e[[0, 2, 3]], np.full(3, 1e-4))


def test_per_step_sigma_coverage():
    import numpy as np

    from testbed.score import _within_sigma

    got = _within_sigma(np.array([0.1, 0.5, 2.0, 3.0]), np.array([1.0, 1.0, 1.0, np.nan]))
    assert got == {"distance_within_1sigma": 2 / 3, "distance_within_2sigma": 1.0}  # the NaN-sigma step left out
    assert _within_sigma(np.array([0.1]), np.array([np.nan])) == {}


def test_orientation_error_splits_into_the_optical_axis_and_the_roll_about_it():
    """A 30-degree roll about the optical axis moves no axis; a 20-degree turn about camera x moves the axis by
    20 and rolls nothing; a composition of both shows both (within the swing-twist split's exactness: 1e-9)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from testbed.evaluate import orientation_errors_deg

    truth = Rotation.from_euler("xyz", [[10, -40, 70], [0, 0, 0]], degrees=True)
    roll = truth * Rotation.from_rotvec([0, 0, np.radians(30)])
    tilt = truth * Rotation.from_rotvec([np.radians(20), 0, 0])
    both = truth * Rotation.from_rotvec([np.radians(20), 0, 0]) * Rotation.from_rotvec([0, 0, np.radians(30)])
    np.testing.assert_allclose(orientation_errors_deg(roll, truth), [[30, 30], [0, 0], [30, 30]], atol=1e-9)
    np.testing.assert_allclose(orientation_errors_deg(tilt, truth), [[20, 20], [20, 20], [0, 0]], atol=1e-9)
    e = orientation_errors_deg(both, truth)
    np.testing.assert_allclose(e[1:], [[20, 20], [30, 30]], atol=1e-9)
    assert (e[0] > 30).all()


def test_rotation_steps_are_summed_over_seeds_by_their_count():
    """The seeds' rotation-step blocks become one, weighted by each seed's step count (a seed with one step
    must not count as much as one with thirty), and the report page states it; no rotation steps, no line."""
    from testbed.evaluate import _rotation_html, _rotation_summary

    a = {"n_steps_scored": 30, "mean_true_roll_deg": 8.0, "mae_roll_deg": 2.0, "rms_roll_error_deg": 3.0,
         "mean_true_tilt_deg": 5.0, "mae_tilt_deg": 2.0}
    b = {"n_steps_scored": 1, "mean_true_roll_deg": 8.0, "mae_roll_deg": 33.0, "rms_roll_error_deg": 33.0,
         "mean_true_tilt_deg": 5.0, "mae_tilt_deg": 2.0}
    rot = _rotation_summary([a, b, {"n_steps_scored": 0}])
    assert rot["n_steps_scored"] == 31
    assert rot["mae_roll_deg"] == pytest.approx((30 * 2.0 + 33.0) / 31)
    assert rot["rms_roll_error_deg"] == pytest.approx(((30 * 9.0 + 33.0**2) / 31) ** 0.5)
    assert "31, roll error 3.00 deg mean" in _rotation_html(rot)
    assert _rotation_summary([]) == {"n_steps_scored": 0} and _rotation_html({"n_steps_scored": 0}) == ""


def test_the_true_channel_changes_the_bound_and_nothing_the_pipeline_does(tmp_path):
    """``evaluate_sequence`` with the scenario's real channel: the bounds grow (less information) while every
    estimate stays the same -- the channel is used for scoring only, the pipeline is never told."""
    import shutil

    from bodyslam.io import read_tum, write_motion_csv
    from bodyslam.steps import StepMotion
    from testbed.evaluate import evaluate_sequence
    from testbed.rf import ChannelModel

    demo = Path(__file__).resolve().parents[2] / "data_samples" / "demo_seed0"
    d = tmp_path / "seq"
    d.mkdir()
    for name in ("meta.json", "rf.csv", "sensors.csv", "groundtruth.tum", "motion_truth.csv"):
        shutil.copy(demo / name, d / name)
    t, gt, grot = read_tum(d / "groundtruth.tum")
    steps = []
    for k in range(1, len(gt)):  # the true steps, as a perfect vision would give them
        R = (grot[k - 1].inv() * grot[k]).as_matrix()
        tc = grot[k - 1].inv().apply(gt[k] - gt[k - 1])
        steps.append(StepMotion(float(np.linalg.norm(tc)), 0.0, 0.0, 0.0, 0.0, 100, "ok", R, tc, 1e-4, 1e-3))
    write_motion_csv(d / "motion.csv", range(1, len(gt)), t[1:], steps)
    ideal = evaluate_sequence(d)
    real = evaluate_sequence(d, ChannelModel(shadowing_corr_m=0.03, pl0_sd_db=2.0, alpha_sd=0.3))
    for a in ideal["estimates"]:
        assert np.array_equal(ideal["estimates"][a], real["estimates"][a], equal_nan=True)
    assert np.all(real["pcrb_m2"] > ideal["pcrb_m2"])
    assert np.all(real["smoothing_bound_m2"] > ideal["smoothing_bound_m2"])


def test_orientation_consistency_takes_the_error_in_the_filters_camera_frame():
    """The orientation's NEES in the EKF's error convention (R_true = R_est Exp(e), e in the camera frame): with a
    covariance tight about camera x (0.01 rad) and loose about y and z (0.5 rad), 0.1 rad about camera x is far
    outside (NEES 100), the same turn about the world's x -- camera z here, the camera turned 90 deg about y -- is
    inside (0.04); and 1-sigma turns along each loose axis give NEES 1."""
    from testbed.evaluate import orientation_consistency

    truth = Rotation.from_rotvec([[0.0, np.pi / 2, 0.0]] * 4)
    cov = np.repeat(np.diag([0.01**2, 0.5**2, 0.5**2])[None], 4, axis=0)
    camera_x = truth * Rotation.from_rotvec([-0.1, 0.0, 0.0])  # R_est = R_true Exp(-e): e = 0.1 about camera x
    world_x = Rotation.from_rotvec([-0.1, 0.0, 0.0]) * truth
    loose = truth * Rotation.from_rotvec([[0.0, -0.5, 0.0], [0.0, 0.0, 0.5], [0.0, 0.3, 0.4], [0.0, 0.0, 0.0]])
    got = {name: orientation_consistency(est, cov, truth) for name, est in
           (("camera_x", camera_x), ("world_x", world_x), ("loose", loose))}
    assert np.allclose(got["camera_x"]["orientation_nees"], 100.0) and not got["camera_x"]["orientation_inside_68"].any()
    assert np.allclose(got["world_x"]["orientation_nees"], 0.04) and got["world_x"]["orientation_inside_68"].all()
    assert np.allclose(got["loose"]["orientation_nees"], [1.0, 1.0, 1.0, 0.0])


def test_steps_beside_the_wall_are_summed_over_seeds_by_their_count():
    """The seeds' beside-the-wall blocks become one, step-weighted, with their share of the measured steps; the
    report page states it, and says nothing where no step was fitted beside the wall."""
    from testbed.evaluate import _beside_wall_html, _beside_wall_summary

    a = {"n_steps_scored": 30, "mae_distance_cm": 0.08, "mae_roll_deg": 0.5, "mae_tilt_deg": 1.5,
         "distance_within_1sigma": 0.7}
    b = {"n_steps_scored": 10, "mae_distance_cm": 0.12, "mae_roll_deg": 0.3, "mae_tilt_deg": 2.5,
         "distance_within_1sigma": 0.9}
    bw = _beside_wall_summary([a, b, {"n_steps_scored": 0}], 160)
    assert bw["n_steps_scored"] == 40 and bw["share_of_measured"] == pytest.approx(0.25)
    assert bw["mae_distance_cm"] == pytest.approx((30 * 0.08 + 10 * 0.12) / 40)
    assert bw["distance_within_1sigma"] == pytest.approx(0.75) and "rotation_within_68pct" not in bw
    assert "40 (25% of the measured), distance error 0.0900 cm" in _beside_wall_html(bw)
    assert _beside_wall_html(_beside_wall_summary([], 100)) == ""


def test_seeds_as_a_count_a_range_or_a_list_and_a_count_said(capsys):
    """``--seeds``: N counts seeds 0..N-1 (so ``--seeds 700`` is 700 runs, which the CLI says before any work), A-B
    includes both ends, a,b,c lists them; a set with no seed is refused."""
    from bodyslam.errors import ConfigError
    from testbed.cli import _seeds_said, parse_seeds

    assert parse_seeds("3") == [0, 1, 2] and parse_seeds("700-702") == [700, 701, 702]
    assert parse_seeds("5,9") == [5, 9] and parse_seeds("7-7") == [7]
    for bad in ("0", "5-3", "x", "1-2-3"):
        with pytest.raises(ConfigError, match="--seeds"):
            parse_seeds(bad)
    assert _seeds_said("700", parse_seeds("700"))[-1] == 699
    assert "--seeds 700: 700 runs, seeds 0-699 (one seed alone: --seeds 700-700)" in capsys.readouterr().out
    _seeds_said("700-709", parse_seeds("700-709"))
    _seeds_said("1", parse_seeds("1"))
    assert capsys.readouterr().out == ""  # a range, or a count of one, says nothing more


def test_reuse_with_no_earlier_run_is_refused_before_any_work(tmp_path):
    """``--reuse`` scores the seeds of an earlier run again; where ``--out`` holds none of them it says so and
    renders nothing (rendering every seed is not what was asked), exit 1."""
    out = tmp_path / "eval"
    out.mkdir()
    (out / "notes.txt").write_text("not a run")
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "evaluate", "demo", "--seeds", "700-702", "--frames",
                        "20", "--out", str(out), "--reuse"], capture_output=True, text=True)
    assert p.returncode == 1
    assert "--reuse" in p.stderr and "seed(s) 700-702" in p.stderr and "without --reuse" in p.stderr
    assert sorted(x.name for x in out.iterdir()) == ["notes.txt"]  # nothing rendered, nothing written

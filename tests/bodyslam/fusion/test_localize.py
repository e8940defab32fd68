"""bodyslam.fusion.localize as a whole: what it gives does not depend on how its stages split the frames; and
`bodyslam localize` on the demo sequence."""

import numpy as np
import pytest

from bodyslam.io import read_tum

from tests.bodyslam.fusion import test_body_slam
from tests.bodyslam.fusion.test_body_slam import DEMO

demo = test_body_slam.demo  # the demo's true steps with noise, and its RF (a fixture of test_body_slam)


def _localize(demo, radius_sd_rel):
    from bodyslam.fusion.localize import RfInput, localize
    from bodyslam.io import read_json

    steps, *_ = demo
    rf = RfInput.read(DEMO / "rf.csv", DEMO / "sensors.csv", read_json(DEMO / "meta.json")["rf"]["pathloss"])
    return localize(steps, np.arange(len(steps) + 1) / 2.0, rf, 2.0, radius_sd_rel=radius_sd_rel)


@pytest.mark.parametrize("radius_sd_rel, block", [(0.0, 7), (0.1, 7), (0.0, 10)])  # 0.1: the scale state
def test_the_output_is_the_same_whatever_the_block_sizes(demo, monkeypatch, radius_sd_rel, block):
    # The stages whose memory would grow with the exam work in blocks of frames (issue 17: memory flat in exam
    # length): the compiled filter's record, the RTS gains, the readings' normalised residuals and the online
    # correlation factor. Each frame's numbers are its own, so blocks of 7 frames over the demo's 41 (the last
    # block short, a block boundary inside the start's search window), or of 10 (the last block one frame; the
    # 40 gains exactly four blocks) must give the bytes of one block.
    # (The whole-exam solve's blocks are held to the same in test_refine.py: its cost sums blocks in block order.)
    import bodyslam.fusion.body_slam as body_slam
    import bodyslam.fusion.channel as channel
    import bodyslam.fusion.ekf as ekf

    whole = _localize(demo, radius_sd_rel)
    for mod, name in ((ekf, "COMPILED_BLOCK_FRAMES"), (body_slam, "GAIN_BLOCK_FRAMES"),
                      (channel, "RESIDUAL_BLOCK_FRAMES")):
        monkeypatch.setattr(mod, name, block)
    blocks = _localize(demo, radius_sd_rel)
    for run in ("filtered", "rts", "smoothed"):
        a, b = getattr(whole, run), getattr(blocks, run)
        assert np.array_equal(a.positions_w_m, b.positions_w_m), run
        assert np.array_equal(a.rotations_w_c.as_quat(), b.rotations_w_c.as_quat()), run
        assert np.array_equal(a.cov, b.cov), run
    assert np.array_equal(whole.kappa_online, blocks.kappa_online)
    assert np.array_equal(whole.kappa_smoothed, blocks.kappa_smoothed)
    assert np.array_equal(whole.channel.rho, blocks.channel.rho) and whole.channel.kappa == blocks.channel.kappa
    # (the demo's channel is ideal, its factor 1 throughout: the test below holds the blocks to a correlated one)


def test_the_correlation_factors_are_the_same_in_blocks(monkeypatch):
    # normalised_residuals and causal_inflation frame by frame in blocks against at once, on residuals that are
    # correlated (so the factor is above 1 and varies from frame to frame) with missing readings.
    import bodyslam.fusion.channel as channel
    from bodyslam.fusion.rf import PathLossModel
    from testbed.rf import SensorLayout

    rng = np.random.default_rng(3)
    n, layout, pl = 500, SensorLayout.thesis_grids(), PathLossModel()
    m = len(layout.names)
    p = np.cumsum(rng.normal(0, 0.002, (n, 3)), axis=0)
    rss = -60.0 + np.cumsum(rng.normal(0, 1.0, (n, m)), axis=0) * 0.3 + rng.normal(0, 3, (n, m))
    rss[rng.random((n, m)) < 0.05] = np.nan
    memory = rng.uniform(0.5, 0.99, n)
    z = channel.normalised_residuals(rss, p, layout.positions_w_m, layout.normals_w, pl)
    k_mem, k_all = channel.causal_inflation(z, memory=memory), channel.causal_inflation(z)
    assert k_mem.max() > 1.5 and np.ptp(k_all) > 0.5  # a factor that varies: the blocks have something to get wrong
    monkeypatch.setattr(channel, "RESIDUAL_BLOCK_FRAMES", 37)
    z37 = channel.normalised_residuals(rss, p, layout.positions_w_m, layout.normals_w, pl)
    assert np.array_equal(z, z37, equal_nan=True)
    assert np.array_equal(k_mem, channel.causal_inflation(z, memory=memory))
    assert np.array_equal(k_all, channel.causal_inflation(z))
    corr = channel.residual_correlation(z)
    k_37 = channel.smoother_inflation(corr, memory)
    monkeypatch.setattr(channel, "RESIDUAL_BLOCK_FRAMES", 10**9)  # one block
    k_one = channel.smoother_inflation(corr, memory)
    assert np.array_equal(k_37, k_one) and k_one.max() > 1.5
    # the whole run's lag sums are carried from block to block: the same sums as over the frames at once
    one = channel.residual_correlation(z)
    assert np.array_equal(corr.rho, one.rho) and np.array_equal(corr.n_pairs, one.n_pairs)
    assert corr.kappa == one.kappa > 1.5 and corr.n_lags == one.n_lags
    ok, z0 = np.isfinite(z), np.nan_to_num(z)  # and they are the pairs at each lag, reaching across the blocks
    for lag in (1, 30):
        pairs = ok[lag:] & ok[:-lag]
        assert corr.n_pairs[lag - 1] == pairs.sum()
        rho = np.sum(z0[lag:] * z0[:-lag] * pairs) / pairs.sum() / (np.sum(z0**2) / ok.sum())
        assert np.isclose(corr.rho[lag - 1], rho, rtol=1e-12)
    assert np.array_equal(k_mem, channel.causal_inflation(z, memory=memory))


def test_the_filters_passes_are_released_after_the_smoother(demo):
    # The filter's per-frame priors, posteriors and F (~1 kB a frame) serve the smoother and the factors' memory
    # only: localize releases them once those have run, instead of holding them through the whole-exam solve and
    # the outputs (issue 17). A released run says so where the passes are asked for again.
    from bodyslam.fusion.body_slam import rts_smooth
    from bodyslam.fusion.channel import filter_memory

    loc = _localize(demo, 0.0)
    for run in (loc.filtered, loc.rts, loc.smoothed):
        assert run.passes.is_released and run.passes.prior_P is None and run.passes.F is None
    with pytest.raises(ValueError, match="released"):
        rts_smooth(loc.filtered)
    with pytest.raises(ValueError, match="released"):
        filter_memory(loc.filtered)


def test_localize_cli_on_the_demo(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "loc"
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "localize", str(DEMO), "--out", str(out), "--jobs", "1"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    for f in ("trajectory.tum", "trajectory_filter.tum", "uncertainty.csv", "rf_fixes.csv", "motion.csv",
              "trajectory.png", "path.png", "report.html"):
        assert (out / f).exists(), f
    _, est, _ = read_tum(out / "trajectory.tum")
    _, gt, _ = read_tum(DEMO / "groundtruth.tum")
    fixes = np.loadtxt(out / "rf_fixes.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3))
    e_fused = np.linalg.norm(est - gt, axis=1).mean()
    e_rf = np.linalg.norm(fixes - gt, axis=1).mean()
    # measured on the demo: RF-only ~5 cm; fused well under half of it (the demo's distances are ~5% short)
    assert e_fused < 0.5 * e_rf, (e_fused, e_rf)
    # refusing to overwrite without --force
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "localize", str(DEMO), "--out", str(out)],
                       capture_output=True, text=True)
    assert p.returncode == 1 and "--force" in p.stderr
    # given the steps (--motion), a sequence without its frames: the same fusion from meta.json and the RF files
    import shutil

    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("meta.json", "rf.csv", "sensors.csv"):
        shutil.copy(DEMO / name, bare / name)
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "localize", str(bare), "--motion",
                        str(out / "motion.csv"), "--out", str(tmp_path / "loc2")], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    _, est2, _ = read_tum(tmp_path / "loc2" / "trajectory.tum")
    assert np.abs(est2 - est).max() < 1e-6  # motion.csv's written digits: the same trajectory to 1 um
    # --no-refine: the smoother alone (measured on the demo: 1.09 cm mean error against 1.01 refined)
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "localize", str(bare), "--motion",
                        str(out / "motion.csv"), "--out", str(tmp_path / "loc3"), "--no-refine"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    _, est3, _ = read_tum(tmp_path / "loc3" / "trajectory.tum")
    assert np.abs(est3 - est).max() > 1e-4


def test_uncertainty_csv_keeps_the_whole_position_covariance(tmp_path):
    """The per-axis 1-sigma and the three correlation coefficients rebuild each frame's 3x3 position covariance to
    the CSV's 9 digits; an axis without spread (a localizer that states none) leaves its correlations empty."""
    import csv

    from bodyslam.fusion.localize import UNCERTAINTY_COLUMNS, write_uncertainty

    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 3, 3)) * 0.01
    cov = a @ np.transpose(a, (0, 2, 1)) + np.eye(3) * 1e-6
    cov[4] = np.diag([1e-4, 0.0, 4e-4])
    write_uncertainty(tmp_path / "u.csv", np.arange(5), np.arange(5) * 0.5, cov)
    rows = list(csv.DictReader(open(tmp_path / "u.csv", newline="")))
    assert list(rows[0]) == UNCERTAINTY_COLUMNS
    for k, r in enumerate(rows[:4]):
        sd = np.array([float(r[c]) for c in ("sd_x_m", "sd_y_m", "sd_z_m")])
        c = np.eye(3)
        c[0, 1] = c[1, 0] = float(r["corr_xy"])
        c[0, 2] = c[2, 0] = float(r["corr_xz"])
        c[1, 2] = c[2, 1] = float(r["corr_yz"])
        assert np.allclose(c * np.outer(sd, sd), cov[k], rtol=1e-7, atol=1e-15)
        assert abs(float(r["corr_xy"])) > 0.01  # these covariances do correlate their axes
    assert rows[4]["corr_xy"] == "" and rows[4]["corr_yz"] == "" and float(rows[4]["corr_xz"]) == 0.0


def test_rf_that_places_nothing_says_why(demo):
    # "RF not usable: 0 frame(s) with an RF fix" named no reason; it now counts the frames by what stopped them
    from dataclasses import replace

    from bodyslam.errors import InputError
    from bodyslam.fusion.localize import RfInput, localize
    from bodyslam.io import read_json

    steps, *_ = demo
    rf = RfInput.read(DEMO / "rf.csv", DEMO / "sensors.csv", read_json(DEMO / "meta.json")["rf"]["pathloss"])
    stamps = np.arange(len(steps) + 1) / 2.0
    late = replace(rf, stamps_s=rf.stamps_s + 1e4)  # readings that are not in time with the frames
    with pytest.raises(InputError, match=f"0 of {len(stamps)} frame.s. with an RF fix, need at least 3; "
                                         f"{len(stamps)} with readings from fewer than 3 sensors"):
        localize(steps, stamps, late, 2.0)
    with pytest.raises(InputError, match=r"the readings at t = 10000-10019\.5 s, the frames at 0-19\.5 s"):
        localize(steps, stamps, late, 2.0)  # the two spans side by side: times in ms, or another clock, show at once
    flat = replace(rf, sensors_w_m=rf.sensors_w_m * np.array([1.0, 1.0, 0.0]))  # one plane through the capsule
    with pytest.raises(InputError, match="whose solve found no position"):
        localize(steps, stamps, flat, 2.0)

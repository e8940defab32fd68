"""RF emulation (testbed) and RF localization (bodyslam): the model, the files, and estimator consistency."""

import subprocess
import sys

import numpy as np
import pytest

from bodyslam.fusion.rf import PathLossModel, locate_lls, locate_ml, locate_nls, read_rf, read_sensors, rss_to_range
from testbed.rf import SensorLayout, TOAModel, emulate_rf, write_rf

PL = PathLossModel()


def test_thesis_grids_follow_spec():
    L = SensorLayout.thesis_grids()
    assert len(L.names) == 32
    assert set(np.round(L.positions_w_m[:, 1], 6)) == {0.15, -0.15}
    assert np.allclose(np.unique(L.positions_w_m[:, 0]), np.linspace(-0.15, 0.15, 4))
    assert np.allclose(np.abs(L.normals_w[:, 1]), 1.0)


def test_clean_rss_is_eq_2_1_and_noise_is_the_table_sigma():
    L = SensorLayout.thesis_grids()
    P = np.zeros((4000, 3))  # the centre: 15 cm below both grids -> deep tissue everywhere
    m = emulate_rf(P, L, PL, rng=3)
    d = np.linalg.norm(L.positions_w_m, axis=1)
    want = -16.0 - 47.14 - 10 * 4.26 * np.log10(d / 0.05)
    assert np.allclose(m["rss_clean_dbm"][0], want)
    noise = m["rss_dbm"] - m["rss_clean_dbm"]
    assert noise.std() == pytest.approx(7.85, rel=0.02)  # 128k draws: 2% is > 10 standard errors
    assert abs(noise.mean()) < 0.1
    # near the front surface (5 cm deep) the front sensors switch to the near-surface parameters
    near = emulate_rf(np.array([[0.0, 0.10, 0.0]]), L, PL, rng=0)
    front = L.positions_w_m[:, 1] > 0
    dn = np.linalg.norm(L.positions_w_m[front] - [0, 0.10, 0], axis=1)
    assert np.allclose(near["rss_clean_dbm"][0, front], -16.0 - 49.81 - 10 * 4.22 * np.log10(dn / 0.05))


def test_toa_uses_the_average_permittivity():
    L = SensorLayout.cuboid()
    m = emulate_rf(np.zeros((1, 3)), L, PL, TOAModel(eps_r=49.0, sigma_toa_s=1e-12), rng=0)
    d = np.linalg.norm(L.positions_w_m, axis=1)
    assert np.allclose(m["toa_clean_s"][0], d * 7.0 / 299_792_458.0)


def test_rss_to_range_inverts_the_mean_model():
    d = np.array([0.05, 0.1, 0.2])
    rss = PL.mean_rss_dbm(d, np.full(3, 1.0))
    got, sig = rss_to_range(rss, PL)
    assert np.allclose(got, d)
    assert np.allclose(sig / d, np.log(10) * 7.85 / 42.6)


@pytest.mark.parametrize("method", ["lls", "nls", "ml"])
def test_localizers_are_unbiased_and_their_covariance_is_honest(method):
    rng = np.random.default_rng(0)
    L = SensorLayout.thesis_grids()
    P = rng.uniform([-0.12, -0.06, -0.12], [0.12, 0.06, 0.12], (150, 3))
    m = emulate_rf(P, L, PL, rng=1)
    fixes = []
    for r in m["rss_dbm"]:
        if method == "lls":
            fixes.append(locate_lls(L.positions_w_m, r, PL))
        elif method == "nls":
            fixes.append(locate_nls(L.positions_w_m, r, PL))
        else:
            fixes.append(locate_ml(L.positions_w_m, L.normals_w, r, PL))
    err = np.array([f.position_w_m - p for f, p in zip(fixes, P)])
    maha = np.array([e @ np.linalg.solve(f.cov_m2, e) for e, f in zip(err, fixes)])
    mean_err = np.linalg.norm(err, axis=1).mean()
    # measured: LLS 14.6 cm, NLS 5.2 cm, ML 5.2 cm mean error with the thesis grids and Table 2.2 shadowing
    assert mean_err < {"lls": 0.20, "nls": 0.07, "ml": 0.07}[method]
    # a consistent covariance gives E[maha] = 3; first-order covariances of a log-normal model are not exact:
    # accept 1.5-6 (an overconfident filter input would be far above)
    assert 1.5 < np.median(maha) * 3 / 2.366 < 6.0  # median of chi2(3) is 2.366


def test_missing_sensors_and_bad_lines(tmp_path):
    L = SensorLayout.thesis_grids()
    m = emulate_rf(np.array([[0.02, 0.01, -0.03]] * 3), L, PL, rng=2)
    m["rss_dbm"][1, :28] = np.nan  # only 4 sensors heard at t = 0.5
    m["rss_dbm"][2, :29] = np.nan  # 3 sensors: no fix
    write_rf(tmp_path / "rf.csv", np.array([0.0, 0.5, 1.0]), L, m)
    L.write_csv(tmp_path / "sensors.csv")
    with (tmp_path / "rf.csv").open("a") as f:
        f.write("1.5,F00,not-a-number\n1.5,XX,-80\n")
    names, pos, nrm = read_sensors(tmp_path / "sensors.csv")
    stamps, rss, problems = read_rf(tmp_path / "rf.csv", names)
    assert len(problems) == 2 and "rf.csv:" in problems[0] and "unknown sensor" in problems[1]
    with (tmp_path / "rf.csv").open("a") as f:  # nan and inf parse as numbers: listed, not silently lost
        f.write("1.5,F01,nan\n1.5,F02,-inf\n")
    _, _, problems = read_rf(tmp_path / "rf.csv", names)
    assert len(problems) == 4 and "rss_dbm=nan" in problems[2] and "rss_dbm=-inf" in problems[3], problems
    assert np.isnan(rss[1]).sum() == 28
    assert locate_ml(pos, nrm, rss[1], PL).status == "ok"
    assert locate_nls(pos, rss[2], PL).status == "too_few_sensors"
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "rf-localize", "--rf", str(tmp_path / "rf.csv"),
                        "--sensors", str(tmp_path / "sensors.csv"), "--out", str(tmp_path / "fixes.csv")],
                       capture_output=True, text=True)
    assert p.returncode == 3  # done, with problems listed: the fixes were still written
    assert "skipped" in p.stdout and (tmp_path / "fixes.csv").exists()
    # nothing usable (a header alone): unusable input, one line, and no empty fixes.csv written
    (tmp_path / "rf.csv").write_text("t,sensor,rss_dbm\n")
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "rf-localize", "--rf", str(tmp_path / "rf.csv"),
                        "--sensors", str(tmp_path / "sensors.csv"), "--out", str(tmp_path / "fixes2.csv")],
                       capture_output=True, text=True)
    assert p.returncode == 1 and p.stderr.strip().splitlines() == [f"error: {tmp_path / 'rf.csv'}: no usable RSS "
                                                                   "reading"], p.stderr
    assert not (tmp_path / "fixes2.csv").exists()


def test_realistic_channel_departs_from_the_calibration_as_configured():
    """Correlated shadowing has Gudmundson's correlation along the path; per-sensor offsets, placement error,
    dropouts and outliers appear at their configured sizes; the ideal channel draws what it always drew."""
    from testbed.rf import ChannelModel, SensorLayout, correlated_shadowing, emulate_rf

    rng = np.random.default_rng(5)
    # a straight path of 20,000 poses 2 mm apart: lag-1 correlation exp(-0.002 / 0.01) = 0.819
    path = np.c_[np.zeros(20000), np.zeros(20000), np.arange(20000) * 0.002]
    s = correlated_shadowing(path, 4, 0.01, rng)
    lag1 = np.mean([np.corrcoef(s[:-1, j], s[1:, j])[0, 1] for j in range(4)])
    lag5 = np.mean([np.corrcoef(s[:-5, j], s[5:, j])[0, 1] for j in range(4)])
    # 80,000 samples of a Gauss-Markov process: the estimates' standard error is ~0.005
    assert lag1 == pytest.approx(np.exp(-0.2), abs=0.02) and lag5 == pytest.approx(np.exp(-1.0), abs=0.03)
    assert s.std() == pytest.approx(1.0, abs=0.03)
    layout, pl = SensorLayout.thesis_grids(), PathLossModel()
    pos = np.c_[np.linspace(-0.05, 0.05, 3000), np.zeros(3000), np.zeros(3000)]
    ideal_a = emulate_rf(pos, layout, pl, rng=7)
    ideal_b = emulate_rf(pos, layout, pl, rng=7, channel=ChannelModel())
    assert np.array_equal(ideal_a["rss_dbm"], ideal_b["rss_dbm"])
    ch = ChannelModel(pl0_sd_db=3.0, placement_sd_m=0.005, dropout_prob=0.05, outlier_prob=0.02, outlier_db=15.0)
    real = emulate_rf(pos, layout, pl, rng=7, channel=ch)
    lost = np.isnan(real["rss_dbm"])
    assert lost.mean() == pytest.approx(0.05, abs=0.01)  # 96,000 readings
    moved = np.linalg.norm(real["true_sensors_w_m"] - layout.positions_w_m, axis=1)
    assert 0.003 < np.sqrt(np.mean(moved**2) / 3) < 0.007  # 32 sensors, sd 5 mm per axis
    # per sensor, the mean departure from the calibrated model (shadowing averages out over 3000 readings)
    d = np.linalg.norm(layout.positions_w_m[None] - pos[:, None], axis=2)
    depth = np.maximum(np.einsum("tnk,nk->tn", layout.positions_w_m[None] - pos[:, None], layout.normals_w), 0)
    resid = real["rss_dbm"] - pl.mean_rss_dbm(d, depth)
    ok = ~lost & (np.abs(resid) < 12)  # outliers (15 dB) left out
    per_sensor = np.array([resid[ok[:, j], j].mean() for j in range(32)])
    assert 1.5 < per_sensor.std() < 5.0  # the 3 dB PL(d0) spread (plus what the placement error adds)
    assert np.mean(np.abs(resid[~lost]) > 12) > 0.01  # outliers are there

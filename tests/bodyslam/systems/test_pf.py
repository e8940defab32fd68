"""Particle-filter RF tracking (papers 002/003): field model and its inverse, likelihoods, the filter on cases
with known answers, and the waypoint method."""

import math

import numpy as np
import pytest

from bodyslam.errors import ConfigError
from bodyslam.systems.pf import (C_MPS, MicsRssiModel, ParticleFilter, RandomWaypoint, attenuation_np_per_m, field_ratio,
                         loglik_permittivity, loglik_toa, permittivity_from_field, simple_distance,
                         waypoint_distance)

F, SIG = 4.1e9, 2.17  # 002 Table 3


def test_attenuation_is_the_lossy_dielectric_value_not_the_printed_eq_10():
    a = float(attenuation_np_per_m(34.25, SIG, F))
    # k = beta - j alpha with (beta^2 - alpha^2, 2 alpha beta) = (w^2 mu0 eps, w mu0 sigma): solve independently
    w, mu0, eps0 = 2 * math.pi * F, 4e-7 * math.pi, 8.8541878128e-12
    k2 = w * w * mu0 * eps0 * 34.25 - 1j * w * mu0 * SIG
    assert a == pytest.approx(-np.sqrt(k2).imag, rel=1e-12)
    assert a == pytest.approx(69.2, abs=0.1)  # the printed Eq. 10 (no square root) would give 139.7


def test_eq_11_inverts_eq_9():
    d = np.array([0.05, 0.12, 0.3])
    for eps in (5.0, 34.25, 120.0):
        back = permittivity_from_field(field_ratio(d, eps, SIG, F), d, SIG, F)
        assert back == pytest.approx(eps, rel=1e-9)
    # a field stronger than any lossy tissue allows has no permittivity
    assert np.isnan(permittivity_from_field(np.array([50.0]), np.array([0.1]), SIG, F)).all()


def test_likelihoods_peak_at_the_truth():
    rx = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (-0.2, 0.2) for z in (-0.1, 0.1)])
    p = np.array([0.03, -0.05, 0.01])
    d = np.linalg.norm(rx - p, axis=1)
    toa = math.sqrt(34.25) * d / C_MPS
    cand = p + np.array([[0, 0, 0], [0.005, 0, 0], [0, 0, -0.005]])  # 5 mm: beyond the 3.2 mm range sigma
    ll = loglik_toa(cand, np.full(3, 34.25), toa, rx, 62.5e-12)
    assert ll[0] == pytest.approx(0.0) and ll[1] < -1 and ll[2] < -1
    assert np.argmax(loglik_toa(np.repeat(p[None], 3, 0), np.array([30.0, 34.25, 40.0]), toa, rx, 62.5e-12)) == 1
    m = MicsRssiModel()
    rss = m.mean_db(d)
    assert np.argmax(m.loglik(cand, rss, rx)) == 0
    # Eq. 18 with log eps_i: the maximum is at the geometric mean of the receivers' estimates
    obs = np.array([20.0, 40.0, 60.0])
    grid = np.log(np.linspace(10, 80, 701))
    best = np.exp(grid[np.argmax(loglik_permittivity(grid, obs, 1.23))])
    assert best == pytest.approx(np.exp(np.log(obs).mean()), rel=0.01)


def test_toa_filter_converges_on_a_stopped_capsule_and_estimates_the_permittivity():
    rng = np.random.default_rng(3)
    lo, hi = np.array([-0.2, -0.2, -0.1]), np.array([0.2, 0.2, 0.1])
    rx = np.array([[x, y, z] for x in lo[:1].tolist() + hi[:1].tolist() for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    p = np.array([0.02, 0.04, -0.01])
    pf = ParticleFilter(4000, lo, hi, RandomWaypoint(speed_mean_mps=0.0, speed_sd_mps=1e-5), eps_range=(15, 70),
                        resample_threshold=0.5, rng=1)
    d = np.linalg.norm(rx - p, axis=1)
    for _ in range(150):
        pf.predict(0.1)
        toa = math.sqrt(34.25) * d / C_MPS + rng.normal(0, 62.5e-12, len(rx))
        pf.update(loglik_toa(pf.pos, np.exp(pf.log_eps), toa, rx, 62.5e-12))
    # 8 ranges of 3.2 mm 1-sigma, 150 times: the static optimum is ~0.3 mm; a PF of 4000 particles in 4-D gets
    # within a few millimetres (the tolerance is 3 mm: a filter that failed to converge is centimetres off)
    assert np.linalg.norm(pf.estimate() - p) < 3e-3
    assert math.exp(pf.estimate_log_eps()) == pytest.approx(34.25, rel=0.05)
    assert pf.covariance().shape == (3, 3)


def test_filter_rejects_bad_set_up():
    with pytest.raises(ConfigError, match="at least 2 particles"):
        ParticleFilter(1, [0, 0, 0], [1, 1, 1])
    with pytest.raises(ConfigError, match="min < max"):
        ParticleFilter(10, [0, 0, 0], [1, 0, 1])
    pf = ParticleFilter(10, [0, 0, 0], [1, 1, 1], rng=0)
    with pytest.raises(ConfigError, match="shape"):
        pf.update(np.zeros(3))
    w = pf.w.copy()
    pf.update(np.full(10, -np.inf))  # no particle explains the reading: weights unchanged
    assert np.array_equal(pf.w, w)


def test_waypoint_method_beats_simple_integration_on_a_noisy_stop_and_go_track():
    rng = np.random.default_rng(0)
    corners = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0.1, 0.1, 0.1]])
    track = []
    for a, b in zip(corners[:-1], corners[1:]):
        track += [a] * 300  # stop 30 s at each waypoint
        track += list(a + (b - a) * np.linspace(0, 1, 2000)[:, None])  # 10 cm at 0.05 cm/s (003 Table 1)
    track += [corners[-1]] * 300
    truth = np.array(track)
    est = truth + rng.normal(0, 5e-4, truth.shape)  # 0.5 mm estimation noise
    l_wp, Q, heads = waypoint_distance(est, S=20, r_thr_m=0.003, p_thr_m=0.03)
    # at 0.05 cm/s the stop test (3 mm between two 1 s halves) never sees motion, so a waypoint is placed every
    # p_thr of travel: the path is followed in 3 cm chords and each 90-degree corner is cut (at most
    # 2 x 3 cm - 3 sqrt(2) cm = 1.8 cm per corner); the true 30 cm must come out within 3 cm
    assert abs(l_wp[-1] - 0.30) < 0.03
    assert simple_distance(est)[-1] > 2 * 0.30  # integrating noise: the simple method runs away
    assert len(Q) >= 9
    # the first chord runs along +x: azimuth 0 in the x-z plane, no elevation (Eq. 9-10)
    assert heads[0] == pytest.approx([0.0, 0.0], abs=0.05)
    # the chords of the +y leg climb at 90 degrees of elevation, those of the +z leg have azimuth 90 degrees
    assert np.sum(np.abs(heads[:, 1] - math.pi / 2) < 0.1) >= 2 and np.sum(np.abs(heads[:, 0] - math.pi / 2) < 0.1) >= 2


def test_rf_track_cli_runs_on_recorded_files_and_reports_bad_lines(tmp_path, capsys):
    # a 30 s ito2016 recording through the user's command: the files alone (no testbed), millimetre tracking
    from bodyslam.cli import main as bodyslam_main
    from testbed.rf_tracking import simulate_rf_tracking
    from testbed.scenario import load_scenario

    scn = load_scenario("ito2016", ["sequence.duration_s=30"])
    simulate_rf_tracking(scn, 4, tmp_path / "rec")
    assert bodyslam_main(["rf-track", str(tmp_path / "rec"), "--out", str(tmp_path / "o"), "--particles",
                          "5000"]) == 0
    gt = np.loadtxt(tmp_path / "rec" / "groundtruth.tum")
    est = np.loadtxt(tmp_path / "o" / "trajectory.tum")
    err = np.linalg.norm(gt[:, 1:4] - est[:, 1:4], axis=1)
    assert np.sqrt(np.mean(err[-30:] ** 2)) < 0.005  # 002 reaches ~1.3 mm; 5 mm leaves room for 30 s, 5000 particles
    eps = np.loadtxt(tmp_path / "o" / "permittivity.csv", delimiter=",", skiprows=1)
    # the permittivity particles start log-uniform over 15-70; after 30 s (not 002's 600 s: RMS error 0.14 there)
    # they must have left that range's middle (~32) for the truth's neighbourhood: within 15%
    assert abs(eps[-1, 1] - 34.25) < 5.0
    lines = (tmp_path / "rec" / "rf.csv").read_text().splitlines()
    lines[5] = lines[5].split(",")[0] + ",rx0,oops,1e-9,-40"
    (tmp_path / "rec" / "rf.csv").write_text("\n".join(lines) + "\n")
    assert bodyslam_main(["rf-track", str(tmp_path / "rec"), "--out", str(tmp_path / "o2"), "--particles", "2000",
                          "--method", "rssi_pf"]) == 3  # the malformed line is reported, the run completes
    assert (tmp_path / "o2" / "trajectory.tum").exists()
    # a recording with no usable reading is unusable input, one line, no output (it ended in an IndexError)
    (tmp_path / "rec" / "rf.csv").write_text(lines[0] + "\n")
    assert bodyslam_main(["rf-track", str(tmp_path / "rec"), "--out", str(tmp_path / "o3")]) == 1
    assert "no usable reading" in capsys.readouterr().err and not (tmp_path / "o3").exists()


def test_converged_from_finds_the_first_step_below_the_threshold():
    from bodyslam.systems.pf import converged_from

    assert converged_from(np.array([0.09, 0.03, 0.008, 0.02, 0.004]), 0.01) == 2
    assert converged_from(np.array([0.09, 0.05]), 0.01) == 1  # never: the last step (nothing before it is trusted)

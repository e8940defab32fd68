"""TOA/DOA + IMU hybrid localization (paper 000): Jacobians, CRB expressions, EKF and PCRB checked numerically."""

import math

import numpy as np
import pytest

from bodyslam.systems.toa_doa import (HybridEkf, Radio, Ura, pcrb, q_continuous, q_discrete, run_scheme, snapshot_fix,
                              toa_doa, jacobian, transition)

ARRAYS = [Ura.spanning("front", (-0.2, 0.2, -0.5), 0.4, 0.4, 5, 5),
          Ura.spanning("back", (-0.2, -0.2, -0.5), 0.4, 0.4, 5, 5)]
RADIO = Radio()


def test_jacobian_matches_finite_differences():
    # Eq. 17 against central differences of Eq. 3a/5 at random points between the arrays, all quadrants of the
    # azimuth included (positions on both sides of each reference element)
    rng = np.random.default_rng(0)
    for _ in range(50):
        p = rng.uniform([-0.3, -0.15, -0.6], [0.3, 0.15, 0.0])
        for a in ARRAYS:
            J = jacobian(p, a.ref_m, RADIO.c_avg_mps)
            num = np.zeros((3, 3))
            for j in range(3):
                e = np.zeros(3)
                e[j] = 1e-6
                d = toa_doa(p + e, a.ref_m, RADIO.c_avg_mps) - toa_doa(p - e, a.ref_m, RADIO.c_avg_mps)
                d[1] = (d[1] + math.pi) % (2 * math.pi) - math.pi
                num[:, j] = d / 2e-6
            np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-9 * np.abs(num).max())


def _steering(theta, phi, ura, lam):
    """Eq. 4: the URA's response (N*M,) for azimuth theta and elevation phi."""
    n = np.arange(ura.n_x)
    m = np.arange(ura.n_z)
    ax = np.exp(1j * 2 * np.pi / lam * ura.dx_m * n * np.cos(theta) * np.cos(phi))
    az = np.exp(1j * 2 * np.pi / lam * ura.dz_m * m * np.sin(phi))
    return np.kron(ax, az)


@pytest.mark.parametrize("theta,phi", [(-0.7, 0.4), (-1.2, -0.3), (-0.3, 1.0)])
def test_doa_crb_equals_fisher_information_of_the_array_response(theta, phi):
    # Eq. 8a/8b are the CRBs of each angle for the signal of Eq. 1 with known amplitude:
    # 1 / (2 SNR |d a / d angle|^2), here with the derivative taken numerically from Eq. 4
    ura, lam, snr = ARRAYS[0], RADIO.wavelength_m, 30.0
    h = 1e-7
    da_t = (_steering(theta + h, phi, ura, lam) - _steering(theta - h, phi, ura, lam)) / (2 * h)
    da_p = (_steering(theta, phi + h, ura, lam) - _steering(theta, phi - h, ura, lam)) / (2 * h)
    # the paper's bounds take each angle alone (no coupling with the other angle or the unknown phase)
    crb_t = 1.0 / (2 * snr * np.vdot(da_t, da_t).real)
    crb_p = 1.0 / (2 * snr * np.vdot(da_p, da_p).real)
    var = RADIO.variances(theta, phi, snr, ura)
    assert var[1] == pytest.approx(crb_t, rel=1e-5)
    assert var[2] == pytest.approx(crb_p, rel=1e-5)
    # Eq. 7: TOA, 1 / (8 pi^2 beta^2 MN SNR)
    assert var[0] == pytest.approx(1 / (8 * np.pi**2 * RADIO.beta_hz**2 * 25 * snr))


def test_process_noise_models():
    A, B = transition(1.0)
    Qc, Qd = q_continuous(0.1, 1.0), q_discrete(0.1, 1.0)
    assert np.allclose(Qc[:3, :3], 0.01 / 3 * np.eye(3)) and np.allclose(Qc[:3, 3:], 0.005 * np.eye(3))
    assert np.linalg.matrix_rank(Qd) == 3 and np.allclose(Qd, 0.01 * B @ B.T)
    assert np.allclose(A[:3, 3:], np.eye(3))


def test_imu_only_ekf_covariance_equals_the_pcrb():
    # a linear-Gaussian case: with no RF update and the exact process noise the EKF is the KF, and the KF's
    # covariance *is* the bound (Eq. 28 without the measurement term)
    P0 = np.diag([1e-4] * 3 + [1e-6] * 3)
    ekf = HybridEkf(ARRAYS, RADIO, np.zeros(6), P0, 3e-4, 1.0, use="none", q_model="discrete")
    traces = [np.trace(P0[:3, :3])]
    for _ in range(30):
        ekf.predict(np.zeros(3))
        traces.append(np.trace(ekf.P[:3, :3]))
    bound = pcrb(np.zeros((31, 3)), ARRAYS, RADIO, 3e-4, 1.0, "none", np.random.default_rng(0), P0=P0)
    np.testing.assert_allclose(traces, bound, rtol=1e-9)


def test_snapshot_fix_recovers_a_noise_free_position_and_skips_a_lost_array():
    p = np.array([0.03, -0.05, -0.3])
    y = np.stack([toa_doa(p, a.ref_m, RADIO.c_avg_mps) for a in ARRAYS])
    snr = np.array([50.0, 50.0])
    q, C = snapshot_fix(y, snr, ARRAYS, RADIO, p + [0.02, -0.02, 0.03])
    np.testing.assert_allclose(q, p, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    y[1] = np.nan  # the back array lost: one array's TOA + DOA still fix the position
    q, _ = snapshot_fix(y, snr, ARRAYS, RADIO, p + [0.01, 0.01, -0.01])
    np.testing.assert_allclose(q, p, atol=1e-6)


def test_ekf_update_ignores_a_lost_array_and_reduces_uncertainty():
    ekf = HybridEkf(ARRAYS, RADIO, np.array([0.0, 0.0, -0.3, 0, 0, 0]), np.diag([5e-4] * 3 + [1e-5] * 3), 3e-4)
    y = np.stack([toa_doa([0.01, 0.0, -0.3], a.ref_m, RADIO.c_avg_mps) for a in ARRAYS])
    y[0] = np.nan
    P_before = np.trace(ekf.P[:3, :3])
    ekf.update(y, np.array([np.nan, 100.0]))
    assert np.all(np.isfinite(ekf.x)) and np.trace(ekf.P[:3, :3]) < 0.05 * P_before  # one array: ~2 mm 1-sigma
    assert abs(ekf.x[0] - 0.01) < 2e-3


def test_unknown_scheme_is_a_clear_error():
    from bodyslam.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown scheme"):
        run_scheme("magic", np.zeros(6), np.eye(6), np.zeros((2, 2, 3)), np.zeros((2, 2)), np.zeros((1, 3)),
                   ARRAYS, RADIO, 3e-4, 1.0)

"""The PCRB recursion (paper 000 Eq. 28-29) on the demo trajectory: sanity properties that could fail."""

from pathlib import Path

import numpy as np
import pytest

from bodyslam.io import read_tum
from bodyslam.fusion.rf import PathLossModel, read_sensors
from testbed.bound import pcrb_positions

DEMO = Path(__file__).resolve().parents[2] / "data_samples" / "demo_seed0"


def setup():
    _, gt, grot = read_tum(DEMO / "groundtruth.tum")
    _, pos, nrm = read_sensors(DEMO / "sensors.csv")
    return gt, grot, pos, nrm, PathLossModel()


def rf_only_crb(p, pos, nrm, pl):
    diff = pos - p
    d = np.linalg.norm(diff, axis=1)
    depth = np.maximum(np.einsum("ij,ij->i", diff, nrm), 0)
    _, alpha, sigma = pl.params(depth)
    H = (10 * alpha / np.log(10))[:, None] * diff / (d**2)[:, None]
    return np.trace(np.linalg.inv(H.T @ (H / (sigma**2)[:, None])))


def test_bound_is_below_rf_alone_and_shrinks_with_better_steps():
    gt, grot, pos, nrm, pl = setup()
    n = len(gt)
    P0 = np.diag([0.02**2] * 3 + [np.radians(10) ** 2] * 3)
    loose = pcrb_positions(gt, grot, np.full(n - 1, 3e-3), np.full(n - 1, np.radians(2)), pos, nrm, pl, P0)
    tight = pcrb_positions(gt, grot, np.full(n - 1, 1e-4), np.full(n - 1, np.radians(0.1)), pos, nrm, pl, P0)
    rf = np.array([rf_only_crb(p, pos, nrm, pl) for p in gt])
    assert np.all(loose[1:] < rf[1:])  # RF plus any motion information beats one RF snapshot
    assert np.all(tight[5:] < loose[5:])  # better visual steps, lower bound
    assert tight[-1] < 0.5 * tight[0]  # information accumulates along the path


def test_efficient_mean_error_matches_the_closed_forms():
    from testbed.bound import efficient_mean_error

    C = np.array([np.eye(3) * 1e-4, np.diag([1e-4, 1e-12, 1e-12])])
    got = efficient_mean_error(C)
    # isotropic 3-D: sigma * 2 sqrt(2/pi); one axis: sigma * sqrt(2/pi) (Monte Carlo: 1.5% is 5 standard errors)
    assert got == pytest.approx([0.01 * 2 * np.sqrt(2 / np.pi), 0.01 * np.sqrt(2 / np.pi)], rel=0.015)


def test_smoothing_bound_is_below_filtering_and_equals_it_at_the_last_frame():
    from testbed.bound import smoothing_bound_positions

    gt, grot, pos, nrm, pl = setup()
    n = len(gt)
    P0 = np.diag([0.02**2] * 3 + [np.radians(10) ** 2] * 3)
    args = (gt, grot, np.full(n - 1, 1e-3), np.full(n - 1, np.radians(0.5)), pos, nrm, pl, P0)
    filt = pcrb_positions(*args, full=True)
    smooth = smoothing_bound_positions(*args)
    # the last frame has no future: smoothing and filtering are the same problem there (batch information
    # inverted in one go against the recursion: equal to rounding)
    assert np.allclose(smooth[-1], filt[-1], rtol=1e-8, atol=1e-14)
    # elsewhere the future's readings only add information: filt - smooth is positive semi-definite
    for k in range(n - 1):
        assert np.linalg.eigvalsh(filt[k] - smooth[k]).min() > -1e-14
    tr_f, tr_s = np.trace(filt, axis1=1, axis2=2), np.trace(smooth, axis1=1, axis2=2)
    assert tr_s[0] < 0.5 * tr_f[0]


def _dense_channel_information(gt, grot, sig_t, sig_r, pos, nrm, pl, P0, channel, upto):
    """The information of states 0..upto and the nuisances from readings 0..upto, built the plain way: every
    reading's Jacobian stacked and the shadowing's full covariance across frames inverted (no whitening)."""
    from testbed.bound import _nuisance_jacobian, _nuisance_prior, _transition

    n, S = upto + 1, len(pos)
    jac = [_nuisance_jacobian(p, pos, nrm, pl, channel) for p in gt[:n]]
    m = jac[0][1].shape[1]
    dim = 6 * n + m
    J = np.zeros((dim, dim))
    J[:6, :6] = np.linalg.inv(P0)
    J[6 * n:, 6 * n:] = _nuisance_prior(channel, S)
    for k in range(n - 1):
        A, Q = _transition(gt, grot, sig_t, sig_r, k)
        G = np.zeros((6, dim))  # x_(k+1) - A x_k = w
        G[:, 6 * k:6 * k + 6] = -A
        G[:, 6 * k + 6:6 * k + 12] = np.eye(6)
        J += G.T @ np.linalg.solve(Q, G)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:n], axis=0), axis=1))])
    corr = np.exp(-np.abs(s[:, None] - s[None, :]) / channel.shadowing_corr_m)
    for j in range(S):
        G = np.zeros((n, dim))
        for k in range(n):
            G[k, 6 * k:6 * k + 3] = jac[k][0][j]
            G[k, 6 * n:] = jac[k][1][j]
        sd = np.array([jac[k][2][j] for k in range(n)])
        J += G.T @ np.linalg.solve(corr * np.outer(sd, sd), G)
    return J


def test_channel_bounds_equal_the_plain_construction_and_the_ideal_bound():
    from testbed.bound import channel_bounds, position_bounds
    from testbed.rf import ChannelModel

    gt, grot, pos, nrm, pl = setup()
    n, pos, nrm = 14, pos[::4], nrm[::4]  # 8 sensors, a short run: the plain construction is dense
    gt, grot = gt[:n], grot[:n]
    P0 = np.diag([0.1**2] * 3 + [np.radians(45) ** 2] * 3)
    args = (gt, grot, np.full(n - 1, 1e-3), np.full(n - 1, np.radians(0.5)), pos, nrm, pl, P0)
    ch = ChannelModel(shadowing_corr_m=0.03, pl0_sd_db=2.0, alpha_sd=0.3, placement_sd_m=0.005)
    filt6, smooth6 = channel_bounds(*args, ch, full_state=True)  # position and orientation blocks
    full = np.linalg.inv(_dense_channel_information(*args, ch, n - 1))
    for k in range(n):  # the smoothing bound: the whole run's information inverted in one piece
        assert np.allclose(smooth6[k], full[6 * k:6 * k + 6, 6 * k:6 * k + 6], rtol=1e-6, atol=1e-14)
    for k in (0, 1, 5, n - 1):  # the causal bound: readings up to k only
        Jk = np.linalg.inv(_dense_channel_information(*args, ch, k))
        assert np.allclose(filt6[k], Jk[6 * k:6 * k + 6, 6 * k:6 * k + 6], rtol=1e-6, atol=1e-14)
    filt, smooth = channel_bounds(*args, ch)
    assert np.array_equal(filt, filt6[:, :3, :3]) and np.array_equal(smooth, smooth6[:, :3, :3])
    # the ideal channel: the recursion of Eq. 28 and its smoother, to rounding
    f0, s0 = channel_bounds(*args, ChannelModel())
    pf, ps = position_bounds(*args)
    assert np.allclose(f0, pf, rtol=1e-8, atol=1e-16) and np.allclose(s0, ps, rtol=1e-8, atol=1e-16)
    # every departure only removes information
    tr = lambda b: np.trace(b, axis1=1, axis2=2)  # noqa: E731
    assert np.all(tr(filt) > tr(f0)) and np.all(tr(smooth) > tr(s0))
    assert tr(smooth).mean() > 1.5 * tr(s0).mean()  # and not by a rounding error

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

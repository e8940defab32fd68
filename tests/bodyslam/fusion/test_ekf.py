"""The error-state EKF (bodyslam.fusion.ekf): against the textbook Kalman filter, its candidates run together and
alone, the passes it stores for the smoother, the RSS bias and visual scale states, the Kalman and information
forms of the RSS update, the step noise, and the compiled filter against numpy's."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import fuse, rts_smooth
from bodyslam.steps import StepMotion, StepStatus, motion_from_transform

from tests.bodyslam.fusion import test_body_slam
from tests.bodyslam.fusion.test_body_slam import Step, synthetic_run

demo = test_body_slam.demo  # the demo's true steps with noise, and its RF (a fixture of test_body_slam)


def test_ekf_equals_the_kalman_filter_in_a_linear_gaussian_case():
    # A stopped capsule (every visual step is zero motion with its own 1-sigma) and RF fixes: the process is a
    # random walk and the fix is linear in the position, so the error-state EKF must be the textbook KF exactly.
    from bodyslam.fusion.rf import Fix

    rng = np.random.default_rng(3)
    n, p_true = 60, np.array([0.01, -0.02, 0.03])
    sig = rng.uniform(3e-4, 3e-3, n - 1)
    steps = [Step(Rotation.identity(), np.zeros(3), s, np.radians(0.2), True) for s in sig]
    covs = [np.diag(rng.uniform(0.01, 0.03, 3) ** 2) for _ in range(n)]
    fixes = [Fix(p_true + rng.multivariate_normal(np.zeros(3), C), C, 8) for C in covs]
    p0 = np.array([0.0, 0.0, 0.0])
    res = fuse(steps, fixes, mode="fix", init=(Rotation.identity(), p0), regap_steps=None)
    assert res.n_rejected == 0
    x, P = p0.copy(), np.eye(3) * 1e-4
    for k in range(n):
        if k > 0:
            P = P + np.eye(3) * sig[k - 1] ** 2
        K = P @ np.linalg.inv(P + covs[k])
        x = x + K @ (fixes[k].position_w_m - x)
        P = (np.eye(3) - K) @ P
        assert np.allclose(res.positions_w_m[k], x, atol=1e-12) and np.allclose(res.cov[k][:3, :3], P, atol=1e-15)


@pytest.mark.parametrize("mode", ["rss", "fix"])
@pytest.mark.parametrize("max_rejections", [5, 1])
def test_candidates_run_together_equal_candidates_run_alone(mode, max_rejections):
    # the orientation search runs its candidates as one batch of the one filter; each must be the filter run on
    # its own, including gated readings (a few per run here) and the divergence guard (with max_rejections=1 it
    # fires on the start 10 cm (fixes) or 50 cm (RSS) off: checked below by the run differing from the
    # max_rejections=5 one)
    from bodyslam.fusion.ekf import ErrorStateEkf

    *data, gt = synthetic_run(2, n=90, gap=(30, 36), gap_roll_deg=10.0, fix_frames=90)
    ekf = ErrorStateEkf(*data, mode, max_rejections)
    Rs = np.array([(Rotation.from_rotvec([0.4, -0.3, 0.2]) * Rotation.from_rotvec(np.radians(v))).as_matrix()
                   for v in ([0, 0, 0], [0, 0, 150], [90, 0, 0], [20, -30, 10])])
    ps = np.array([gt[0], gt[0] + 0.03, gt[0] - (0.1 if mode == "fix" else 0.5), gt[0]])
    P = np.repeat(np.diag([1e-4] * 3 + [np.radians(30.0) ** 2] * 3)[None], 4, axis=0)
    if max_rejections == 1:
        other = ErrorStateEkf(*data, mode, 5).run(ps[2:3], Rs[2:3], P[:1], 5, 90)[0]
        assert not np.allclose(ekf.run(ps[2:3], Rs[2:3], P[:1], 5, 90)[0], other)
    pos, rot, covs, nll_k, _ = ekf.run(ps, Rs, P, 5, 90)
    rejected = ekf.n_rejected.copy()
    for c in range(4):
        p1, r1, c1, n1, _ = ekf.run(ps[c:c + 1], Rs[c:c + 1], P[c:c + 1], 5, 90)
        # the same arithmetic on a batch of one: equal to rounding (BLAS may group the sums differently)
        assert np.allclose(pos[c], p1[0], atol=1e-12) and np.allclose(covs[c], c1[0], atol=1e-15)
        assert np.allclose(nll_k[c], n1[0], rtol=1e-12) and ekf.n_rejected[0] == rejected[c]
    assert rejected.sum() > 0  # the gate was exercised


def test_the_committed_run_keeps_its_priors_and_posteriors():
    """x_prior / x_post of every frame, consistent with the process model and the output."""
    from bodyslam.fusion.ekf import process_model

    *data, gt = synthetic_run(3, n=60)
    res = fuse(*data, mode="rss", init_search=False)
    ps = res.passes
    assert ps.post_p.shape == (60, 3) and ps.F.shape == (59, 6, 6)
    k = 30
    F, Q = process_model(ps.post_R[k][None], data[0][k].t_c1_c2_m, data[0][k].R_c1_c2,
                         max(data[0][k].sigma_t_m, 3e-4), max(data[0][k].sigma_r_rad, np.radians(0.2)))
    assert np.allclose(ps.F[k], F[0], atol=1e-15)
    assert np.allclose(ps.prior_P[k + 1], F[0] @ ps.post_P[k] @ F[0].T + Q[0], atol=1e-15)
    assert np.allclose(res.committed_positions_w_m, ps.post_p, atol=0)


def test_rss_bias_states_find_a_sensor_offset():
    """Four sensors read 6 dB high for the whole run (a calibration the channel does not follow): the bias states
    (a long correlation distance: the offset persists) end near +6 dB on those four and near 0 on the others, and
    the run without them is unchanged by the option's existence (off by default)."""
    from bodyslam.fusion.ekf import ErrorStateEkf

    *data, gt = synthetic_run(5, n=120)
    steps, fixes, rss, pos, nrm, pl = data
    rss = rss.copy()
    rss[:, :4] += 6.0
    ekf = ErrorStateEkf(steps, fixes, rss, pos, nrm, pl, "rss", 5, bias_corr_m=10.0, bias_sd_db=6.0)
    P0 = np.diag([1e-4] * 3 + [np.radians(5.0) ** 2] * 3)
    R0 = Rotation.from_rotvec([0.4, -0.3, 0.2])  # synthetic_run's true start
    ekf.run(gt[0][None], R0.as_matrix()[None], P0[None], 0, 120)
    b = ekf.b[0]
    # 120 readings of ~7 dB shadowing per sensor: each bias to about 7 / sqrt(120) ~ 0.7 dB, plus what the
    # position's uncertainty leaves (measured: the four at 4.9-6.7 dB, the others within 3.0 dB -- the sensors far
    # from the capsule constrain their bias least): margins 2 dB and 3.5 dB
    assert np.all(np.abs(b[:4] - 6.0) < 2.0) and np.all(np.abs(b[4:]) < 3.5), b.round(1)
    assert b[:4].mean() - np.abs(b[4:]).mean() > 4.0
    plain = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss")
    assert np.array_equal(plain.positions_w_m, fuse(steps, fixes, rss, pos, nrm, pl, mode="rss",
                                                    bias_corr_m=0.0).positions_w_m)


def test_bias_states_are_marginalised_in_the_stored_passes_and_taken_off_the_readings():
    """With the RSS bias states the stored passes keep the pose block only (memory of a 6-state filter whatever the
    number of sensors) and the biases after each update beside them; the smoother runs on that block, and
    ``net_of_bias`` takes the biases off the readings (the whole-exam solve's and the 1-sigma's input). Without the
    states it hands the readings back as they are."""
    from bodyslam.fusion.localize import net_of_bias

    *data, gt = synthetic_run(5, n=120)
    steps, fixes, rss, pos, nrm, pl = data
    rss = rss.copy()
    rss[:, :4] += 6.0  # four sensors read 6 dB high for the whole run
    R0 = Rotation.from_rotvec([0.4, -0.3, 0.2])  # synthetic_run's true start
    res = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", init=(R0, gt[0]), bias_corr_m=10.0, bias_sd_db=6.0)
    ps = res.passes
    n, m = rss.shape
    assert ps.prior_P.shape == ps.post_P.shape == (n, 6, 6) and ps.F.shape == (n - 1, 6, 6)
    assert ps.post_bias_db.shape == (n, m) and ps.post_b.shape == (n, 0)
    # the four offsets found by the end (the filter's own test above: 4.9-6.7 dB), the others near zero
    assert ps.post_bias_db[-1, :4].mean() > 4.0 and np.abs(ps.post_bias_db[-1, 4:]).mean() < 2.0
    net = net_of_bias(res, rss)
    assert np.array_equal(net, rss - ps.post_bias_db)
    sm = rts_smooth(res)
    e_f = np.linalg.norm(res.positions_w_m - gt, axis=1).mean()
    e_s = np.linalg.norm(sm.positions_w_m - gt, axis=1).mean()
    assert np.isfinite(sm.cov).all() and e_s < e_f, (e_s, e_f)
    plain = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", init=(R0, gt[0]))
    assert plain.passes.post_bias_db is None and net_of_bias(plain, rss) is rss


def test_the_kalman_and_the_information_form_of_the_rss_update_agree():
    """With the bias states the RSS update solves the m x m innovation covariance (Kalman form) instead of
    inverting the D x D one twice (information form, D = 6 + m): the same run either way, gated readings (a
    sensor reading 25 dB off for 20 frames) and candidates run together included."""
    from bodyslam.fusion.ekf import ErrorStateEkf

    *data, gt = synthetic_run(3, n=80)
    steps, fixes, rss, pos, nrm, pl = data
    rss = rss.copy()
    rss[30:50, 5] += 25.0
    R0 = Rotation.from_rotvec([0.4, -0.3, 0.2])
    Rs = np.array([R0.as_matrix(), (R0 * Rotation.from_rotvec([0.0, 0.3, 0.0])).as_matrix()])
    P = np.diag([1e-4] * 3 + [np.radians(10.0) ** 2] * 3)
    out = {}
    for form in (True, False):
        ekf = ErrorStateEkf(steps, fixes, rss, pos, nrm, pl, "rss", 5, bias_corr_m=0.03, bias_sd_db=2.0)
        assert ekf.kalman_form
        ekf.kalman_form = form
        out[form] = ekf.run(np.repeat(gt[:1], 2, axis=0), Rs, np.repeat(P[None], 2, axis=0), 0, len(gt))
        out[form] += (ekf.b.copy(), ekf.n_rejected.copy())
    k, i = out[True], out[False]
    assert k[6].sum() > 0 and np.array_equal(k[6], i[6])  # the same readings gated
    # to rounding (measured: 1.5e-16 m, covariances 2e-15 relative, 5e-13 nats, biases 7e-15 dB of up to 1.9)
    assert np.allclose(k[0], i[0], rtol=0, atol=1e-12) and np.allclose(k[2], i[2], rtol=1e-9, atol=1e-18)
    assert np.allclose(k[3], i[3], rtol=1e-12) and np.allclose(k[5], i[5], rtol=0, atol=1e-10)
    assert not ErrorStateEkf(steps, fixes, rss, pos, nrm, pl, "rss", 5).kalman_form  # without biases: D x D


def _scaled(steps, factor):
    """The steps as a vision that assumed a radius ``factor`` times too large would give them."""
    from dataclasses import replace

    return [replace(s, t_c1_c2_m=s.t_c1_c2_m * factor, distance_m=s.distance_m * factor) if s.has_estimate else s
            for s in steps]


def test_the_scale_state_finds_a_wrong_radius():
    """The vision assumed a radius 30% too large, so every step is 30% long (the true scale error s = 1/1.3 - 1 =
    -0.23). With the scale state (the radius prior's 25%, a correlation distance longer than the run: one radius)
    the filter ends near s = -0.23 and its positions beat the filter without it; bias and scale states together
    keep both working (the bias states sit after the scale in the state)."""
    from bodyslam.fusion.ekf import ErrorStateEkf

    *data, gt = synthetic_run(7, n=160)
    steps, fixes, rss, pos, nrm, pl = data
    steps = _scaled(steps, 1.3)
    P0 = np.diag([1e-4] * 3 + [np.radians(5.0) ** 2] * 3)
    R0 = Rotation.from_rotvec([0.4, -0.3, 0.2])  # synthetic_run's true start
    out = {}
    for name, kw in {"plain": {}, "scale": {"scale_sd_rel": 0.25, "scale_corr_m": 10.0},
                     "both": {"scale_sd_rel": 0.25, "scale_corr_m": 10.0, "bias_corr_m": 10.0, "bias_sd_db": 3.0}}.items():
        ekf = ErrorStateEkf(steps, fixes, rss, pos, nrm, pl, "rss", 5, **kw)
        p, *_ = ekf.run(gt[0][None], R0.as_matrix()[None], P0[None], 0, len(gt))
        out[name] = (np.linalg.norm(p[0] - gt, axis=1).mean(), ekf.b[0])
    # 64 cm of path against the RSS of 24 sensors: the length to ~10% (measured: s = -0.22 alone, -0.23 with the biases)
    assert abs(out["scale"][1][0] + 0.23) < 0.08, out["scale"][1]
    assert abs(out["both"][1][0] + 0.23) < 0.10, out["both"][1][:1]
    # measured: 3.5 cm without, 0.7 cm with it, 1.2 cm with the biases too
    assert out["scale"][0] < 0.4 * out["plain"][0], (out["scale"][0], out["plain"][0])
    assert out["both"][0] < 0.6 * out["plain"][0]
    # fuse / rts_smooth report the state per frame with its 1-sigma (the smoothed one over the whole run)
    kw = {"scale_sd_rel": 0.25, "scale_corr_m": 10.0}
    f = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", init=(R0, gt[0]), **kw)
    sm = rts_smooth(f)
    assert f.scale.shape == sm.scale.shape == (len(gt),) and abs(sm.scale[0] + 0.23) < 0.1
    assert sm.scale_sd[0] < f.scale_sd[0] and fuse(steps, fixes, rss, pos, nrm, pl, mode="rss").scale is None


def test_steps_carry_the_radius_uncertainty_and_the_filter_takes_it_back_out():
    """``with_lumen_uncertainty`` adds ``rel * |d|`` in quadrature to an estimated step's 1-sigma (a 4 mm step
    with a 0.1 mm fit and a 20% radius prior: hypot(0.1, 0.8) mm) and leaves steps without an estimate alone; the
    filter with a scale state of the same prior applies the fit's part only. A lumen-shape share (10%: 0.4 mm)
    is added too and stays: the scale state does not carry it."""
    from bodyslam.fusion.ekf import step_noise
    from bodyslam.vision.odometry import with_lumen_uncertainty

    s = motion_from_transform(Rotation.identity(), [0.0, 0.0, 0.004], 50, 1e-4, np.radians(0.5))
    miss = StepMotion.failed(StepStatus.TOO_FEW_MATCHES)
    a, b = with_lumen_uncertainty([s, miss], 0.2)
    assert a.sigma_distance_m == pytest.approx(np.hypot(1e-4, 8e-4), rel=1e-9) and b is miss
    assert with_lumen_uncertainty([s], 0.0)[0] is s and with_lumen_uncertainty([s], 0.0, 0.0)[0] is s
    _, sig_t, _ = step_noise(a, np.zeros(3), 0.2)
    assert sig_t == pytest.approx(3e-4)  # the fit's 0.1 mm, raised to the filter's 0.3 mm floor
    _, sig_t, _ = step_noise(a, np.zeros(3), 0.0)
    assert sig_t == pytest.approx(np.hypot(1e-4, 8e-4))
    c = with_lumen_uncertainty([s], 0.2, 0.1)[0]
    assert c.sigma_distance_m == pytest.approx(np.sqrt(1e-4**2 + 8e-4**2 + 4e-4**2), rel=1e-9)
    _, sig_t, _ = step_noise(c, np.zeros(3), 0.2)
    assert sig_t == pytest.approx(np.hypot(1e-4, 4e-4), rel=1e-9)  # the fit's and the shape's, not the radius's
    # a step facing the wall: its shape share is inflated as its fit's share was (estimate_wall), not the radius's
    from bodyslam.vision.odometry import WALL_SIGMA_FACTOR

    w = with_lumen_uncertainty([s.with_status(StepStatus.WALL)], 0.2, 0.1)[0]
    assert w.sigma_distance_m == pytest.approx(np.sqrt(1e-4**2 + 8e-4**2 + (WALL_SIGMA_FACTOR * 4e-4)**2), rel=1e-9)


def test_a_rotation_step_turns_the_filter_and_takes_the_long_steps_length(demo):
    """A step with only its rotation measured (status rotation): the dead reckoner and the filters apply that
    rotation, with its own 1-sigma, and the last translation stretched to the steps so far at their 90th
    percentile (a step lost to motion is a long one), with that length as 1-sigma; a step without any estimate
    repeats the last translation as it is, with at least that 1-sigma."""
    from bodyslam.fusion.body_slam import DeadReckoner
    from bodyslam.fusion.ekf import MISSING_SIGMA_T_MIN_M, process_noise, step_rotation_matrices
    from bodyslam.steps import LOST_STEP_QUANTILE, StepLengths

    steps, *_ = demo
    steps = list(steps[:10])
    R5 = Rotation.from_matrix(steps[5].R_c1_c2)
    steps[5] = StepMotion(np.nan, 0.0, 0.0, 0.0, 0.0, 100, "rotation", R5.as_matrix(), None, np.nan, 0.07)
    lengths = StepLengths()
    for s in steps[:5]:
        lengths.add(float(np.linalg.norm(s.t_c1_c2_m)))
    q, t4 = lengths.percentile(LOST_STEP_QUANTILE), np.asarray(steps[4].t_c1_c2_m)
    assert q > np.linalg.norm(t4) * 1.05  # the demo's step 4 is shorter than the first five's 90th percentile
    t_applied, sig_t, sig_r = process_noise(steps)
    assert np.allclose(t_applied[5], t4 * q / np.linalg.norm(t4))  # the last step's direction, the long length
    assert sig_t[5] == pytest.approx(max(q, MISSING_SIGMA_T_MIN_M))
    assert sig_r[5] == pytest.approx(0.07)  # its own rotation 1-sigma, not a missing step's 5 deg
    steps_miss = list(steps)
    steps_miss[5] = StepMotion.failed("too_few_matches")
    t_m, sig_m, _ = process_noise(steps_miss)
    assert np.allclose(t_m[5], t4) and sig_m[5] == pytest.approx(max(q, MISSING_SIGMA_T_MIN_M))
    assert np.allclose(step_rotation_matrices(steps)[5], R5.as_matrix())
    dr, ref = DeadReckoner(), DeadReckoner()
    for k, s in enumerate(steps):
        dr.step(s)
        ref.step(s if k != 5 else StepMotion.failed("too_few_matches"))
    # the rotation step's turn is kept, not dropped: the two orientations differ by R5 seen through the later steps
    assert R5.magnitude() > 0.01
    assert (ref.R_w_c.inv() * dr.R_w_c).magnitude() == pytest.approx(R5.magnitude(), abs=1e-9)
    # with the radius's floor (bodyslam.steps.lost_step_floor_m) above the percentile, the lost step takes the
    # floor, and so does every missing step's 1-sigma; a step lost before any estimate moves forward by the floor
    floor = 2.0 * q
    t_f, sig_f, _ = process_noise(steps, lost_floor_m=floor)
    assert np.allclose(t_f[5], t4 * floor / np.linalg.norm(t4)) and sig_f[5] == pytest.approx(floor)
    assert np.allclose(process_noise(steps_miss, lost_floor_m=floor)[0][5], t4)  # not lost: the last step as it is
    first_lost = [StepMotion.failed("lost")] + list(steps[1:])
    t0, s0, _ = process_noise(first_lost, lost_floor_m=floor)
    assert np.allclose(t0[0], [0.0, 0.0, floor]) and s0[0] == pytest.approx(max(floor, MISSING_SIGMA_T_MIN_M))
    dr_f = DeadReckoner(floor)
    dr_f.step(first_lost[0])
    assert dr_f.path_m == pytest.approx(floor)


def test_the_compiled_filter_equals_numpys(monkeypatch):
    """``_ekf_rss.c`` runs one candidate's frames between the resets and decisions (ErrorStateEkf.run): the same
    run as numpy's to rounding -- with the scale state, a gap whose end searches the orientation again (a reset),
    the start's recheck, NaN readings, one sensor 25 dB off (its readings gated) and every reading 40 dB off for
    12 frames (the divergence guard fires)."""
    import bodyslam.fusion.ekf as ekf_mod

    if ekf_mod._ekf_c is None:
        pytest.skip("bodyslam/fusion/_ekf_rss.c is not built here (no C compiler at install)")
    *data, gt = synthetic_run(4, n=200, gap=(70, 80), gap_roll_deg=12.0, fix_frames=200)
    steps, fixes, rss, pos, nrm, pl = data
    rss = rss.copy()
    rss[30:60, 5] += 25.0
    rss[120:132] += 40.0
    rss[::7, ::3] = np.nan
    calls = []

    class Counted:  # the extension, its calls counted
        @staticmethod
        def run(*args):
            calls.append(args[7:9])
            return ekf_mod._ekf_rss_real.run(*args)

    monkeypatch.setattr(ekf_mod, "_ekf_rss_real", ekf_mod._ekf_c, raising=False)
    out = {}
    for name, module in (("c", Counted), ("numpy", None)):
        monkeypatch.setattr(ekf_mod, "_ekf_c", module)
        out[name] = [fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", scale_sd_rel=0.2, scale_corr_m=1.0),
                     fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", causal_start=True)]
    # the committed runs went through the extension around the gap's end (frame 80: numpy's, its search decides)
    assert (0, 80) in calls and (81, 200) in calls, calls
    for c, n in zip(out["c"], out["numpy"]):
        assert [s.frames for s in c.searches] == [s.frames for s in n.searches] and len(c.searches) >= 2
        assert (c.n_rejected, c.n_updates) == (n.n_rejected, n.n_updates) and c.n_rejected > 30
        # sums in another order: measured positions 5e-15 m apart, covariances 2e-15 (entries up to 2e-2; an entry
        # that cancels to 2e-14 differs relatively by 1e-4, so the bound is absolute, 1e-11 of the largest)
        assert np.allclose(c.positions_w_m, n.positions_w_m, rtol=0, atol=1e-12)
        assert np.allclose(c.rotations_w_c.as_matrix(), n.rotations_w_c.as_matrix(), rtol=0, atol=1e-12)
        assert np.allclose(c.cov, n.cov, rtol=0, atol=1e-11 * np.abs(n.cov).max())
        for f in ("prior_p", "prior_R", "prior_P", "F", "post_P", "prior_b", "post_b"):
            a, b = getattr(c.passes, f), getattr(n.passes, f)
            assert a.shape == b.shape and np.allclose(a, b, rtol=0, atol=1e-11 * np.abs(b).max(initial=1e-300)), f
    # the guard fired: every reading 40 dB off for 12 frames, the position's 1-sigma opened by its 5 cm
    sd = np.sqrt(np.trace(out["c"][0].cov[:, :3, :3], axis1=1, axis2=2))
    assert sd[120:132].max() > 0.04 > sd[110], (sd[110], sd[120:132].max())
    assert out["c"][0].scale is not None and np.allclose(out["c"][0].scale, out["numpy"][0].scale, atol=1e-12)

"""Fusion of visual steps with RF: on the demo sequence's RF draws, with true steps plus step noise."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import align_to_fixes, fuse, rts_smooth
from bodyslam.io import read_json, read_tum
from bodyslam.fusion.rf import PathLossModel, locate_ml, read_rf, read_sensors
from bodyslam.steps import StepMotion, StepStatus, motion_from_transform


def Step(R: Rotation, t, sigma_t_m: float, sigma_r_rad: float, ok: bool) -> StepMotion:
    """A step with the given pose and 1-sigmas (``ok``), or one without an estimate."""
    if not ok:
        return StepMotion.failed(StepStatus.NO_LUMEN)
    return motion_from_transform(R, t, 50, sigma_t_m, sigma_r_rad)

DEMO = Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0"


@pytest.fixture(scope="module")
def demo():
    names, pos, nrm = read_sensors(DEMO / "sensors.csv")
    _, rss, problems = read_rf(DEMO / "rf.csv", names)
    assert not problems
    pl = PathLossModel.from_dict(read_json(DEMO / "meta.json")["rf"]["pathloss"])
    _, gt, grot = read_tum(DEMO / "groundtruth.tum")
    rng = np.random.default_rng(0)
    steps = []
    for k in range(len(gt) - 1):
        R = grot[k].inv() * grot[k + 1]
        t = grot[k].inv().apply(gt[k + 1] - gt[k])
        # visual-step noise at the tube estimator's measured level (0.004 cm, 0.03 deg per step) x 5
        steps.append(Step(R * Rotation.from_rotvec(rng.normal(0, np.radians(0.15), 3)),
                          t + rng.normal(0, 2e-4, 3), 2e-4, np.radians(0.15), True))
    fixes = [locate_ml(pos, nrm, r, pl) for r in rss]
    return steps, fixes, rss, pos, nrm, pl, gt


def err(P, gt):
    return float(np.mean(np.linalg.norm(P - gt, axis=1)))


def test_alignment_recovers_a_known_frame():
    rng = np.random.default_rng(1)
    q = np.cumsum(rng.normal(0, 0.01, (30, 3)), axis=0)
    R = Rotation.from_rotvec([0.3, -1.0, 2.0])
    p0 = np.array([0.05, -0.02, 0.1])
    from bodyslam.fusion.rf import Fix

    fixes = [Fix(p0 + R.apply(x), np.eye(3) * 1e-6, 32) for x in q]
    R_est, p_est, rms = align_to_fixes(q, fixes)
    assert (R_est.inv() * R).magnitude() < 1e-9 and np.allclose(p_est, p0) and rms < 1e-9


@pytest.mark.parametrize("mode", ["fix", "rss"])
def test_fusion_beats_rf_alone_and_the_smoother_beats_the_filter(demo, mode):
    steps, fixes, rss, pos, nrm, pl, gt = demo
    rf_only = err(np.array([f.position_w_m for f in fixes]), gt)
    ekf = fuse(steps, fixes, rss, pos, nrm, pl, mode=mode)
    rts = rts_smooth(ekf)
    e_ekf, e_rts = err(ekf.positions_w_m, gt), err(rts.positions_w_m, gt)
    # 40 frames, 16 cm of travel: RF alone is ~5 cm off; accurate steps tie the fixes together
    assert e_ekf < 0.5 * rf_only, (e_ekf, rf_only)
    assert e_rts <= e_ekf + 1e-4
    # covariances are positive definite and honest to within a factor 3 in the smoothed positions
    sd = np.sqrt(np.trace(rts.cov[:, :3, :3], axis1=1, axis2=2)).mean()
    assert np.all(np.linalg.eigvalsh(rts.cov[:, :3, :3]) > 0)
    assert e_rts / 3 < sd < 3 * max(e_rts, 0.003)


def test_steps_without_an_estimate_are_bridged(demo):
    steps, fixes, rss, pos, nrm, pl, gt = demo
    holed = [s if not 15 <= k < 22 else Step(Rotation.identity(), np.zeros(3), 0, 0, False)
             for k, s in enumerate(steps)]
    res = rts_smooth(fuse(holed, fixes, rss, pos, nrm, pl, mode="rss"))
    assert np.isfinite(res.positions_w_m).all()
    # the gap's frames carry more uncertainty than their neighbours
    sd = np.sqrt(np.trace(res.cov[:, :3, :3], axis1=1, axis2=2))
    assert sd[19] > sd[5]


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


def test_thesis_kf_runs_and_improves_on_rf(demo):
    from bodyslam.fusion.body_slam import kf_thesis
    from bodyslam.fusion.rf import locate_nls

    steps, fixes, rss, pos, nrm, pl, gt = demo
    nls = [locate_nls(pos, r, pl) for r in rss]
    init = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss").init
    got = kf_thesis(steps, nls, init)
    assert err(got, gt) < err(np.array([f.position_w_m for f in nls]), gt)


def test_dead_reckoner_streams_the_filters_prediction(demo):
    from bodyslam.fusion.body_slam import DeadReckoner
    from bodyslam.vision.tracking import dead_reckon

    steps, *_ , gt = demo
    steps = list(steps)
    steps[5] = Step(Rotation.identity(), np.zeros(3), 0.0, 0.0, False)  # one step without an estimate
    dr = DeadReckoner()
    pos, sd = [dr.p_w_m.copy()], [0.0]
    for s in steps:
        dr.step(s)
        pos.append(dr.p_w_m.copy())
        sd.append(float(np.sqrt(np.trace(dr.P[:3, :3]))))
    pos = np.array(pos)
    # the missing step repeats step 4's translation (constant velocity) with no rotation
    bridged = [s if k != 5 else Step(Rotation.identity(), steps[4].t_c1_c2_m, 0.0, 0.0, True)
               for k, s in enumerate(steps)]
    ref, _ = dead_reckon(bridged)
    assert np.allclose(pos, ref, atol=1e-12)
    # the step without an estimate costs far more certainty than an estimated one (its 1-sigma is its own size,
    # at least the steps so far at their 90th percentile)
    from bodyslam.steps import LOST_STEP_QUANTILE, StepLengths

    assert sd[6] - sd[5] > 5 * abs(sd[5] - sd[4])
    assert dr.path_m == pytest.approx(sum(np.linalg.norm(s.t_c1_c2_m) for s in bridged), rel=1e-12)
    lengths = StepLengths()
    for s in steps[:5]:
        lengths.add(float(np.linalg.norm(s.t_c1_c2_m)))
    sig5 = max(np.linalg.norm(steps[4].t_c1_c2_m), lengths.percentile(LOST_STEP_QUANTILE), 3e-3)
    assert dr.path_var_m2 == pytest.approx(sum(max(s.sigma_t_m, 3e-4) ** 2 for s in steps if s.ok) + sig5**2,
                                           rel=1e-12)


def test_thesis_kf_keeps_its_rotation_on_the_updated_heading():
    # A capsule turning 5 deg per 1 cm step, started with a 30 deg misaligned camera, 2 cm RF fixes: the steps'
    # rotations must be carried into the world by a rotation whose optical axis follows the filter's corrected
    # heading. Mean error over 10 fix draws: 1.30 cm; 1.57 when R_w_c stays dead reckoning's (the margin, 0.13
    # cm, is 4 standard errors of the 10-draw mean).
    from bodyslam.fusion.body_slam import kf_thesis
    from bodyslam.fusion.rf import Fix

    Rs, t = Rotation.from_rotvec([0, np.radians(5), 0]), np.array([0, 0, 0.01])
    R_true, p, gt, steps = Rotation.identity(), np.zeros(3), [np.zeros(3)], []
    for _ in range(150):
        steps.append(Step(Rs, t, 1e-4, 1e-3, True))
        p = p + R_true.apply(t)
        R_true = R_true * Rs
        gt.append(p.copy())
    gt = np.array(gt)
    init = (Rotation.from_rotvec([np.radians(30), 0, 0]), np.zeros(3))
    errs = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        fixes = [Fix(g + rng.normal(0, 0.02, 3), np.eye(3) * 0.02**2, 8) for g in gt]
        errs.append(np.linalg.norm(kf_thesis(steps, fixes, init) - gt, axis=1).mean())
    assert np.mean(errs) < 0.0143


# -- synthetic runs with known truth: a capsule curving through the thesis sensor grids ---------------------------

def synthetic_run(seed, n=120, gap=None, gap_roll_deg=0.0, fix_frames=60, channel=None):
    """Truth, visual steps with the filter's assumed noise (0.3 mm, 0.2 deg per axis), RSS from Eq. 2.1 with
    Table 2.2 shadowing (through ``channel``, a :class:`testbed.rf.ChannelModel`, if given), ML fixes for the first
    ``fix_frames`` frames (the RSS filter uses fixes only to align its start). ``gap``: steps ``[a, b)`` without
    an estimate, during which the capsule also rolls ``gap_roll_deg`` per step. The path: 0.4 cm steps."""
    from bodyslam.fusion.rf import Fix
    from testbed.rf import ChannelModel, SensorLayout, emulate_rf

    rng = np.random.default_rng(seed)
    layout, pl = SensorLayout.thesis_grids(), PathLossModel()
    R, p = Rotation.from_rotvec([0.4, -0.3, 0.2]), np.array([-0.04, 0.0, -0.04])
    steps, gt = [], [p]
    for k in range(n - 1):
        Rs = Rotation.from_rotvec(np.radians([2.0 * np.sin(k / 15), 3.0 * np.cos(k / 25), 2.0]))
        t = np.array([0.0, 0.0, 0.004])
        if gap and gap[0] <= k < gap[1]:
            Rs = Rs * Rotation.from_rotvec([0.0, 0.0, np.radians(gap_roll_deg)])
            steps.append(Step(Rotation.identity(), np.zeros(3), 0.0, 0.0, False))
        else:
            steps.append(Step(Rs * Rotation.from_rotvec(rng.normal(0, np.radians(0.2), 3)),
                              t + rng.normal(0, 3e-4, 3), 3e-4, np.radians(0.2), True))
        p = p + R.apply(t)
        R = R * Rs
        gt.append(p)
    gt = np.array(gt)
    rss = emulate_rf(gt, layout, pl, rng=seed, channel=channel or ChannelModel())["rss_dbm"]
    fixes = [locate_ml(layout.positions_w_m, layout.normals_w, r, pl) if k < fix_frames
             else Fix(np.full(3, np.nan), np.full((3, 3), np.nan), 0, "failed") for k, r in enumerate(rss)]
    return steps, fixes, rss, layout.positions_w_m, layout.normals_w, pl, gt


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


def test_rss_filter_and_smoother_are_consistent():
    # Normalised estimation error squared of the positions over 10 runs whose visual steps carry exactly the
    # noise the filter assumes: at each frame its mean over the runs is chi2(30)/10 if the covariances are
    # honest; the 99% band of that is [1.50, 5.10]. Frames from 60 on (after the start's alignment window).
    nees = {"filter": [], "smoother": []}
    for seed in range(10):
        *data, gt = synthetic_run(seed)
        ekf = fuse(*data, mode="rss")
        for name, res in (("filter", ekf), ("smoother", rts_smooth(ekf))):
            e = res.positions_w_m - gt
            nees[name].append([float(e[k] @ np.linalg.solve(res.cov[k][:3, :3], e[k])) for k in range(60, len(gt))])
    for name, v in nees.items():
        per_frame = np.mean(v, axis=0)
        inside = np.mean((per_frame > 1.50) & (per_frame < 5.10))
        # measured (12 runs of 160 frames): mean NEES 2.88 filter, 3.02 smoother; consecutive frames are
        # correlated, so ask for 90% of frames inside the 99% band, and a mean within 2.0-4.0
        assert inside >= 0.9 and 2.0 < per_frame.mean() < 4.0, (name, inside, per_frame.mean())


def test_orientation_is_searched_again_after_a_long_gap():
    # Ten steps without a visual estimate while the capsule rolls 12 deg per step: its orientation afterwards is
    # 120 deg from the filter's prediction, which a linearised update cannot repair. Measured on seeds 0-2:
    # mean error after the gap 1.4-1.8 cm with the search, 4.0-5.4 cm without.
    *data, gt = synthetic_run(0, n=160, gap=(60, 70), gap_roll_deg=12.0)
    with_search = fuse(*data, mode="rss")
    without = fuse(*data, mode="rss", regap_steps=None)
    e_with = np.linalg.norm(with_search.positions_w_m[70:] - gt[70:], axis=1).mean()
    e_without = np.linalg.norm(without.positions_w_m[70:] - gt[70:], axis=1).mean()
    assert [s.frames[0] for s in with_search.searches] == [0, 70]
    assert e_with < 0.5 * e_without and e_with < 0.025, (e_with, e_without)
    # what the smoother is told about the re-start: the new orientation does not depend on the old, so every stored
    # prior is F post F^T plus a process noise without position-orientation cross terms (with the reset's F
    # unchanged the cross block here was 1.2e-3, and on a realistic run the smoothed covariance had eigenvalues
    # down to -10 and NaN 1-sigmas)
    ps = with_search.passes
    for k in range(len(ps.F)):
        q = ps.prior_P[k + 1] - ps.F[k] @ ps.post_P[k] @ ps.F[k].T
        assert np.abs(q[:3, 3:6]).max() < 1e-12, k
    assert np.linalg.eigvalsh(rts_smooth(with_search).cov).min() > -1e-12


def test_start_search_recovers_a_wrong_alignment_and_the_online_output_is_causal():
    from bodyslam.fusion.ekf import ErrorStateEkf
    from bodyslam.fusion.orientation_search import search_orientation

    *data, gt = synthetic_run(1)
    steps, fixes, rss, pos, nrm, pl = data
    ekf = ErrorStateEkf(steps, fixes, rss, pos, nrm, pl, "rss", 5)
    R_true = Rotation.from_rotvec([0.4, -0.3, 0.2])
    P = np.diag([1e-4] * 3 + [np.radians(30.0) ** 2] * 3)
    def err_after_60(R):
        return np.linalg.norm(ekf.run(gt[0], R, P, 0, len(gt))[0][0, 60:] - gt[60:], axis=1).mean()

    e_true = err_after_60(R_true)
    for wrong in ([0, 0, 150], [120, 0, 0], [0, 90, 90]):
        centre = R_true * Rotation.from_rotvec(np.radians(wrong))
        found = search_orientation(ekf, 0, 80, centre, lambda R: gt[0], P, [])
        R = found.R
        # The readings pin the orientation only to within ~30 deg (measured: from the truth itself the search
        # lands 10 deg away), which the filter's 30 deg start covariance then absorbs: the chosen start must be
        # inside that and track as well as the true one (measured 0.79-0.86 cm against 0.83 after frame 60),
        # where the wrong start itself does not.
        assert np.degrees((R.inv() * R_true).magnitude()) < 40.0, (wrong, found.turn_from_centre_deg)
        assert err_after_60(R) < 1.2 * e_true and err_after_60(centre) > 2 * e_true
    # Readings after frame 90 change nothing before it (the start's decision window is frames 0-79; inside it
    # the output is the candidates' mixture on the readings so far)
    ref = fuse(*data, mode="rss")
    rss2 = rss.copy()
    rss2[90:] += 6.0
    moved = fuse(steps, fixes, rss2, pos, nrm, pl, mode="rss")
    assert np.array_equal(ref.positions_w_m[:90], moved.positions_w_m[:90])
    assert np.array_equal(ref.rotations_w_c[:90].as_matrix(), moved.rotations_w_c[:90].as_matrix())
    assert not np.allclose(ref.positions_w_m[90:], moved.positions_w_m[90:])


def test_a_search_scored_from_a_later_frame_compares_the_candidates_on_those_frames_only():
    """``score_from`` (the start's recheck): the candidates run from ``k0`` but their likelihoods, the mixture and
    the leader are taken over frames ``score_from ..`` only; from ``k0`` itself it is the plain search."""
    from bodyslam.fusion.ekf import ErrorStateEkf
    from bodyslam.fusion.orientation_search import search_orientation

    *data, gt = synthetic_run(1)
    ekf = ErrorStateEkf(*data, "rss", 5, bias_corr_m=0.03, bias_sd_db=2.0)
    centre = Rotation.from_rotvec(np.radians([0.0, 0.0, 150.0]))
    P = np.diag([1e-4] * 3 + [np.radians(45.0) ** 2] * 3)
    plain = search_orientation(ekf, 0, 100, centre, lambda R: gt[0], P, [])
    same = search_orientation(ekf, 0, 100, centre, lambda R: gt[0], P, [], score_from=0)
    assert same.frames == plain.frames == (0, 100) and same.R.approx_equal(plain.R)
    assert np.array_equal(same.mixture_positions_w_m, plain.mixture_positions_w_m)
    later = search_orientation(ekf, 0, 100, centre, lambda R: gt[0], P, [], score_from=60)
    assert later.frames == (60, 100) and len(later.mixture_positions_w_m) == len(later.lead_nll) == 40
    # the centre candidate's score: its cumulative nll over frames 60..99, the run from frame 0 less frames 0..59
    nll = ekf.run(gt[0], centre, P, 0, 100)[3][0]
    assert later.least_nll[-1] == pytest.approx(later.nll_best) and later.nll_best <= later.nll_centre
    # (rel 1e-9: the search runs the centre batched with the other candidates, the reference alone -- rounding only)
    assert later.nll_centre == pytest.approx(nll[-1] - nll[59], rel=1e-9)
    assert later.nll_centre < plain.nll_centre  # 40 frames' worth, not 100
    with pytest.raises(ValueError, match="outside the run"):
        search_orientation(ekf, 0, 100, centre, lambda R: gt[0], P, [], score_from=100)


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


def test_the_strictly_causal_start_uses_no_later_reading():
    """With ``causal_start`` frame k's estimate depends on frames 0..k only -- inside the start window too, where
    the default start aligns the first 40+ frames' fixes (a look-ahead)."""
    from bodyslam.fusion.rf import Fix

    *data, gt = synthetic_run(4, n=100)
    steps, fixes, rss, pos, nrm, pl = data
    rss2 = rss.copy()
    rss2[20:] += 6.0
    fixes2 = [f if k < 20 else Fix(f.position_w_m + 0.05, f.cov_m2, f.n_sensors, f.status) for k, f in enumerate(fixes)]
    causal = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", causal_start=True)
    causal2 = fuse(steps, fixes2, rss2, pos, nrm, pl, mode="rss", causal_start=True)
    assert np.array_equal(causal.positions_w_m[:20], causal2.positions_w_m[:20])
    # its orientation too (the leading candidate's on the readings so far, not the one decided at frame 80)
    assert np.array_equal(causal.rotations_w_c[:20].as_matrix(), causal2.rotations_w_c[:20].as_matrix())
    ahead = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss")
    ahead2 = fuse(steps, fixes2, rss2, pos, nrm, pl, mode="rss")
    assert not np.allclose(ahead.positions_w_m[:20], ahead2.positions_w_m[:20])  # the look-ahead start does see them
    # and it still tracks: after its 80-frame decision the causal filter is within 2 cm (measured 0.6-1.0 cm)
    assert np.linalg.norm(causal.positions_w_m[80:] - gt[80:], axis=1).mean() < 0.02


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


def test_a_start_committed_far_off_is_turned_by_the_recheck_and_the_output_stays_causal(monkeypatch):
    """The start's search is made to commit 150 deg off (as thesis seed 707's strictly causal start did, 142 deg).
    The recheck over the next window turns it and the run starts again from the start turned the same way: after
    that window the error is a good run's (measured: 0.68 cm against 37.5 without the recheck; 1.5 cm would be 2x
    the unforced run's). Inside the window the output on frame k depends on readings 0..k only. Without the
    forced error the same run keeps its start (the recheck's margin stays below the threshold)."""
    import bodyslam.fusion.body_slam as bs
    from dataclasses import replace as dc_replace

    *data, gt = synthetic_run(5, n=240, fix_frames=240)
    steps, fixes, rss, pos, nrm, pl = data
    plain = fuse(*data, mode="rss", causal_start=True)
    assert [s.frames[0] for s in plain.searches] == [0]
    bias = dict(bias_corr_m=0.03, bias_sd_db=2.0)  # per-sensor RSS bias states (below)
    plain_b = fuse(*data, mode="rss", causal_start=True, **bias)

    real_search = bs.search_orientation
    calls = []

    def first_one_off(ekf, k0, *args, **kw):
        found = real_search(ekf, k0, *args, **kw)
        calls.append(k0)
        if len(calls) == 1:  # the start: committed 150 deg off
            return dc_replace(found, R=found.R * Rotation.from_rotvec(np.radians([0.0, 150.0, 0.0])))
        return found

    monkeypatch.setattr(bs, "search_orientation", first_one_off)

    def run(rss_, **kw):
        calls.clear()
        return fuse(steps, fixes, rss_, pos, nrm, pl, mode="rss", causal_start=True, **kw)

    off, on = run(rss, recheck_start=False), run(rss)
    e_off = np.linalg.norm(off.positions_w_m[160:] - gt[160:], axis=1).mean()
    e_on = np.linalg.norm(on.positions_w_m[160:] - gt[160:], axis=1).mean()
    assert [s.frames[0] for s in on.searches] == [0, 80] and [s.frames[0] for s in off.searches] == [0]
    e_plain = np.linalg.norm(plain.positions_w_m[160:] - gt[160:], axis=1).mean()
    assert e_on < max(2 * e_plain, 0.015) and e_off > 10 * e_on, (e_on, e_off, e_plain)
    rss2 = rss.copy()
    rss2[120:] += 6.0  # later readings: nothing before frame 120 may move
    moved = run(rss2)
    assert np.array_equal(on.positions_w_m[:120], moved.positions_w_m[:120])
    assert np.array_equal(on.rotations_w_c[:120].as_matrix(), moved.rotations_w_c[:120].as_matrix())
    assert not np.allclose(on.positions_w_m[120:], moved.positions_w_m[120:])
    # With per-sensor RSS bias states (3 cm, 2 dB) the committed run absorbs part of the misfit in the biases and
    # had drifted 11-14 cm by the window's end; a recheck searched from that pose turned 120 deg the wrong way
    # (10-12 cm after frame 160). Its candidates now run from frame 0 (measured: 0.8 cm after frame 160, the
    # unforced run 0.8)
    on_b = run(rss, **bias)
    e_on_b = np.linalg.norm(on_b.positions_w_m[160:] - gt[160:], axis=1).mean()
    e_plain_b = np.linalg.norm(plain_b.positions_w_m[160:] - gt[160:], axis=1).mean()
    assert [s.frames[0] for s in on_b.searches] == [0, 80] and e_on_b < max(2 * e_plain_b, 0.015), (e_on_b, e_plain_b)


def _bend_window_by_growing(q, m0, spread_m):
    """The rule as first written: grow the window one point at a time (O(n^2))."""
    from bodyslam.fusion.body_slam import _second_spread

    n, m = len(q), min(len(q), max(m0, 3))
    while m < n and _second_spread(q[:m]) < spread_m:
        m += 1
    return m


def test_the_alignment_window_is_the_one_grown_point_by_point():
    """The start's window (the shortest dead-reckoned path that bends by ``init_spread_m``) found from prefix sums
    is the one the point-by-point rule finds: on straight paths that never bend, paths that bend early or late,
    a capsule at rest, far from the origin (the sums' rounding), a window that starts at the end, and a path whose
    spread lands exactly on the threshold at a known point."""
    from bodyslam.fusion.body_slam import _bend_window, _second_spread

    rng = np.random.default_rng(11)
    line = np.c_[np.linspace(0, 0.3, 900), np.zeros(900), np.zeros(900)] + rng.normal(0, 1e-4, (900, 3))
    arc_t = np.linspace(0, 2.0, 900)
    arc = 0.1 * np.c_[np.sin(arc_t), 1 - np.cos(arc_t), 0.1 * arc_t]
    late = line.copy()
    late[600:, 1] += np.linspace(0, 0.1, 300) ** 2 * 8  # straight, then it turns
    walk = np.cumsum(rng.normal(0, 1e-3, (900, 3)), axis=0)
    cases = [line, arc, late, walk, np.zeros((500, 3)), walk + 0.8, arc[:41], arc[:40], arc[:2]]
    for q in cases:
        for m0, spread in ((40, 0.015), (3, 0.002), (40, 0.05), (100, 1e-4)):
            assert _bend_window(q, m0, spread) == _bend_window_by_growing(q, m0, spread)
    assert _bend_window(line, 40, 0.015) == len(line)  # never bends: the whole path
    # the threshold met exactly at a known window: the spread of arc[:300] itself
    s300 = _second_spread(arc[:300])
    assert _bend_window(arc, 40, s300) == _bend_window_by_growing(arc, 40, s300) <= 300


def test_a_path_that_never_bends_costs_no_spread_per_point(monkeypatch):
    """The exact spread (an SVD of the whole window) is computed only near the threshold: along a straight path of
    5,000 points it is never needed, where growing the window took 5,000 SVDs (55,000 on a whole exam: 74 s)."""
    from bodyslam.fusion import body_slam

    calls = []
    exact = body_slam._second_spread
    monkeypatch.setattr(body_slam, "_second_spread", lambda q: calls.append(len(q)) or exact(q))
    rng = np.random.default_rng(2)
    line = np.c_[np.linspace(0, 1.0, 5000), np.zeros((5000, 2))] + rng.normal(0, 1e-4, (5000, 3))
    assert body_slam._bend_window(line, 40, 0.015) == 5000
    assert calls == []


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

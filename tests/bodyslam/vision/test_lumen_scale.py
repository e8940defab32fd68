"""The lumen's scale from a tube with one contraction ring (bodyslam.vision.lumen_scale)."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.steps import StepMotion, rotation_step
from bodyslam.vision.lumen_scale import (RING_MIN_SAMPLES, RING_SAMPLE_MIN_STEPS, RING_SAMPLES_MAX, SCALE_SD_FLOOR_REL,
                                         exam_scale, rescaled, ring_distance_ratio, ring_every)

EVERY_RATIO = dict(min_cost_drop=-np.inf, min_significance=-np.inf)  # no test of whether a ring is seen
from bodyslam.vision.motion import fit_tube, motion_from_transform
from tests.bodyslam.vision.test_motion import CAM, R_TUBE, synth_matches


def ringed_tube_points(n, rng, depth, centre_m, width_m, s_range=(0.002, 0.06)):
    """Points on a tube along the optical axis whose radius narrows in one ring: R (1 - depth exp(-(z - c)^2 /
    2 w^2))."""
    z = rng.uniform(*s_range, n)
    a = rng.uniform(0, 2 * math.pi, n)
    r = R_TUBE * (1.0 - depth * np.exp(-0.5 * ((z - centre_m) / width_m) ** 2))
    return np.c_[r * np.cos(a), r * np.sin(a), z]


def _ratio_and_fit(X1, rv, t, rng, noise_px=0.3, **kw):
    m = synth_matches(X1, Rotation.from_rotvec(rv), np.array(t), noise_px=noise_px, rng=rng)
    s, x = fit_tube(m, CAM, R_TUBE)
    assert s.ok
    return ring_distance_ratio(m.pts1_px, m.pts2_px, CAM, R_TUBE, x, **kw), s


@pytest.mark.parametrize("rv, t", [((0.0, 0.0, 0.14), (0.0, 0.0, 0.0041)),
                                   ((0.04, -0.03, 0.1), (0.0004, -0.0002, 0.005))])
def test_a_plain_cylinder_keeps_its_scale(rv, t):
    """On the cylinder the fit assumes, the ring has nothing to explain: its fit keeps the scale (within 3%: 0.3 px
    noise on 150 rays lets the ring's depth wander by a few hundredths), and no ring is seen, so the step has no
    ratio at all."""
    rng = np.random.default_rng(5)
    X1 = ringed_tube_points(300, rng, 0.0, 0.03, 0.7 * R_TUBE)
    ratio, _ = _ratio_and_fit(X1, rv, t, np.random.default_rng(6), **EVERY_RATIO)
    assert abs(ratio - 1.0) < 0.03
    ratio, _ = _ratio_and_fit(X1, rv, t, np.random.default_rng(6))
    assert math.isnan(ratio)


def test_a_ring_counts_only_where_the_matches_show_one():
    """Short steps on noisy matches (0.6 mm, 1 px: twice the ray noise the fits assume) on a plain cylinder: the
    ring fit settles on some narrowing and reads the step short (the bias this test is about: 0.835 of the true step
    at the median of 24; 0.76-0.85 over other draws); the ring lowers the cost by more than the noise the fits
    assume on many of them, but by little against their own residual scale: at most 2 of 24 ratios count (none
    here; 1 of 12 in another draw). A ring that is there (closing the lumen by 45%, 0.3 px, 4.1-mm steps) is seen
    and counts with the ratio it had."""
    ratios, kept = [], []
    for k in range(24):
        rng = np.random.default_rng(100 + k)
        X1 = ringed_tube_points(300, rng, 0.0, 2 * R_TUBE, R_TUBE)
        rv, t = rng.normal(0, 0.03, 3), np.r_[rng.normal(0, 6e-5, 2), 6e-4]
        m = synth_matches(X1, Rotation.from_rotvec(rv), t, noise_px=1.0, rng=rng)
        s, x = fit_tube(m, CAM, R_TUBE)
        ratio = ring_distance_ratio(m.pts1_px, m.pts2_px, CAM, R_TUBE, x, **EVERY_RATIO)
        ratios.append(ratio * s.distance_m / np.linalg.norm(t))  # the step the ring reads, over the truth
        kept.append(ring_distance_ratio(m.pts1_px, m.pts2_px, CAM, R_TUBE, x))
    assert np.median(ratios) < 0.9
    assert np.sum(np.isfinite(kept)) <= 2
    for k in range(3):
        rng = np.random.default_rng(200 + k)
        X1 = ringed_tube_points(300, rng, 0.45, 2 * R_TUBE, R_TUBE)
        every, _ = _ratio_and_fit(X1, (0.0, 0.0, 0.1), (0.0, 0.0, 0.0041), np.random.default_rng(k), **EVERY_RATIO)
        seen, _ = _ratio_and_fit(X1, (0.0, 0.0, 0.1), (0.0, 0.0, 0.0041), np.random.default_rng(k))
        assert seen == every < 0.9


def test_a_contraction_ring_shortens_the_step_toward_the_truth():
    """Where the lumen narrows by 45% in a ring two radii ahead (as wide as the model's), the cylinder of the prior's
    radius reads the near wall as farther and the step comes out too long; the ring's ratio takes at least half of
    that error back. (A ring narrower than the model's is over-corrected: docs/RESULTS.md, session 39.)"""
    from bodyslam.vision.lumen_scale import RING_WIDTH_RADII

    rng = np.random.default_rng(7)
    t = np.array([0.0, 0.0, 0.0041])
    X1 = ringed_tube_points(300, rng, 0.45, 2.0 * R_TUBE, RING_WIDTH_RADII * R_TUBE)
    ratio, s = _ratio_and_fit(X1, (0.0, 0.0, 0.1), t, rng)
    true_d = motion_from_transform(Rotation.identity(), t).distance_m
    assert s.distance_m > 1.05 * true_d  # the cylinder's reading is long: the test sees the bias it is about
    assert ratio < 0.97
    assert abs(ratio * s.distance_m - true_d) < 0.5 * abs(s.distance_m - true_d)


def test_no_ratio_without_a_step_or_a_fit():
    x = np.zeros(10)
    assert math.isnan(ring_distance_ratio(np.zeros((30, 2)), np.zeros((30, 2)), CAM, R_TUBE, x))  # no length
    x[5] = 0.004
    x[0] = np.nan
    assert math.isnan(ring_distance_ratio(np.zeros((30, 2)), np.zeros((30, 2)), CAM, R_TUBE, x))  # no fit


def test_the_exam_scale_is_the_median_of_enough_ratios():
    r = [0.9] * RING_MIN_SAMPLES + [math.nan, None, -1.0, 5.0]  # not measured / impossible: left out
    assert exam_scale(r, 20) == (pytest.approx(0.9), RING_MIN_SAMPLES + 1)
    few = [0.8] * (RING_MIN_SAMPLES - 1)
    assert exam_scale(few, len(few)) == (1.0, RING_MIN_SAMPLES - 1)  # too few: the prior's scale
    odd = [0.7, 0.8, 0.9, 1.0, 1.1, 5.0, 0.85, 0.95] * (RING_MIN_SAMPLES // 8 + 1)  # an outlier does not move it
    assert exam_scale(odd, 2 * len(odd)) == (pytest.approx(0.925), len(odd))


def test_the_exam_scale_states_its_1_sigma():
    """The factor's relative 1-sigma: its median's scatter (1.2533 x the robust spread of ln r over sqrt(n)) with the
    ring measure's own error (SCALE_SD_FLOOR_REL, chosen on tuning renders) in quadrature; the radius the steps amount
    to takes it where the scale applied, the radius's own 1-sigma where it did not."""
    from scipy.stats import norm

    from bodyslam.vision.lumen_scale import SCALE_SD_FLOOR_REL, exam_scale_sd_rel, radius_sd_rel_after

    assert SCALE_SD_FLOOR_REL == 0.06
    assert exam_scale_sd_rel([0.8] * 30) == pytest.approx(SCALE_SD_FLOOR_REL)  # no scatter: the floor alone
    q = norm.ppf((np.arange(40) + 0.5) / 40)  # ln r spread as a normal of 1-sigma 0.3, 40 ratios
    sd = exam_scale_sd_rel(list(0.8 * np.exp(0.3 * q)) + [math.nan, None, -1.0])  # not measured: left out
    assert sd == pytest.approx(math.hypot(1.2533 * 0.3 / math.sqrt(40), SCALE_SD_FLOOR_REL), rel=0.03)
    # four times the ratios: the median's share halves
    sd4 = exam_scale_sd_rel(list(0.8 * np.exp(0.3 * norm.ppf((np.arange(160) + 0.5) / 160))))
    assert sd4 == pytest.approx(math.hypot(1.2533 * 0.3 / math.sqrt(160), SCALE_SD_FLOOR_REL), rel=0.03)
    assert math.isnan(exam_scale_sd_rel([math.nan]))
    applied = {"applied": True, "factor": 0.8, "factor_sd_rel": sd}
    assert radius_sd_rel_after(applied, 0.2) == sd
    assert radius_sd_rel_after({"applied": False, "factor": 1.0, "factor_sd_rel": None}, 0.2) == 0.2
    assert radius_sd_rel_after(None, 0.2) == 0.2
    assert radius_sd_rel_after({"applied": True, "factor": 0.8}, 0.2) == 0.2  # a summary from before session 63
    # beside it, each step keeps the radius's change over its few millimetres, white (only where a factor applied)
    from bodyslam.steps import StepStatus
    from bodyslam.vision.lumen_scale import SCALE_LOCAL_SD_REL, local_sd_rel_after
    from bodyslam.vision.odometry import with_lumen_uncertainty

    assert SCALE_LOCAL_SD_REL == 0.11
    assert local_sd_rel_after(applied) == SCALE_LOCAL_SD_REL
    assert local_sd_rel_after(None) == 0.0 and local_sd_rel_after({"applied": True, "factor": 0.8}) == 0.0
    step = StepMotion(0.004, 0.0, 0.0, 0.0, 40, StepStatus.OK, t_c1_c2_m=np.array([0.0, 0.0, 0.004]),
                      R_c1_c2=np.eye(3), sigma_distance_m=0.0003)
    one = with_lumen_uncertainty([step], sd, 0.13, SCALE_LOCAL_SD_REL)[0]
    assert one.sigma_distance_m == pytest.approx(math.hypot(0.0003, 0.004 * sd, 0.004 * 0.13, 0.004 * 0.11))


def test_an_exam_shows_rings_only_beyond_what_a_lumen_without_them_lets_through():
    """The ideal `exam` tube (no rings; its radius varies by +-8%) let 10 and 13 of 124 fitted steps through the ring
    test, reading short (median ~0.95): enough ratios, but no more than a lumen without rings shows, so the prior's
    scale stands. Realistic tuning runs show rings on 40-75% of them; 23 rings among ~60 fitted steps (reporting
    seed 709 had 23, one short of the count needed before session 42) are plainly rings."""
    from bodyslam.vision.lumen_scale import RING_NULL_SHARE, shows_rings

    assert RING_MIN_SAMPLES == 12 and RING_NULL_SHARE == 0.10
    assert exam_scale([0.95] * 13, 124) == (1.0, 13) and exam_scale([0.95] * 10, 124) == (1.0, 10)
    assert not shows_rings(20, 124)  # 16% of them: the binomial tail ~0.04, not below 0.01
    assert shows_rings(23, 124) and shows_rings(23, 60) and shows_rings(12, 30)
    assert exam_scale([0.85] * 23, 60) == (pytest.approx(0.85), 23)
    assert not shows_rings(11, 11)  # all of them, but too few for their median to mean much
    # the least count shown grows with the sample, to 22 of a whole exam's ~128 (17%)
    edge = [next(n for n in range(RING_MIN_SAMPLES, tried + 1) if shows_rings(n, tried)) for tried in (30, 60, 128)]
    assert edge == [12, 13, 22]


def test_the_binomial_tail_is_scipys_without_importing_scipy_stats():
    """binomial_tail replaced scipy.stats.binom.sf (whose import cost 0.26-0.58 s at every exam's serial end): the
    same tail to 1e-11 relative wherever it is above 1e-100 (measured: 2e-12 at most for n to 2,000), the edge cases
    exact, and the decision shows_rings makes with it unchanged for every sample size to 300 (both tails fall with
    the count, so the least count that passes decides every count)."""
    import subprocess
    import sys

    from scipy.stats import binom

    from bodyslam.vision.lumen_scale import RING_NULL_SHARE, RING_SHARE_ALPHA, binomial_tail

    for n in (1, 2, 7, 30, 124, 128, 300, 2000):
        for k in sorted({0, 1, n // 10, n // 6, n // 2, n - 1, n, n + 1}):
            for p in (RING_NULL_SHARE, 0.03, 0.5):
                want = float(binom.sf(k - 1, n, p))
                if want > 1e-100:
                    assert binomial_tail(k, n, p) == pytest.approx(want, rel=1e-11), (k, n, p)
    assert binomial_tail(0, 5, 0.3) == 1.0 and binomial_tail(6, 5, 0.3) == 0.0
    assert binomial_tail(1, 5, 0.0) == 0.0 and binomial_tail(5, 5, 1.0) == 1.0
    for n in range(RING_MIN_SAMPLES, 301):
        ours = next((k for k in range(n + 1) if binomial_tail(k, n, RING_NULL_SHARE) < RING_SHARE_ALPHA), None)
        theirs = next((k for k in range(n + 1) if binom.sf(k - 1, n, RING_NULL_SHARE) < RING_SHARE_ALPHA), None)
        assert ours == theirs, n
    # and shows_rings needs no scipy.stats (asked in a fresh interpreter: this one has imported it above)
    code = ("import sys; from bodyslam.vision.lumen_scale import shows_rings; shows_rings(23, 124); "
            "print('scipy.stats' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() \
        == "False"


def test_the_steps_the_ring_was_fitted_to_are_counted_from_their_statuses():
    """ring_tried: the steps fitted from their own matches into sampled positions (statuses[k]: the step into
    position k + 1), which are the ones a chunk fits the ring to."""
    from bodyslam.vision.lumen_scale import ring_tried

    st = ["ok", "wall", "lost", "ok", "rotation", "bridged", "ok", "ok"]  # positions 1..8
    assert ring_tried(st, 1) == 5
    assert ring_tried(st, 2) == 3  # positions 2 (wall), 4 (ok), 8 (ok); 6 is bridged: no fit of its own
    assert ring_tried(st, 0) == 0  # not sampled


def test_the_sample_thins_with_the_exam_and_stays_in_bounds():
    assert ring_every(100) == 1 and ring_every(200) == 2 and ring_every(300) == 3
    assert ring_every(20) == 0 and ring_every(2) == 0  # too short: not sampled (an 18-frame clip is not)
    assert (ring_every(RING_SAMPLE_MIN_STEPS + 1), ring_every(RING_SAMPLE_MIN_STEPS)) == (1, 0)
    for n in (300, 10_000, 55_000):
        every = ring_every(n)
        assert n / every <= RING_SAMPLES_MAX and n / (every - 1) > RING_SAMPLES_MAX


def test_rescaled_moves_the_translation_and_its_sigma_only():
    s = motion_from_transform(Rotation.from_rotvec([0.01, 0.02, 0.1]), np.array([0.001, 0.0, 0.004]), 50,
                              sigma_distance_m=2e-4, sigma_rotation_rad=0.01)
    r = rescaled(s, 0.9)
    assert r.distance_m == pytest.approx(0.9 * s.distance_m)
    assert np.allclose(r.t_c1_c2_m, 0.9 * s.t_c1_c2_m) and r.sigma_distance_m == pytest.approx(1.8e-4)
    assert np.array_equal(r.R_c1_c2, s.R_c1_c2) and r.roll_rad == s.roll_rad and r.tilt_rad == s.tilt_rad
    rot = rotation_step(Rotation.from_rotvec([0.0, 0.0, 0.2]), 30, 0.02)
    assert rescaled(rot, 0.9) is rot
    failed = StepMotion.failed("lost")
    assert rescaled(failed, 0.9) is failed


def test_the_scale_is_measured_only_where_the_radius_is_a_prior():
    """A radius known exactly (the ideal testbed's, or --radius-m) is the scale: nothing to correct; nor is one
    known to within the ring measure's own error (a testbed tube's mean with its spread along the tube: the demo's
    6.5%); the thesis estimator has no tube fit to compare; --no-lumen-scale turns it off."""
    from bodyslam.vision.odometry import LUMEN_SCALE_MIN_PRIOR_SD_REL, MotionSettings, lumen_scale_measured

    assert lumen_scale_measured(MotionSettings(), 0.2)  # bodyslam batch's assumed prior on real frames
    assert lumen_scale_measured(MotionSettings(), LUMEN_SCALE_MIN_PRIOR_SD_REL)
    assert not lumen_scale_measured(MotionSettings(), 0.065)
    assert not lumen_scale_measured(MotionSettings(), 0.0)
    assert not lumen_scale_measured(MotionSettings(estimator="thesis"), 0.2)
    assert not lumen_scale_measured(MotionSettings(lumen_scale=False), 0.2)


def test_what_a_run_says_of_its_lumen_scale():
    from bodyslam.vision.lumen_scale import lumen_scale_summary, lumen_scale_text

    assert "not measured" in lumen_scale_text(None)
    short = lumen_scale_text(lumen_scale_summary(1.0, 0, 0, 0.0125))
    assert "not applied" in short and "too few frames" in short
    assert "--radius-from" in short and "effective_radius_m" in short  # how a clip takes its exam's scale
    few = lumen_scale_text(lumen_scale_summary(1.0, RING_MIN_SAMPLES - 3, 2, 0.0125, tried=40))
    assert (f"{RING_MIN_SAMPLES - 3} of 40 sampled step(s) showed a ring, {RING_MIN_SAMPLES} needed" in few
            and "frames" not in few)
    plain = lumen_scale_text(lumen_scale_summary(1.0, 13, 16, 0.0125, tried=124))
    assert "13 of 124 sampled step(s) showed a ring, no more than the ~10% a lumen without rings shows" in plain
    done = lumen_scale_summary(0.88, 30, 4, 0.0125, tried=70, factor_sd_rel=0.085)
    assert done["effective_radius_m"] == pytest.approx(0.011) and done["applied"] and done["steps_tried"] == 70
    assert done["effective_radius_sd_m"] == pytest.approx(0.011 * 0.085)
    assert ("steps x0.880 +- 8%, the median over the 30 of 70 sampled steps that showed a ring (every 4th step "
            "sampled)" in lumen_scale_text(done))
    assert "1.10 +- 0.09 cm" in lumen_scale_text(done)
    assert lumen_scale_summary(1.0, 5, 4, 0.0125, factor_sd_rel=0.085)["factor_sd_rel"] is None  # not applied
    assert "(every step sampled)" in lumen_scale_text(lumen_scale_summary(0.9, 30, 1, 0.0125))
    said = [lumen_scale_text(lumen_scale_summary(0.9, 30, n, 0.0125)) for n in (2, 3, 11, 21, 22, 112)]
    assert [t.split("(every ")[1].split(" step")[0] for t in said] == ["2nd", "3rd", "11th", "21st", "22nd", "112th"]


def test_motion_and_batch_apply_the_same_lumen_scale(tmp_path, monkeypatch):
    """``bodyslam motion``'s engine (sequence_motion) and ``batch`` (chunks, then the scale from their rows) write the
    same motion.csv with the lumen scale applied, byte for byte. The demo tells its radius to within its spread along
    the tube (6.5%: not measured), so the copy here makes it a wide prior; the least sample is lowered to fit its 40
    frames, and every ring fitted counts (the demo's tube has no contraction rings). The steps counted as fitted
    with the ring are the ones it was fitted to."""
    import json
    import shutil

    from bodyslam.exam.batch import BatchSettings, open_exams, run_batch
    from bodyslam.io import write_motion_csv
    from bodyslam.vision import lumen_scale
    from bodyslam.vision.odometry import MotionSettings, sequence_motion
    from tests.bodyslam.exam.test_batch import DEMO

    monkeypatch.setattr(lumen_scale, "RING_MIN_SAMPLES", 4)
    monkeypatch.setattr(lumen_scale, "RING_MIN_COST_DROP", -np.inf)
    monkeypatch.setattr(lumen_scale, "RING_MIN_DROP_SIGNIFICANCE", -np.inf)
    seq = tmp_path / "seq"
    shutil.copytree(DEMO, seq, ignore=shutil.ignore_patterns("depth"))
    meta = json.loads((seq / "meta.json").read_text())
    meta["tube_radius_sd_m"] = 0.2 * meta["tube_radius_m"]
    (seq / "meta.json").write_text(json.dumps(meta))
    settings = MotionSettings(match_mode="fast")
    used: list = []
    fits = []  # every ring fit the chunks run: the count ring_tried gives from the statuses
    ratio = lumen_scale.ring_distance_ratio
    monkeypatch.setattr(lumen_scale, "ring_distance_ratio", lambda *a, **k: fits.append(1) or ratio(*a, **k))
    from bodyslam.vision import odometry

    radius_shares = []  # the radius's relative 1-sigma each step's 1-sigma is given, and the local share
    share = odometry.with_lumen_uncertainty
    monkeypatch.setattr(odometry, "with_lumen_uncertainty",
                        lambda st, r, shape, local: radius_shares.append((r, local)) or share(st, r, shape, local))
    steps = sequence_motion(seq, settings, jobs=1, lumen_scale_used=used)
    assert used[0]["applied"] and used[0]["factor"] != 1.0
    assert used[0]["steps_tried"] == len(fits) > 20
    stamps = np.arange(len(steps) + 1) / meta["frame_rate_hz"]
    write_motion_csv(tmp_path / "motion.csv", range(1, len(steps) + 1), stamps[1:], steps)
    run_batch(open_exams([str(seq)]), tmp_path / "batch", BatchSettings(settings, chunk_frames=7), jobs=1)
    assert (tmp_path / "motion.csv").read_text() == (tmp_path / "batch" / "seq" / "motion.csv").read_text()
    summary = json.loads((tmp_path / "batch" / "seq" / "summary.json").read_text())
    assert summary["lumen_scale"]["factor"] == used[0]["factor"]
    # the path travelled from the rescaled steps, as bodyslam motion and testbed's scoring take it: its missing
    # steps' model in radii of the prior (not rescaled: docs/RESULTS.md, session 39)
    from bodyslam.io import read_motion_steps
    from bodyslam.steps import lost_to_motion
    from bodyslam.vision.tracking import path_travelled

    assert any(lost_to_motion(s) for s in steps)  # a step the missing steps' model fills
    # the measured factor's 1-sigma, not the prior's 20%, is the radius's now: in the summary, in each step's 1-sigma,
    # and the same from motion.csv's ring ratios (bodyslam localize --motion, testbed evaluate)
    rel = used[0]["factor_sd_rel"]
    assert SCALE_SD_FLOOR_REL <= rel < 0.2 and summary["lumen_scale"]["factor_sd_rel"] == rel
    assert lumen_scale.radius_sd_rel_after(used[0], 0.2) == rel
    again = lumen_scale.scale_of_steps(read_motion_steps(tmp_path / "motion.csv", range(1, len(steps) + 1)), True)
    # (motion.csv keeps 9 digits of each ratio)
    assert again["factor"] == pytest.approx(used[0]["factor"], rel=1e-8)
    assert again["factor_sd_rel"] == pytest.approx(rel, rel=1e-8)
    # what motion and batch put in every step's 1-sigma
    assert set(radius_shares) == {(rel, lumen_scale.SCALE_LOCAL_SD_REL)}
    assert summary["lumen_scale"]["local_sd_rel"] == lumen_scale.SCALE_LOCAL_SD_REL
    path, var = path_travelled(steps, rel, meta["tube_radius_m"])
    # testbed score-motion states the same path 1-sigma from motion.csv's ring ratios
    from testbed.cli import main as testbed_main

    assert testbed_main(["score-motion", str(seq), str(tmp_path / "motion.csv"), "--json",
                         str(tmp_path / "score.json")]) == 0
    scored = json.loads((tmp_path / "score.json").read_text())["path_travelled"]
    assert scored["sigma_m"] == pytest.approx(math.sqrt(var[-1]), rel=1e-6)
    assert summary["path_travelled_m"] == pytest.approx(path[-1], rel=1e-6)
    assert summary["sd_path_travelled_m"] == pytest.approx(math.sqrt(var[-1]), rel=1e-6)


def test_compiled_ring_residuals_equal_numpys_at_the_edges():
    """The compiled ring residuals (bodyslam/vision/_tube_fit.c) against numpy's where they could part: a ray that
    never leaves the tube inside the depth cap (along the axis), a wall crossed before the grid's first depth (the
    camera outside the ringed wall), rings deep, shallow and behind the camera, the Rodrigues series' switch, and a
    batch of forward differences as the fit builds it (its Jacobian)."""
    from bodyslam.vision import lumen_scale

    if lumen_scale._tube_c is None:
        pytest.skip("the compiled residuals are not built here")
    rng = np.random.default_rng(5)
    b1 = rng.normal(size=(60, 3))
    b1[:, 2] = np.abs(b1[:, 2]) + 0.05
    b1[0] = (0.0, 0.0, 1.0)  # along the axis: no crossing
    b1 /= np.linalg.norm(b1, axis=1)[:, None]
    b2 = b1 + rng.normal(0, 0.02, b1.shape)
    b2 /= np.linalg.norm(b2, axis=1)[:, None]
    P = np.zeros((8, 12))
    P[:, 3:6] = (0.0005, -0.001, 0.004)
    P[:, 10:12] = (0.3, 2.0)
    P[0, 0:3] = (3e-5, -2e-5, 1e-5)  # series branch
    P[1, 0:3], P[1, 10:12] = (1.2e-4, 0.0, 0.0), (3.0, 0.5)  # just above the switch; a deep ring near the camera
    P[2, 0:3], P[2, 6:12] = (0.1, -0.2, 0.15), (0.1, -0.05, 0.002, -0.001, -0.4, 3.5)  # a bulge, not a ring
    P[3, 8], P[3, 11] = 0.011, -1.0  # the camera 0.88 radii off the axis; the ring behind it
    P[4, 8], P[4, 10:12] = 0.012, (5.0, 0.3)  # the wall crossed before the first depth
    P[5:] = P[2] + np.diag(1e-6 * np.r_[[0.05] * 3, [0.003] * 3, [0.2] * 2, [0.005] * 2, 0.1, 0.5])[[0, 5, 11]]
    grid = (np.arange(1, lumen_scale.RING_GRID + 1) / lumen_scale.RING_GRID) ** 2
    got = lumen_scale._ring_residuals(P, b1, b2, R_TUBE, 0.3, 0.003, grid, 2.0)
    want = lumen_scale._ring_residuals_numpy(P, b1, b2, R_TUBE, 0.3, 0.003, grid, 2.0)
    assert np.isfinite(want).all() and got.shape == want.shape == (8, 3 * 60 + 6)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    fd_got, fd_want = (got[5:] - got[2]) / 1e-6, (want[5:] - want[2]) / 1e-6  # the fit's Jacobian columns
    np.testing.assert_allclose(fd_got, fd_want, rtol=1e-4, atol=1e-4 * np.abs(fd_want).max())
    with pytest.raises(ValueError, match="float64 arrays"):
        lumen_scale._tube_c.ring_residuals(P, b1, b2[:-1], R_TUBE, 0.3, 0.003, np.ones(4), grid, np.ones(5),
                                           np.empty_like(got))


def test_the_compiled_ring_fit_is_numpys_loop(monkeypatch):
    """The ring fit runs the compiled loop (``_tube_fit.lm``, model 1; session 67) where it is built: the same ratio,
    cost drop and residual scale as numpy's loop (:func:`bodyslam.vision.motion._lm_soft_l1`) on a ring that is
    there and on a plain cylinder, to 1e-6 (measured 5e-9: the loops differ only in the order of a few sums; a
    ratio is read to ~1e-2). Its motion columns reuse the rays' depths, its ring columns do not: both must hold
    for this to."""
    from bodyslam.vision import lumen_scale, motion

    if motion._tube_c is None or not hasattr(motion._tube_c, "lm"):
        pytest.skip("bodyslam/vision/_tube_fit.c is not built here")
    for depth in (0.45, 0.0):
        rng = np.random.default_rng(11)
        X1 = ringed_tube_points(300, rng, depth, 2.0 * R_TUBE, R_TUBE)
        m = synth_matches(X1, Rotation.from_rotvec((0.0, 0.02, 0.1)), np.array([0.0002, 0.0, 0.0041]),
                          noise_px=0.3, rng=rng)
        _, x = fit_tube(m, CAM, R_TUBE)
        b1, _ = CAM.unproject(m.pts1_px[:150])
        b2, _ = CAM.unproject(m.pts2_px[:150])
        got = lumen_scale._ring_ratio_rays(b1, b2, R_TUBE, x, 0.003, 0.3)
        monkeypatch.setattr(motion, "LM_COMPILED", False)
        want = lumen_scale._ring_ratio_rays(b1, b2, R_TUBE, x, 0.003, 0.3)
        monkeypatch.setattr(motion, "LM_COMPILED", True)
        assert np.all(np.isfinite(want))
        np.testing.assert_allclose(got, want, rtol=1e-6)
        if depth:
            assert want[0] < 0.97 and want[1] > 10  # a ring the fit sees: the test compares a fit that moved

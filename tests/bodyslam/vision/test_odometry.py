"""The one visual-odometry engine: every command that turns frames into steps gives the same steps."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bodyslam.io import read_image, write_image
from bodyslam.vision.tracking import path_from_lengths

DEMO = Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0"


def run(*args):
    return subprocess.run([sys.executable, "-m", "bodyslam.cli", *args], capture_output=True, text=True)


def _with_wall_frames(dst: Path, dark: tuple[int, ...] = (), insert_dark_after: int | None = None,
                      radius_sd_m: float | None = None) -> Path:
    """The demo sequence with frames blacked out (a capsule against the wall: classified FL), and optionally a
    dark frame inserted after frame ``insert_dark_after`` (the capsule looks at the wall for a moment and comes
    back to the view it left)."""
    import json

    shutil.copytree(DEMO, dst, ignore=shutil.ignore_patterns("depth", "frames"))
    (dst / "frames").mkdir()
    src = [DEMO / "frames" / f"{k:06d}.png" for k in range(40)]
    if insert_dark_after is not None:
        src.insert(insert_dark_after + 1, None)
    for k, f in enumerate(src):
        img = read_image(f if f is not None else src[0])
        write_image(dst / "frames" / f"{k:06d}.png", np.zeros_like(img) if f is None or k in dark else img)
    meta = json.loads((dst / "meta.json").read_text())
    meta["n_frames"] = len(src)
    if radius_sd_m is not None:  # the radius a prior, as on real exams: the steps' scales are chained
        meta["tube_radius_sd_m"] = radius_sd_m
    (dst / "meta.json").write_text(json.dumps(meta))
    return dst


@pytest.mark.parametrize("opts, radius_sd_m", [(["--mode", "fast"], None), (["--mode", "sift"], 0.0025),
                                               (["--mode", "sift", "--estimator", "thesis", "--unroll-mode", "thesis"],
                                                None)])
def test_motion_and_batch_write_identical_motion_csv(tmp_path, opts, radius_sd_m):
    """Same frames, same settings: ``bodyslam motion`` and ``bodyslam batch`` write the same file, byte for
    byte -- gap bridging included (frames 30-31 face the wall, so steps 30-32 have no estimate of their own and
    are bridged by matching frame 29 with 32; a dark frame inserted after 13 makes a gap whose ends are consecutive
    frames of the sequence: bridged too, in fast mode) and the thesis estimator's unroll mode honoured (both were
    lost in batch before the engine was shared; the thesis estimator gives no pose to bridge with). With the
    radius a prior, the steps' scales are tied to their neighbours' (bodyslam.vision.scale_chain), across the
    batch's chunk seams too."""
    seq = _with_wall_frames(tmp_path / "seq", dark=(30, 31), insert_dark_after=13, radius_sd_m=radius_sd_m)
    p = run("motion", str(seq), "--out", str(tmp_path / "motion.csv"), "--jobs", "1", *opts)
    assert p.returncode == 0, p.stderr
    p = run("batch", str(seq), "--out", str(tmp_path / "batch"), "--jobs", "1", "--chunk-frames", "7", *opts)
    assert p.returncode == 0, p.stdout + p.stderr
    a = (tmp_path / "motion.csv").read_text()
    b = (tmp_path / "batch" / "seq" / "motion.csv").read_text()
    assert a == b
    rows = list(csv.DictReader(a.splitlines()))
    status = {int(r["frame"]): r["status"] for r in rows}
    links = [float(r["scale_link"]) for r in rows]
    chained = [float(r["chain_factor"]) for r in rows]
    if radius_sd_m:  # links between the fitted steps, seams included (every 7th step starts a chunk in batch)
        assert sum(map(np.isfinite, links)) > 20 and sum(map(np.isfinite, chained)) > 20
        assert np.isfinite([links[k - 1] for k in (8, 22) if status[k] == "ok" and status[k - 1] == "ok"]).all()
    else:  # a known radius is the scale: nothing chained
        assert not any(map(np.isfinite, chained))
    chunks = [json.loads(f.read_text()) for f in sorted((tmp_path / "batch" / "seq" / "chunks").glob("*.json"))]
    if "--estimator" not in opts:
        assert [status[k] for k in (14, 15, 30, 31, 32)] == ["bridged"] * 5
        # the gap of steps 30-32 lies inside the chunk of positions 28-35: its worker bridged it; the gap of steps
        # 14-15 spans the seam at position 14: bridged once all chunks were in
        inside = [tuple(g) for c in chunks for g in c["gaps"]]
        by_worker = {int(k) for c in chunks for k in c["bridged"]}
        assert (29, 32) in inside and (13, 15) not in inside
        assert {29, 30, 31} <= by_worker and not {13, 14} & by_worker
    else:  # the thesis estimator gives no full pose to bridge with: the gaps stay gaps
        assert [status[k] for k in (14, 15, 30, 31, 32)] == ["no_lumen"] * 5


def test_path_rule_is_the_same_forwards_and_backwards():
    """Runs without an estimate at the start, inside and at the end take the mean of their estimated
    neighbours, so reversing the steps reverses nothing but their order: the total path is identical."""
    nan = np.nan
    length = np.array([nan, nan, 1.0, 2.0, nan, nan, nan, 4.0, 3.0, nan])
    var = np.where(np.isfinite(length), 0.01, 0.0)
    fwd, vf = path_from_lengths(length, var)
    bwd, vb = path_from_lengths(length[::-1], var[::-1])
    assert fwd[-1] == pytest.approx(bwd[-1], rel=1e-15) and vf[-1] == pytest.approx(vb[-1], rel=1e-15)
    # start: the first estimate (1.0) twice; inside: mean(2, 4) three times; end: the last estimate (3.0)
    assert fwd[-1] == pytest.approx(2 * 1.0 + 1 + 2 + 3 * 3.0 + 4 + 3 + 3.0)
    assert path_from_lengths(np.full(3, nan), np.zeros(3))[0][-1] == 0.0


def test_a_clip_played_backwards_travels_the_same_path(tmp_path):
    """The demo clip as a plain folder, forwards and with its frames in reverse order: the paths batch
    reports agree within their stated 1-sigma (was 2.3 against 0.9 cm on a real clip: unestimated steps at
    the end repeated the last step, at the start they added nothing)."""
    fwd, bwd = tmp_path / "fwd", tmp_path / "bwd"
    fwd.mkdir()
    bwd.mkdir()
    for k in range(40):
        shutil.copy(DEMO / "frames" / f"{k:06d}.png", fwd / f"f_{k:03d}.png")
        shutil.copy(DEMO / "frames" / f"{k:06d}.png", bwd / f"f_{39 - k:03d}.png")
    paths = []
    for d in (fwd, bwd):
        p = run("batch", str(d), "--out", str(tmp_path / f"out_{d.name}"), "--jobs", "1", "--radius-m", "0.0138")
        assert p.returncode == 0, p.stdout + p.stderr
        s = __import__("json").loads((tmp_path / f"out_{d.name}" / d.name / "summary.json").read_text())
        paths.append((s["path_travelled_m"], s["sd_path_travelled_m"]))
    (a, sa), (b, sb) = paths
    assert abs(a - b) <= np.hypot(sa, sb), paths
    assert 0.10 < a < 0.25  # the demo capsule travels 16 cm in 40 frames (truth.json); the tube fit scales it


def test_the_k_step_check_tells_an_honest_1sigma_from_an_optimistic_one():
    """Pairs: non-overlapping runs of 3 estimated steps, spread over the exam. Diagnostic: 2000 synthetic pairs
    whose straight 3-frame distance differs from the composed single steps by noise of the stated size give ~68%
    within 1-sigma and ~95% within 2 (the 2000 draws' sampling error is ~1%: margins 4%); the same errors stated
    4x too small give ~20%."""
    from scipy.spatial.transform import Rotation

    from bodyslam.steps import StepMotion, StepStatus, motion_from_transform
    from bodyslam.vision.odometry import consistency_diagnostic, consistency_pairs

    ok, bad = StepStatus.OK, StepStatus.TOO_FEW_MATCHES
    assert consistency_pairs([ok, ok, ok, ok, bad, ok, ok, ok, ok, ok, ok]) == [(0, 3), (5, 8), (8, 11)]
    assert len(consistency_pairs([ok] * 3000, max_pairs=30)) == 30
    rng = np.random.default_rng(1)

    def run(stated_scale):
        singles, totals = [], []
        for _ in range(2000):
            ks = [motion_from_transform(Rotation.identity(), [0, 0, 0.003], 50, 2e-4 * stated_scale, 0.01)
                  for _ in range(3)]
            true_sigma = np.sqrt(4 * (2e-4) ** 2)  # three singles and the pair, each 0.2 mm
            d = 0.009 + rng.normal(0, true_sigma)
            totals.append(motion_from_transform(Rotation.identity(), [0, 0, d], 50, 2e-4 * stated_scale, 0.01))
            singles.append(ks)
        return consistency_diagnostic(singles, totals)

    honest, optimistic = run(1.0), run(0.25)
    assert honest["pairs_estimated"] == 2000 and honest["k"] == 3
    assert abs(honest["within_1sigma"] - 0.683) < 0.04 and abs(honest["within_2sigma"] - 0.954) < 0.03
    assert optimistic["within_1sigma"] < 0.3
    assert honest["median_distance_ratio_pair_over_singles"] == pytest.approx(1.0, abs=0.01)
    assert consistency_diagnostic([[StepMotion.failed(bad)] * 3], [None])["pairs_estimated"] == 0
    assert "stated_within_1sigma" not in honest  # no lumen-shape share (the ideal tube): the fit's own only

    # the fit's own 1-sigma (0.05 mm) leaves out a lumen-shape share of 2% of each estimate's distance; counted as
    # the steps state it, the check reads honest, where the fit's own alone reads optimistic
    shape, fit_sd = 0.02, 5e-5
    singles, totals = [], []
    for _ in range(2000):
        singles.append([motion_from_transform(Rotation.identity(), [0, 0, 0.003], 50, fit_sd, 0.01)
                        for _ in range(3)])
        true_sd = np.sqrt(4 * fit_sd**2 + 3 * (shape * 0.003) ** 2 + (shape * 0.009) ** 2)
        totals.append(motion_from_transform(Rotation.identity(), [0, 0, 0.009 + rng.normal(0, true_sd)], 50, fit_sd,
                                            0.01))
    c = consistency_diagnostic(singles, totals, shape_sd_rel=shape)
    assert c["within_1sigma"] < 0.45 and c["lumen_shape_sd_rel"] == shape
    assert abs(c["stated_within_1sigma"] - 0.683) < 0.04 and abs(c["stated_within_2sigma"] - 0.954) < 0.03


@pytest.mark.parametrize("settings_kw, status", [({}, "wall"), ({"wall_steps": "drop"}, "no_lumen"),
                                                  ({"estimator": "thesis"}, "no_lumen")])
def test_a_step_facing_the_wall_is_estimated_by_the_tube_fit_with_a_wider_1sigma(settings_kw, status):
    """By default a step touching an FL frame is fitted like any other (the tube fit needs the wall, not the
    lumen, in view) and says so: status wall, the same motion, its 1-sigma times WALL_SIGMA_FACTOR. The
    dissertation's rule (drop it) is one setting away, and the thesis estimator, whose unrolling needs the lumen
    in view, always drops it."""
    from bodyslam.meta import read_meta
    from bodyslam.vision.odometry import WALL_SIGMA_FACTOR, MotionSettings, VisualOdometry

    meta = read_meta(DEMO)
    vo = VisualOdometry(meta.camera_model(), MotionSettings(**settings_kw), meta.tube_radius_m)
    f1, f2 = (vo.matcher.features(read_image(DEMO / "frames" / f"{k:06d}.png")) for k in (10, 11))
    s, w = vo.estimate_pair(f1, f2), vo.estimate_wall(f1, f2)
    assert w.status == status
    if status == "wall":
        assert s.ok and w.ok and w.has_estimate
        assert w.distance_m == s.distance_m and np.array_equal(w.t_c1_c2_m, s.t_c1_c2_m)
        assert w.sigma_distance_m == pytest.approx(WALL_SIGMA_FACTOR * s.sigma_distance_m, rel=1e-12)
        assert w.sigma_rotation_rad == pytest.approx(WALL_SIGMA_FACTOR * s.sigma_rotation_rad, rel=1e-12)
    else:
        assert not w.has_estimate and np.isnan(w.distance_m)


def test_a_fit_that_puts_the_camera_beside_its_tube_wall_gets_a_wider_1sigma(monkeypatch):
    """A tube fit whose cylinder passes more than BESIDE_WALL_RADII radii from the camera (where no capsule fits
    in a cylindrical lumen) gets BESIDE_WALL_SIGMA_RADII lumen radii in its 1-sigma distance (in quadrature) and
    its rotation's 1-sigma times BESIDE_WALL_ROTATION_FACTOR; one nearer the axis keeps the fit's own 1-sigmas.
    With BESIDE_WALL_HELD_AXIS off (here) the flagged fit keeps its motion; on, its motion is the held fit's (the
    next test). The demo pair's fit is used with its axis moved to 0.7 and 0.9 radii from the camera,
    tilted 30 degrees (the distance is measured square to the axis: the offset in the image plane is larger by
    1/cos 30). Between frames facing the tunnel (``ahead``) an axis tilted more than ACROSS_TILT_RAD widens it
    too (50 degrees, 0.2 radii from the camera), and only there."""
    import math

    from bodyslam.meta import read_meta
    from bodyslam.vision.motion import axis_tilt_rad, camera_off_axis_radii
    from bodyslam.vision import odometry
    from bodyslam.vision.odometry import (ACROSS_TILT_RAD, BESIDE_WALL_RADII, BESIDE_WALL_ROTATION_FACTOR,
                                          BESIDE_WALL_SIGMA_RADII, MotionSettings, VisualOdometry)

    monkeypatch.setattr(odometry, "BESIDE_WALL_HELD_AXIS", False)
    meta = read_meta(DEMO)
    R = meta.tube_radius_m
    vo = VisualOdometry(meta.camera_model(), MotionSettings(), R)
    f1, f2 = (vo.matcher.features(read_image(DEMO / "frames" / f"{k:06d}.png")) for k in (10, 11))
    plain = vo.estimate_pair(f1, f2)
    assert plain.ok and not plain.beside_wall
    fit = vo._fit

    def with_axis(tilt_deg, off):
        """The fit, its axis tilted toward +x and passing ``off`` radii from the camera (the offset in the image
        plane, along the tilt, is larger by 1 / cos(tilt))."""
        def fitted(m, estimator=None):
            s, x = fit(m, estimator)
            x = x.copy()
            x[6:10] = math.tan(math.radians(tilt_deg)), 0.0, off * R / math.cos(math.radians(tilt_deg)), 0.0
            assert camera_off_axis_radii(x, R) == pytest.approx(off, rel=1e-9)
            assert axis_tilt_rad(x) == pytest.approx(math.radians(tilt_deg), rel=1e-9)
            return s, x
        return fitted

    for off in (0.7, 0.9):
        monkeypatch.setattr(vo, "_fit", with_axis(30.0, off))
        s = vo.estimate_pair(f1, f2)
        assert s.distance_m == plain.distance_m and np.array_equal(s.t_c1_c2_m, plain.t_c1_c2_m)
        want = (math.hypot(plain.sigma_distance_m, BESIDE_WALL_SIGMA_RADII * R) if off > BESIDE_WALL_RADII
                else plain.sigma_distance_m)
        assert s.sigma_distance_m == pytest.approx(want, rel=1e-12)
        assert s.sigma_rotation_rad == pytest.approx(plain.sigma_rotation_rad * (
            BESIDE_WALL_ROTATION_FACTOR if off > BESIDE_WALL_RADII else 1.0), rel=1e-12)
        assert s.beside_wall == (off > BESIDE_WALL_RADII)  # and says so (motion.csv's beside_wall column)
    assert want > 2 * plain.sigma_distance_m  # the widening is not lost in the fit's own 1-sigma

    monkeypatch.setattr(vo, "_fit", with_axis(50.0, 0.2))
    assert math.degrees(ACROSS_TILT_RAD) < 50.0
    assert vo.estimate_pair(f1, f2).sigma_distance_m == plain.sigma_distance_m
    across = vo.estimate_pair(f1, f2, ahead=True)
    assert across.sigma_distance_m == pytest.approx(want, rel=1e-12) and across.beside_wall


def test_a_fit_beside_the_wall_is_fitted_again_with_the_axis_held(monkeypatch):
    """BESIDE_WALL_HELD_AXIS: a tube fit that puts the camera beside the wall of its own cylinder (made so here: the
    demo pair's fit with its axis moved to 0.9 radii from the camera) takes the motion of the same matches fitted
    with the axis held on the optical axis and the camera on it (fit_tube's hold_axis, from the free fit's motion
    and from a forward step), its 1-sigmas widened as any fit beside the wall, and its flag; the scale chain's
    points are triangulated with the held fit; the ring ratio (the lumen scale's sample) stays the free fit's. A
    fit flagged only for its axis across the view (a turn: 50 deg, 0.2 radii) keeps its own motion. Where the held
    fit fails, the free fit stays."""
    import math

    from bodyslam.meta import read_meta
    from bodyslam.steps import StepMotion
    from bodyslam.vision import motion, odometry
    from bodyslam.vision.odometry import (BESIDE_WALL_ROTATION_FACTOR, BESIDE_WALL_SIGMA_RADII, MotionSettings,
                                          VisualOdometry)

    assert odometry.BESIDE_WALL_HELD_AXIS
    meta = read_meta(DEMO)
    R = meta.tube_radius_m
    vo = VisualOdometry(meta.camera_model(), MotionSettings(), R)
    f1, f2 = (vo.matcher.features(read_image(DEMO / "frames" / f"{k:06d}.png")) for k in (10, 11))
    plain = vo.estimate_pair(f1, f2)
    fit, seen = vo._fit, {}

    def beside(m, estimator=None):
        s, x = fit(m, estimator)
        x = x.copy()
        x[6:10] = 0.0, 0.0, 0.9 * R, 0.0
        seen["m"], seen["x"] = m, x
        return s, x

    monkeypatch.setattr(vo, "_fit", beside)
    s = vo.estimate_pair(f1, f2)
    from bodyslam.vision import lumen_scale

    monkeypatch.setattr(lumen_scale, "ring_distance_ratio", lambda *a: 0.83)  # the free fit's, as on every step
    assert vo.estimate_pair(f1, f2, ring=True).ring_ratio == 0.83 and np.isnan(s.ring_ratio)
    forward = np.zeros(10)
    forward[0:3] = seen["x"][0:3]
    forward[5] = motion.ESSENTIAL_START_STEP * R
    held, xh = motion.fit_tube(seen["m"], vo.camera, R, hold_axis=True, starts=[seen["x"], forward])
    assert held.ok and s.beside_wall and s.distance_m != plain.distance_m
    assert s.distance_m == pytest.approx(held.distance_m, rel=1e-12)
    assert s.roll_rad == pytest.approx(held.roll_rad, abs=1e-12)
    assert s.tilt_rad == pytest.approx(held.tilt_rad, abs=1e-12)
    assert s.sigma_distance_m == pytest.approx(math.hypot(held.sigma_distance_m, BESIDE_WALL_SIGMA_RADII * R),
                                               rel=1e-12)
    assert s.sigma_rotation_rad == pytest.approx(held.sigma_rotation_rad * BESIDE_WALL_ROTATION_FACTOR, rel=1e-12)
    sig = vo.signatures
    from bodyslam.vision.scale_chain import step_signatures

    want = step_signatures(seen["m"].pts1_px, seen["m"].pts2_px, xh, vo.camera)
    assert np.array_equal(sig[0].log_depth, want[0].log_depth)

    def across(m, estimator=None):  # the axis 50 deg off the view, 0.2 radii from the camera: a turn, not the wall
        s, x = fit(m, estimator)
        x = x.copy()
        x[6:10] = math.tan(math.radians(50.0)), 0.0, 0.2 * R / math.cos(math.radians(50.0)), 0.0
        return s, x

    monkeypatch.setattr(vo, "_fit", across)
    turn = vo.estimate_pair(f1, f2, ahead=True)
    assert turn.beside_wall and turn.distance_m == plain.distance_m and turn.tilt_rad == plain.tilt_rad

    monkeypatch.setattr(vo, "_fit", beside)
    failed = StepMotion(n_matches=5, status="too_few_matches")
    free_fit = motion.fit_tube
    monkeypatch.setattr(motion, "fit_tube", lambda *a, **k: (failed, None) if k.get("hold_axis") else free_fit(*a, **k))
    kept = vo.estimate_pair(f1, f2)
    assert kept.beside_wall and kept.distance_m == pytest.approx(plain.distance_m, rel=1e-12)


def test_a_fit_beside_the_wall_without_parallax_is_a_capsule_at_rest(monkeypatch):
    """REST_PARALLAX_PX: a demo frame and the same frame turned 5 degrees about the principal point (a capsule
    rolling in place: no parallax) fitted beside the wall (made so, as above) is reported at rest -- distance 0,
    REST_SIGMA_RADII radii of 1-sigma, the roll of the pure rotation, not flagged; with the rule off it is the held
    fit beside the wall. The moving pair of the test above keeps its held fit (that test)."""
    import math

    import cv2

    from bodyslam.meta import read_meta
    from bodyslam.vision import odometry
    from bodyslam.vision.odometry import REST_SIGMA_RADII, MotionSettings, VisualOdometry

    meta = read_meta(DEMO)
    R = meta.tube_radius_m
    cam = meta.camera_model()
    vo = VisualOdometry(cam, MotionSettings(), R)
    img = read_image(DEMO / "frames" / "000010.png")
    turned = cv2.warpAffine(img, cv2.getRotationMatrix2D((cam.cx, cam.cy), 5.0, 1.0), img.shape[1::-1],
                            flags=cv2.INTER_CUBIC)
    fit = vo._fit

    def beside(m, estimator=None):
        s, x = fit(m, estimator)
        x = x.copy()
        x[6:10] = 0.0, 0.0, 0.9 * R, 0.0
        return s, x

    monkeypatch.setattr(vo, "_fit", beside)
    s = vo.estimate_pair(vo.matcher.features(img), vo.matcher.features(turned))
    assert s.ok and not s.beside_wall and s.distance_m == 0.0 and np.array_equal(s.t_c1_c2_m, np.zeros(3))
    assert s.sigma_distance_m == pytest.approx(REST_SIGMA_RADII * R) and vo.signatures is None
    assert abs(math.degrees(s.roll_rad)) == pytest.approx(5.0, abs=0.2) and math.degrees(s.tilt_rad) < 0.2
    monkeypatch.setattr(odometry, "REST_PARALLAX_PX", 0.0)
    held = vo.estimate_pair(vo.matcher.features(img), vo.matcher.features(turned))
    assert held.beside_wall and held.sigma_distance_m > 5 * REST_SIGMA_RADII * R


def test_an_unknown_wall_step_rule_is_refused():
    from bodyslam.errors import ConfigError
    from bodyslam.vision.odometry import MotionSettings

    with pytest.raises(ConfigError, match="wall_steps must be one of estimate, drop"):
        MotionSettings(wall_steps="keep")


def test_fast_mode_rescue_fits_a_step_the_cheaper_tries_lose_and_can_be_turned_off():
    """Demo step 1 (thesis motion, 1.006 cm true): tracking and SIFT at 0.5 / 0.7 scale verify ~10 matches, so
    without the rescue the step is lost to motion; SIFT on the full frame fits it (status ok, 1.02 cm measured;
    bounds 0.7-1.3 cm: a wrong minimum of the tube fit lands far outside). ``--no-rescue`` reaches the engine from
    the commands' options."""
    from bodyslam.cli import _motion_settings, _parser
    from bodyslam.meta import read_meta
    from bodyslam.vision.odometry import MotionSettings, VisualOdometry

    meta = read_meta(DEMO)
    f0, f1 = (read_image(DEMO / "frames" / f"{k:06d}.png") for k in (0, 1))
    out = {}
    for rescue in (True, False):
        vo = VisualOdometry(meta.camera_model(), MotionSettings("fast", classify=False, rescue=rescue),
                            meta.tube_radius_m)
        out[rescue] = vo.estimate_pair(vo.matcher.features(f0), vo.matcher.features(f1))
    assert out[False].status == "lost" and not out[False].ok
    assert out[True].ok and 0.007 < out[True].distance_m < 0.013
    for cmd in ("motion", "batch"):
        args = _parser().parse_args([cmd, str(DEMO), "--out", "x", "--no-rescue"])
        assert _motion_settings(args).rescue is False
        assert _motion_settings(_parser().parse_args([cmd, str(DEMO), "--out", "x"])).rescue is True


def test_fast_mode_tries_the_07_scale_last_where_the_rescues_fit_fails_and_keeps_its_result_else(monkeypatch):
    """With the rescue, a pair whose rescue verified enough matches but whose fit failed (``uncertain``) gets the
    0.7-scale try last (session 72: skipping it cost realistic seeds 916-919 ten of 574 fitted steps): its fit is
    taken where it succeeds, and where it fails too the rescue's result stands (its match count, so ``lost`` keeps
    its meaning). A rescue with too few matches is not followed (0.7's fewer keypoints never fitted such a pair).
    In sift mode nothing follows."""
    from bodyslam.meta import read_meta
    from bodyslam.steps import StepMotion, StepStatus
    from bodyslam.vision.odometry import MotionSettings, VisualOdometry

    meta = read_meta(DEMO)
    f3, f4 = (read_image(DEMO / "frames" / f"{k:06d}.png") for k in (3, 4))
    vo = VisualOdometry(meta.camera_model(), MotionSettings("fast", classify=False), meta.tube_radius_m)
    a, b = vo.matcher.features(f3), vo.matcher.features(f4)
    tries = list(vo.matcher.cascade(a, b))
    last = vo.matcher.last_resort(a, b)
    assert len(last) != len(tries[-1])  # the two tries are told apart by their matches
    fit, seen = vo._fit, []

    def fails_but(accept, status=StepStatus.UNCERTAIN):
        def fitted(m, estimator=None):
            seen.append(m)
            if accept is not None and len(m) == len(accept) and np.array_equal(m.pts1_px, accept.pts1_px):
                return fit(m, estimator)
            return StepMotion(n_matches=len(m), status=status), None
        return fitted

    monkeypatch.setattr(vo, "_fit", fails_but(last))
    s = vo.estimate_pair(a, b, rotation=False)
    want = vo.to_body(fit(last, None)[0])
    assert s.ok and len(seen) == len(tries) + 1 and s.distance_m == want.distance_m and s.n_matches == len(last)
    for accept, status in ((None, StepStatus.UNCERTAIN), (last, StepStatus.TOO_FEW_MATCHES)):
        seen.clear()
        monkeypatch.setattr(vo, "_fit", fails_but(accept, status))
        s = vo.estimate_pair(a, b, rotation=False)
        assert not s.ok and s.status == status and s.n_matches == len(tries[-1])  # the rescue's, not 0.7's
        assert len(seen) == len(tries) + (status == StepStatus.UNCERTAIN)
    sift = VisualOdometry(meta.camera_model(), MotionSettings("sift", classify=False), meta.tube_radius_m)
    c, d = sift.matcher.features(f3), sift.matcher.features(f4)
    calls = []
    monkeypatch.setattr(sift, "_fit", lambda m, e=None: calls.append(m) or (StepMotion(status=StepStatus.UNCERTAIN),
                                                                           None))
    sift.estimate_pair(c, d, rotation=False)
    assert len(calls) == 1


def test_gaps_are_found_between_estimated_steps_and_split_exactly():
    from scipy.spatial.transform import Rotation

    from bodyslam.vision.odometry import find_gaps, split_motion
    from bodyslam.steps import StepMotion, motion_from_transform
    from bodyslam.vision.tracking import dead_reckon

    ok = motion_from_transform(Rotation.from_rotvec([0.01, 0.0, 0.1]), np.array([0.0, 0.001, 0.004]), 50)
    no = StepMotion(status="no_lumen")
    bad = StepMotion(status="bad_frame")
    steps = [no, ok, no, no, ok, ok, no, no, no, ok, bad, ok, no]
    # step index i is the move into frame i+1: the gap frames 2..4 (steps 2,3 missing) and 6..9; not the leading
    # gap (no estimated step before it), not the bad frame's, not the trailing one
    assert find_gaps(steps, 15) == [(2, 4), (6, 9)]
    assert find_gaps(steps, 2) == [(2, 4)]
    total = motion_from_transform(Rotation.from_rotvec([0.3, -0.2, 0.6]), np.array([0.002, -0.001, 0.012]), 40)
    total = replace(total, sigma_distance_m=4e-4, sigma_rotation_rad=0.02)
    parts = split_motion(total, 4)
    assert [p.status for p in parts] == ["bridged"] * 4 and all(p.has_estimate for p in parts)
    pos, rot = dead_reckon(parts)
    assert np.allclose(pos[-1], total.t_c1_c2_m, atol=1e-12)
    assert np.allclose(rot[-1].as_matrix(), total.R_c1_c2, atol=1e-12)
    assert parts[0].sigma_distance_m == pytest.approx(2e-4)  # 4e-4 / sqrt(4): four independent shares


def test_bridged_shares_split_what_matched_and_decline_a_total_too_short_for_its_lost_steps():
    """The rule a gap is bridged by, in ``bodyslam motion`` and in a batch chunk's worker alike: a gap whose ends
    did not match stays a gap; one whose end-to-end motion is shorter than half the least length of the steps it
    lost to motion is declined (a wrong match); the others are split into equal shares."""
    from scipy.spatial.transform import Rotation

    from bodyslam.steps import StepMotion, StepStatus, lost_step_floor_m, motion_from_transform
    from bodyslam.vision.odometry import BRIDGE_MIN_LOST_SHARE, bridged_shares

    radius_m = 0.0125
    floor = lost_step_floor_m(radius_m)
    ok = motion_from_transform(Rotation.identity(), np.array([0.0, 0.0, 0.004]), 50)
    lost, unlit = StepMotion(status=StepStatus.LOST), StepMotion(status=StepStatus.NO_LUMEN)
    steps = [ok, lost, lost, ok, lost, lost, ok, unlit, ok]
    gaps = [(1, 3), (4, 6), (7, 8)]

    def forward(length_m):
        return motion_from_transform(Rotation.identity(), np.array([0.0, 0.0, length_m]), 40)

    limit = BRIDGE_MIN_LOST_SHARE * 2 * floor  # two steps lost to motion in each of the first two gaps
    out = bridged_shares(steps, gaps, [forward(1.01 * limit), forward(0.99 * limit), None], radius_m)
    assert sorted(out) == [1, 2]  # the first gap bridged; the second declined; the third did not match
    assert all(s.status == StepStatus.BRIDGED for s in out.values())
    assert out[1].distance_m == pytest.approx(1.01 * limit / 2, rel=1e-9)  # two equal shares of a straight move
    # a gap of steps without an estimate that were not lost to motion (frames facing no lumen) has no floor
    assert sorted(bridged_shares(steps, [(7, 8)], [forward(1e-5)], radius_m)) == [7]


def test_a_gap_is_matched_as_it_closes_from_the_features_the_run_made(tmp_path):
    """``run(..., bridge=True)`` (a batch chunk's worker) matches the ends of each gap that closes inside its
    frames as it closes, from the features its steps made: the same motion ``bridge`` finds from the two frames
    read again, for the same gaps ``find_gaps`` finds; ``bridge_inside`` then gives the shares ``bridge_gaps``
    gives from the frames."""
    from bodyslam.vision.odometry import (MotionSettings, Sequence, VisualOdometry, bridge_gaps, bridge_inside,
                                          find_gaps, resolve_mask)
    from bodyslam.steps import StepStatus

    seq = Sequence.open(_with_wall_frames(tmp_path / "seq", dark=(30, 31), insert_dark_after=13))
    settings = MotionSettings("fast")
    vo = VisualOdometry(seq.camera, settings, seq.radius_m)
    res = vo.run(seq.source.read(5, 40), 5, bridge=True)
    statuses = [s for *_, s in res.steps]
    gaps = [(5 + a, 5 + b) for a, b in find_gaps(statuses, settings.bridge_gaps)]
    assert gaps == sorted(res.gap_totals) and (29, 32) in gaps and (13, 15) in gaps  # FL frames; a dark frame
    fresh = VisualOdometry(seq.camera, settings, seq.radius_m)
    for (a, b), total in res.gap_totals.items():
        want = fresh.bridge(seq.source.read_one(a).image, seq.source.read_one(b).image)
        assert (total is None) == (want is None), (a, b)
        if want is not None:
            assert np.array_equal(total.t_c1_c2_m, want.t_c1_c2_m) and np.array_equal(total.R_c1_c2, want.R_c1_c2)
            assert total.sigma_distance_m == want.sigma_distance_m and total.n_matches == want.n_matches
    # the chunk's bridges from the run's totals: the gaps and shares bridge_gaps finds from the frames read again
    got, shares = bridge_inside(statuses, 5, settings, seq.radius_m, res.gap_totals)
    assert got == gaps and {29, 30, 31} <= set(shares)
    base = seq.task_base(settings, resolve_mask(seq.source, seq.camera, settings.mask))
    # (the steps into positions 1-5 left out as unreadable: no gap starts before the chunk, as inside it)
    again = bridge_gaps([StepStatus.BAD_FRAME] * 5 + statuses, settings, base, jobs=1)
    assert sorted(again) == sorted(shares)
    assert all(np.array_equal(again[i].t_c1_c2_m, shares[i].t_c1_c2_m) for i in shares)

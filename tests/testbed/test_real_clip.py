"""Clips of known motion from one real frame (testbed.real_clip): the geometry, what stays, the files, bad input."""

from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest

from bodyslam.camera import FisheyeCamera
from bodyslam.errors import InputError
from bodyslam.io import read_image, write_image
from bodyslam.meta import read_meta
from testbed.real_clip import FOV_DEG, Lumen, field_mask, make_clip, tube_view


def capsule_frame(size: int = 192, seed: int = 0, dark_at: tuple[int, int] | None = (80, 90)) -> np.ndarray:
    """A capsule-like frame: textured mucosa inside an octagonal field stop, black corners, a dark lumen, and
    burned-in white text below the field that touches it (as the PillCam logo does)."""
    rng = np.random.default_rng(seed)
    tex = sum(cv2.resize(rng.normal(0, 1, (s, s)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
              for s in (8, 24, 64))
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    rgb = np.stack([60 + 150 * tex, 40 + 100 * tex, 20 + 60 * tex], axis=-1)
    if dark_at is not None:
        yy, xx = np.mgrid[0:size, 0:size]
        rgb *= 1 - 0.85 * np.exp(-((xx - dark_at[0]) ** 2 + (yy - dark_at[1]) ** 2) / (2 * (size / 12) ** 2))[..., None]
    m = size // 2 - 8
    c = (size - 1) / 2
    octagon = np.array([[c + m * math.cos(a), c + m * math.sin(a)] for a in np.arange(8) * math.pi / 4 + math.pi / 8])
    field = np.zeros((size, size), np.uint8)
    cv2.fillConvexPoly(field, np.rint(octagon).astype(np.int32), 1)
    rgb[field == 0] = 0
    rgb = np.clip(rgb, 0, 255).astype(np.uint8)
    cv2.putText(rgb, "CAPSULE", (2, size - 6), cv2.FONT_HERSHEY_SIMPLEX, size / 480, (255, 255, 255), 1)
    return rgb


def test_the_field_is_the_octagon_without_the_text():
    rgb = capsule_frame()
    mask = field_mask(rgb)
    white = (rgb.min(axis=2) > 200)
    assert white.any() and not (mask & white).any()  # the text stays outside
    assert mask[96, 96] and not mask[0, 0] and not mask[0, 191]
    inside = rgb.max(axis=2) > 25
    assert 0.97 < (mask & inside).sum() / (inside & ~white).sum() <= 1.0  # the lit field, all of it


def test_a_wall_hit_is_the_cylinder_s_range_on_and_off_its_axis():
    axis = np.array([0.2, -0.1, 1.0]) / math.hypot(0.2, 0.1, 1.0)
    lumen = Lumen(axis=axis, radius_m=0.012)
    v = np.random.default_rng(1).normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for c in (np.zeros(3), 0.005 * lumen.basis()[0] + 0.002 * lumen.basis()[1] + 0.01 * axis):
        t, normal = lumen.hit(c, v)
        # |(c + t v)_perp| = R: a quadratic in t, its positive root
        cp, vp = c - (c @ axis) * axis, v - (v @ axis)[:, None] * axis
        a, b, cc = np.sum(vp * vp, axis=1), 2 * vp @ cp, cp @ cp - 0.012**2
        exact = (-b + np.sqrt(b * b - 4 * a * cc)) / (2 * a)
        near = exact < 0.9  # the cast reaches a metre
        assert np.allclose(t[near], exact[near], rtol=1e-9, atol=1e-12)
        assert np.isinf(t[exact > 1.1]).all()
        p = c + t[near, None] * v[near]
        radial = p - (p @ axis)[:, None] * axis
        assert np.allclose(normal[near], radial / np.linalg.norm(radial, axis=1, keepdims=True), atol=1e-9)


def test_a_folded_wall_hit_lies_on_the_wall_and_its_normal_is_the_wall_s():
    lumen = Lumen(axis=np.array([0.0, 0.0, 1.0]), radius_m=0.0125, lobes=4, lobe_depth=0.3, offset_m=0.003)
    e1, e2 = lumen.basis()
    c = -0.003 * e1
    v = np.random.default_rng(2).normal(size=(400, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    t, normal = lumen.hit(c, v)
    ok = np.isfinite(t)
    assert ok.mean() > 0.9
    p = c + t[ok, None] * v[ok]
    x, y = p @ e1, p @ e2
    phi = np.arctan2(y, x)
    r = 0.0125 * (1 + 0.3 * np.cos(4 * phi))
    assert np.allclose(np.hypot(x, y), r, atol=1e-10)
    tangent = (-0.0125 * 0.3 * 4 * np.sin(4 * phi))[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2) \
        + r[:, None] * (-np.sin(phi)[:, None] * e1 + np.cos(phi)[:, None] * e2)  # d p / d phi on the wall
    n = normal[ok]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0) and np.allclose(n @ lumen.axis, 0.0, atol=1e-12)
    assert np.allclose(np.sum(n * tangent, axis=1), 0.0, atol=1e-9)
    assert (np.sum(n * (x[:, None] * e1 + y[:, None] * e2), axis=1) > 0).all()  # outward
    # the first crossing: no sample nearer the camera is outside the wall
    s = np.linspace(0.0, 1.0, 50)[None, :] * t[ok, None]
    xs, ys = (c @ e1) + s * (v[ok] @ e1)[:, None], (c @ e2) + s * (v[ok] @ e2)[:, None]
    assert (np.hypot(xs, ys)[:, :-1] <= 0.0125 * (1 + 0.3 * np.cos(4 * np.arctan2(ys, xs)))[:, :-1] + 1e-12).all()


@pytest.mark.parametrize("light", ["baked", "capsule"])
def test_the_first_frame_is_the_frame_itself(light):
    rgb = capsule_frame()
    cam = FisheyeCamera.equidistant(192, 192, FOV_DEG)
    lumen = Lumen(axis=np.array([0.1, 0.05, 1.0]) / math.hypot(0.1, 0.05, 1.0), lobes=3, lobe_depth=0.2,
                  offset_m=0.002)
    assert np.array_equal(tube_view(rgb, field_mask(rgb), cam, lumen, 0.0, 0.0, light=light), rgb)


def test_a_wall_point_moves_where_the_camera_model_puts_it():
    """A bright dot on the wall, seen again after the camera advanced and rolled: it lands where projecting the
    same 3-D point from the moved camera puts it (an independent path through the camera model)."""
    size = 192
    cam = FisheyeCamera.equidistant(size, size, FOV_DEG)
    rgb = np.full((size, size, 3), 90, np.uint8)
    rgb[~cam.fov_mask()] = 0
    u0 = np.array([[130.0, 70.0]])
    cv2.circle(rgb, (130, 70), 2, (255, 255, 255), -1)
    lumen = Lumen(axis=np.array([0.0, 0.0, 1.0]), radius_m=0.0125)
    ray, _ = cam.unproject(u0)
    P = ray[0] * 0.0125 / np.hypot(ray[0, 0], ray[0, 1])  # the dot's wall point, camera 0
    for advance, roll in ((0.004, 0.0), (0.008, 0.2)):
        out = tube_view(rgb, field_mask(rgb), cam, lumen, advance, roll, light="baked")
        c, s = math.cos(roll), math.sin(roll)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])  # camera k -> camera 0
        expected, _ = cam.project((Rz.T @ (P - advance * lumen.axis))[None])
        bright = out.min(axis=2) > 170
        ys, xs = np.nonzero(bright)
        assert len(xs) > 3
        assert np.hypot(xs.mean() - expected[0, 0], ys.mean() - expected[0, 1]) < 0.6  # px: the dot's sampling
        assert np.hypot(*(expected[0] - u0[0])) > 6  # it did move


def test_a_clip_keeps_its_field_stop_and_text_and_states_its_truth(tmp_path):
    rgb = capsule_frame()
    src = tmp_path / "real.png"
    write_image(src, rgb)
    out = tmp_path / "clip"
    truth = make_clip(src, out, n_frames=5, step_m=0.0015, roll_rad=0.05, radius_m=0.01, lobes=4, lobe_depth=0.25,
                      jpeg_quality=0, label="FT", fov_deg=170.0)
    mask = field_mask(rgb)
    frames = sorted((out / "frames").iterdir())
    assert [f.name for f in frames] == [f"{i:06d}.png" for i in range(5)]
    for f in frames[1:]:
        img = read_image(f)
        assert np.array_equal(img[~mask], rgb[~mask])  # corners and text stay where they are
        assert np.abs(img[mask].astype(int) - rgb[mask]).mean() > 3  # the field moved
    rows = list(csv.DictReader(open(out / "motion_truth.csv", newline="")))
    assert len(rows) == 4
    for r in rows:
        assert float(r["distance_m"]) == pytest.approx(0.0015, rel=1e-9)
        assert float(r["roll_rad"]) == pytest.approx(0.05, rel=1e-9)
        assert abs(float(r["tilt_rad"])) < 1e-9 and r["label"] == "FT"
    meta = read_meta(out)
    assert meta.camera["fov_deg"] == pytest.approx(170.0)  # the lens the clip was made with
    assert meta.tube_radius_m == pytest.approx(0.0125)  # the prior, not the clip's 1 cm: the truth is hidden
    assert json.loads((out / "truth.json").read_text())["radius_m"] == pytest.approx(0.01)
    assert truth["step_in_prior_radius_m"] == pytest.approx(0.0015 * 1.25)
    assert len((out / "groundtruth.tum").read_text().strip().splitlines()) >= 5


@pytest.mark.parametrize("kw, what", [
    ({"n_frames": 1}, "at least 2 frames"),
    ({"step_m": 0.0}, "must be positive"),
    ({"lobe_depth": 1.0}, "lobe_depth"),
    ({"offset_frac": 0.8, "lobe_depth": 0.3}, "inside the lumen"),
    ({"label": "XX"}, "label"),
    ({"light": "sun"}, "light"),
    ({"fov_deg": 30.0}, "fov_deg"),
    ({"max_magnification": 0.5}, "at least 1"),
    ({"noise": -1.0}, "noise"),
    ({"jpeg_quality": 101}, "jpeg_quality"),
])
def test_a_clip_with_bad_parameters_is_refused_before_anything_is_written(tmp_path, kw, what):
    src = tmp_path / "real.png"
    write_image(src, capsule_frame())
    with pytest.raises(InputError, match=what):
        make_clip(src, tmp_path / "clip", **kw)
    assert not (tmp_path / "clip").exists()


def test_a_clip_from_a_bad_frame_or_into_a_full_directory_is_refused(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(InputError, match="bad.png"):
        make_clip(tmp_path / "bad.png", tmp_path / "c1")
    write_image(tmp_path / "black.png", np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(InputError, match="no lit field"):
        make_clip(tmp_path / "black.png", tmp_path / "c2")
    write_image(tmp_path / "real.png", capsule_frame())
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        make_clip(tmp_path / "real.png", tmp_path / "full")
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_a_clip_ends_before_it_enlarges_the_frame_past_the_limit_and_keeps_no_earlier_frames(tmp_path):
    write_image(tmp_path / "real.png", capsule_frame())
    out = tmp_path / "clip"
    whole = make_clip(tmp_path / "real.png", out, n_frames=12, step_m=0.002, jpeg_quality=0)
    assert whole["magnification"][0] == pytest.approx(1.0, abs=1e-3)
    assert np.all(np.diff(whole["magnification"]) > 0)  # forward: ever more enlarged
    past = whole["frames_past_2x"]
    assert 0 < past < 11
    cut = make_clip(tmp_path / "real.png", out, n_frames=12, step_m=0.002, jpeg_quality=0, max_magnification=2.0,
                    force=True)
    assert cut["n_frames"] == 12 - past and max(cut["magnification"]) <= 2.0
    assert len(list((out / "frames").iterdir())) == cut["n_frames"]  # the longer clip's frames are gone
    assert len((out / "motion_truth.csv").read_text().splitlines()) == cut["n_frames"]
    with pytest.raises(InputError, match="shorter step"):
        make_clip(tmp_path / "real.png", tmp_path / "c2", step_m=0.03, max_magnification=2.0)
    assert not (tmp_path / "c2").exists()


def test_the_pipeline_reads_a_clip_s_steps_forward_at_their_length(tmp_path):
    """End to end: the clip's frames through `bodyslam motion`, scored by `testbed score-motion`'s code. The camera
    advances 1 mm a frame along the lumen the pipeline assumes (1.25 cm, centred) and rolls 3 deg: each step must
    come out forward, its length within 0.01 cm and its roll within 0.3 deg on average (measured 0.0009 cm and
    0.035 deg: the tolerances are ~10x that, and a step read at the wrong length or roll sign is far outside)."""
    from bodyslam.cli import main as bodyslam_main
    from testbed.score import score_motion

    write_image(tmp_path / "real.png", capsule_frame(seed=3))
    seq = tmp_path / "clip"
    make_clip(tmp_path / "real.png", seq, n_frames=5, step_m=0.001, roll_rad=math.radians(3), label="FT")
    assert bodyslam_main(["motion", str(seq), "--out", str(tmp_path / "m.csv"), "--mode", "sift"]) == 0
    rep = score_motion(seq, tmp_path / "m.csv")
    assert rep["all"]["n_steps_scored"] >= 3
    rows = [r for r in csv.DictReader(open(tmp_path / "m.csv", newline="")) if r["status"] == "ok"]
    assert all(float(r["tz_m"]) > 0 for r in rows)
    assert rep["all"]["mae_distance_cm"] < 0.01  # of 0.1 cm a step
    assert rep["all"]["mae_roll_deg"] < 0.3  # of 3 deg


def test_the_command_makes_a_clip_and_names_what_is_wrong(tmp_path, capsys):
    from testbed.cli import main

    write_image(tmp_path / "real.png", capsule_frame())
    assert main(["real-clip", str(tmp_path / "real.png"), "--out", str(tmp_path / "c"), "--frames", "3",
                 "--step-mm", "2", "--roll-deg", "4", "--radius-cm", "1", "--lobes", "4", "--lobe-depth", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "3 frames" in out and "advances 0.40 cm" in out and "2.500 mm in the prior's radius" in out
    rows = list(csv.DictReader(open(tmp_path / "c" / "motion_truth.csv", newline="")))
    assert float(rows[0]["roll_rad"]) == pytest.approx(math.radians(4))
    assert main(["real-clip", str(tmp_path / "real.png"), "--out", str(tmp_path / "c")]) == 1  # not empty
    assert "not empty" in capsys.readouterr().err
    assert main(["real-clip", str(tmp_path / "nope.png"), "--out", str(tmp_path / "d")]) == 1
    assert "nope.png" in capsys.readouterr().err

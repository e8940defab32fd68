import math

import cv2
import numpy as np
import pytest

from bodyslam.camera import FisheyeCamera, PinholeCamera, camera_from_dict
from bodyslam.errors import InputError


def random_rays(rng, n, max_angle_deg):
    th = np.radians(rng.uniform(0, max_angle_deg, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.c_[np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]


def test_equidistant_radius_is_proportional_to_angle():
    cam = FisheyeCamera.equidistant(320, 320, 156.0)
    rays = random_rays(np.random.default_rng(0), 200, 78.0)
    uv, valid = cam.project(rays * 0.03)
    assert valid.all()
    r_px = np.hypot(uv[:, 0] - cam.cx, uv[:, 1] - cam.cy)
    theta = np.arccos(rays[:, 2])
    # image circle of 320 px spans 156 deg: r = 160 px * theta / 78 deg, exactly (float rounding only)
    np.testing.assert_allclose(r_px, 160.0 * theta / math.radians(78.0), atol=1e-9)


@pytest.mark.parametrize("k", [(0, 0, 0, 0), (-0.02, 0.004, -0.001, 0.0002)])
def test_fisheye_matches_opencv_and_round_trips(k):
    cam = FisheyeCamera(width=320, height=300, fx=110.0, fy=112.0, cx=158.3, cy=151.1, fov_deg=160.0, k=k)
    pts = random_rays(np.random.default_rng(1), 300, 79.0) * np.random.default_rng(2).uniform(0.01, 0.2, (300, 1))
    uv, valid = cam.project(pts)
    assert valid.all()
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.D)
    # same model as cv2.fisheye: agreement to float rounding (1e-6 px)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    rays, ok = cam.unproject(uv)
    assert ok.all()
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-9)


def test_fov_mask_is_the_image_circle():
    cam = FisheyeCamera.equidistant(100, 100, 156.0)
    m = cam.fov_mask()
    assert m[50, 50] and not m[0, 0] and not m[99, 99]
    # the valid area is the inscribed disc: pi/4 of the square, up to the pixel grid
    assert abs(m.mean() - math.pi / 4) < 0.02


def test_pinhole_round_trip_and_from_dict():
    cam = camera_from_dict({"model": "pinhole", "width": 64, "height": 48, "hfov_deg": 90.0})
    assert isinstance(cam, PinholeCamera)
    uv = np.array([[0.0, 0.0], [31.5, 23.5], [63.0, 47.0]])
    rays, _ = cam.unproject(uv)
    back, valid = cam.project(rays)
    assert valid.all()
    np.testing.assert_allclose(back, uv, atol=1e-9)


def test_to_dict_round_trip():
    cam = FisheyeCamera.equidistant(420, 420, 156.0)
    again = camera_from_dict(cam.to_dict())
    uv = np.array([[10.0, 200.0], [300.0, 33.0]])
    np.testing.assert_allclose(again.unproject(uv)[0], cam.unproject(uv)[0])


@pytest.mark.parametrize(
    "desc, match",
    [
        ({"model": "kaleidoscope"}, "unknown camera model"),
        ({"model": "equidistant", "width": 320}, "missing parameter 'height'"),
        ({"model": "equidistant", "width": 320, "height": 320, "fov_deg": 400}, "fov_deg"),
        ({"model": "pinhole", "width": 1, "height": 4, "fx": 1, "fy": 1, "cx": 0, "cy": 0}, "image size"),
        ({"model": "opencv_fisheye", "width": 64, "height": 64, "fx": 30, "fy": 30, "cx": 32, "cy": 32,
          "fov_deg": 180, "k": [-1.0, 0, 0, 0]}, "not monotonic"),
        # fov_deg in radians: a field of radius 3 px, every step lost and exit 0 before it was refused
        ({"model": "opencv_fisheye", "width": 320, "height": 320, "fx": 117.5, "fy": 117.5, "cx": 159.5, "cy": 159.5,
          "fov_deg": 2.72}, r"radius 3 px on a 320x320 image .*2\.72 rad is 156 deg"),
    ],
)
def test_bad_camera_descriptions_raise(desc, match):
    with pytest.raises(InputError, match=match):
        camera_from_dict(desc)


def _disc(h, w, cx, cy, r):
    yy, xx = np.mgrid[:h, :w]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def test_an_assumed_lens_is_centred_on_a_field_that_is_off_centre_or_small():
    from bodyslam.camera import FIELD_MIN_SHARE, equidistant_on_field

    # the frame's own field (a disc across the shorter side, an octagon of 89% like real PillCam frames): None
    assert equidistant_on_field(_disc(320, 320, 159.5, 159.5, 158), 156.0) is None
    octagon = np.zeros((576, 576), np.uint8)
    c, r = 287.5, 255 / math.cos(math.pi / 8)
    pts = [(c + r * math.cos(math.pi / 8 + k * math.pi / 4), c + r * math.sin(math.pi / 8 + k * math.pi / 4))
           for k in range(8)]
    cv2.fillConvexPoly(octagon, np.round(pts).astype(np.int32), 1)
    assert equidistant_on_field(octagon > 0, 156.0) is None
    # an image beside a panel: centred on the field, the circle as wide as the field
    cam = equidistant_on_field(_disc(600, 800, 297.5, 299.5, 255), 156.0)
    assert (cam.width, cam.height) == (800, 600) and (cam.cx, cam.cy) == (297.5, 299.5)
    assert cam.fx == pytest.approx(510 / 2 / math.radians(78))  # columns 43-552 of the disc
    u, valid = cam.project(np.array([[0.0, 0.0, 1.0], [math.sin(math.radians(77)), 0.0, math.cos(math.radians(77))]]))
    assert valid.all() and u[0] == pytest.approx([297.5, 299.5]) and 540 < u[1, 0] < 553  # the field's right edge
    # a small image in the middle of a large frame
    small = equidistant_on_field(_disc(720, 1280, 639.5, 359.5, 0.3 * 720), 156.0)
    assert small is not None and small.fx < FIELD_MIN_SHARE * FisheyeCamera.equidistant(1280, 720, 156.0).fx
    # a field the frame cuts off says nothing of the circle; an empty one nothing at all
    assert equidistant_on_field(_disc(600, 800, 250, 299.5, 300), 156.0) is None
    assert equidistant_on_field(np.zeros((50, 60), bool), 156.0) is None

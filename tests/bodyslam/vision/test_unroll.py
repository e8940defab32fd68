"""Unrolling: pixel <-> (azimuth, angular depth) from the camera model; the thesis's linear Eq. 3.11 mode."""

import math

import numpy as np
import pytest

from bodyslam.camera import FisheyeCamera
from bodyslam.errors import ConfigError
from bodyslam.vision.unroll import Unroller


def rays_at(phi, theta):
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0, 0.0), (-0.02, 0.003, 0.0, 0.0)])
def test_exact_angles_invert_the_camera_model(k):
    cam = FisheyeCamera(320, 320, 110.0, 110.0, 159.5, 159.5, 156.0, k)
    rng = np.random.default_rng(1)
    phi = rng.uniform(0, 2 * math.pi, 200)
    theta = rng.uniform(0.01, math.radians(77), 200)
    uv, _ = cam.project(rays_at(phi, theta))
    got_phi, got_theta = Unroller(cam).angles(uv)
    assert np.abs(np.angle(np.exp(1j * (got_phi - phi)))).max() < 1e-9
    assert np.abs(got_theta - theta).max() < 1e-9


def test_thesis_linear_depth_is_exact_only_for_an_equidistant_lens():
    rng = np.random.default_rng(2)
    theta = rng.uniform(0.05, math.radians(75), 100)
    phi = rng.uniform(0, 2 * math.pi, 100)
    eq = FisheyeCamera.equidistant(320, 320, 156.0)
    uv, _ = eq.project(rays_at(phi, theta))
    assert np.abs(Unroller(eq, mode="thesis").angles(uv)[1] - theta).max() < 1e-9
    kb = FisheyeCamera(320, 320, 110.0, 110.0, 159.5, 159.5, 156.0, (-0.05, 0.004, 0.0, 0.0))
    uv, _ = kb.project(rays_at(phi, theta))
    err = np.abs(Unroller(kb, mode="thesis").angles(uv)[1] - theta)
    assert err.max() > math.radians(1.0)  # the linear approximation is off by degrees for a distorted lens


def test_unrolled_image_rows_are_angular_depth():
    cam = FisheyeCamera.equidistant(200, 200, 156.0)
    un = Unroller(cam, 360, 100)
    # an image whose brightness is the pixel's angle from the axis (degrees): every unrolled row is constant
    rays, valid = cam.pixel_rays()
    img = np.where(valid, np.degrees(np.arccos(np.clip(rays[..., 2], -1, 1))), 0).astype(np.float32)
    out = un.unroll(img)
    expect = (np.arange(100) + 0.5) / 100 * 78.0
    assert np.abs(out[5:-2].mean(axis=1) - expect[5:-2]).max() < 0.3
    assert out[5:-2].std(axis=1).max() < 0.3


def test_bad_mode_is_a_config_error():
    with pytest.raises(ConfigError):
        Unroller(FisheyeCamera.equidistant(64, 64, 156.0), mode="spherical")

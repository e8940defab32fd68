import math

import numpy as np
import pytest

from bodyslam.errors import ConfigError
from testbed.centerline import Centerline, min_self_distance, procedural_centerline


@pytest.mark.parametrize("seed", [0, 5])
def test_procedural_centerline_is_packed_smooth_and_self_avoiding(seed):
    r = 0.015
    box = (0.32, 0.24, 0.34)
    cl = procedural_centerline(2.5, seed, radius_max_m=r, abdomen_box_m=box)
    assert abs(cl.length_m - 2.5) < cl.ds_m
    np.testing.assert_allclose(np.diff(cl.s_m), cl.ds_m)
    # the whole tube (centre line + radius) stays inside the abdomen box
    assert np.all(np.abs(cl.points_w) + r <= np.array(box) / 2)
    # never closer to itself than two tube diameters (pairs more than a quarter-turn apart along the path)
    assert min_self_distance(cl.points_w, cl.s_m, 4 * r * math.pi / 2) >= 4 * r
    # bends wider than the tube radius: the swept tube does not fold onto itself
    assert 1.0 / cl.curvature_per_m().max() > r
    # frames are orthonormal and right-handed: n x b = t
    np.testing.assert_allclose(np.cross(cl.normals_w, cl.binormals_w), cl.tangents_w, atol=1e-9)
    np.testing.assert_allclose(np.sum(cl.normals_w * cl.tangents_w, axis=1), 0, atol=1e-9)


def test_same_seed_same_path_other_seed_other_path():
    a = procedural_centerline(1.0, 3)
    b = procedural_centerline(1.0, 3)
    c = procedural_centerline(1.0, 4)
    np.testing.assert_array_equal(a.points_w, b.points_w)
    assert np.abs(a.points_w - c.points_w).max() > 0.01


def test_rotation_minimising_frame_does_not_twist_on_a_helix():
    # On a helix the RMF rotates relative to the Frenet frame at the rate of the torsion; its own twist rate
    # (d n/ds . b) must be ~0, which is what keeps roll truth free of spurious frame rotation.
    u = np.linspace(0, 4 * np.pi, 2000)
    pts = np.c_[0.03 * np.cos(u), 0.03 * np.sin(u), 0.02 * u]
    cl = Centerline.from_points(pts, 0.01, ds_m=5e-4)
    dn = np.gradient(cl.normals_w, cl.ds_m, axis=0)
    twist = np.sum(dn * cl.binormals_w, axis=1)
    assert np.abs(twist[5:-5]).max() < 1e-2  # rad/m; a Frenet frame here twists at 11 rad/m


def test_impossible_packing_is_a_config_error():
    with pytest.raises(ConfigError, match="does not fit the abdomen box"):
        procedural_centerline(20.0, 0)

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.geometry import relative_motion, swing_twist_z


def test_pure_motions_are_reported_in_their_own_channel():
    R0 = Rotation.from_euler("xyz", [0.3, -0.2, 1.0])
    p0 = np.array([0.1, 0.0, -0.05])
    roll = Rotation.from_rotvec([0, 0, 0.2])
    pitch = Rotation.from_rotvec([0.05, 0, 0])
    yaw = Rotation.from_rotvec([0, -0.07, 0])
    Rs = Rotation.concatenate([R0, R0 * roll, R0 * roll * pitch, R0 * roll * pitch * yaw])
    ps = np.array([p0, p0 + R0.apply([0, 0, 0.004]), p0 + R0.apply([0, 0, 0.004]), p0])
    m = relative_motion(Rs, ps)
    np.testing.assert_allclose(m["roll_rad"], [0.2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m["pitch_rad"], [0.0, 0.05, 0.0], atol=1e-12)
    np.testing.assert_allclose(m["yaw_rad"], [0.0, 0.0, -0.07], atol=1e-12)
    # forward along the optical axis is +, the way back is -
    np.testing.assert_allclose(m["distance_m"], [0.004, 0.0, -0.004], atol=1e-12)


def test_tilt_is_the_angle_between_optical_axes():
    R = Rotation.random(50, random_state=3)
    twist, swing = swing_twist_z(R)
    z = R.apply([0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(swing, axis=1), np.arccos(np.clip(z[:, 2], -1, 1)), atol=1e-9)
    np.testing.assert_allclose(swing[:, 2], 0, atol=1e-12)
    back = Rotation.from_rotvec(swing) * Rotation.from_rotvec(np.c_[0 * twist, 0 * twist, twist])
    assert np.max((back.inv() * R).magnitude()) < 1e-9


def test_rotation_conversions_agree_with_scipy_near_zero_and_near_pi():
    from bodyslam.geometry import matrix_to_rotvec, rotvec_to_matrix

    rng = np.random.default_rng(2)
    axes = rng.normal(size=(400, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = np.r_[rng.uniform(0, np.pi, 300), [0.0, 1e-9, 1e-5, 1e-3], np.pi - np.r_[1e-3, 1e-6, 1e-9],
                   rng.uniform(0, 1e-4, 93)]
    rv = axes * angles[:, None]
    want_R = Rotation.from_rotvec(rv).as_matrix()
    assert np.abs(rotvec_to_matrix(rv) - want_R).max() < 1e-14  # batched
    assert max(np.abs(rotvec_to_matrix(r) - m).max() for r, m in zip(rv, want_R)) < 1e-14  # one at a time
    want_rv = Rotation.from_matrix(want_R).as_rotvec()
    got = matrix_to_rotvec(want_R)
    one = np.array([matrix_to_rotvec(m) for m in want_R])
    # near pi a rotation vector and its negative are the same rotation: compare the rotations there
    for g in (got, one):
        assert np.abs(rotvec_to_matrix(g) - want_R).max() < 1e-12
        away = angles < np.pi - 1e-2
        assert np.abs(g[away] - want_rv[away]).max() < 1e-12
        assert np.all(np.linalg.norm(g, axis=1) <= np.pi + 1e-12)

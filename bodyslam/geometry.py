"""Rigid-motion conventions shared by the pipeline and the testbed.

Poses are ``T_w_c``: ``p_w = R_w_c p_c + t_w_c`` (camera in world). The per-step motion between frames ``k-1`` and
``k`` is ``T_c1_c2 = T_w_c1^-1 T_w_c2``, reported as (SPEC.md "Per-step motion"):

- ``distance_m``: ``|t_c1_c2|``, signed ``+`` when the camera moved forward along its own optical axis
  (``t_z >= 0``), ``-`` when it moved backward;
- ``roll_rad``: the twist of ``R_c1_c2`` about the optical axis z (swing-twist decomposition
  ``R = R_swing R_twist``, ``R_twist`` about z, ``R_swing`` about an axis in the x-y plane);
- ``pitch_rad``, ``yaw_rad``: the x and y components of the swing's rotation vector (rotation about x, about y);
- ``tilt_rad``: the swing angle, which equals the angle between the two optical axes exactly.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["swing_twist_z", "relative_motion", "rotvec_to_matrix", "matrix_to_rotvec"]


# Small batched rotation conversions. scipy's Rotation costs ~0.1 ms per object (array-API checks), which per
# frame of a whole exam's filter, smoother and motion rows was a third of the time after the last chunk; these
# are plain numpy on (..., 3) / (..., 3, 3) arrays and agree with scipy to ~1e-15 (tests/bodyslam/test_geometry.py).
def rotvec_to_matrix(rv) -> np.ndarray:
    """Rodrigues: rotation vectors ``(..., 3)`` -> matrices ``(..., 3, 3)``."""
    rv = np.asarray(rv, float)
    if rv.shape == (1, 3):
        return rotvec_to_matrix(rv[0])[None]
    if rv.shape == (3,):  # one: Python floats (numpy's per-call cost is most of the work at this size)
        x, y, z = float(rv[0]), float(rv[1]), float(rv[2])
        t2 = x * x + y * y + z * z
        if t2 < 1e-8:
            a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
        else:
            th = math.sqrt(t2)
            a, b = math.sin(th) / th, (1.0 - math.cos(th)) / t2
        return np.array([[1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
                         [a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z],
                         [-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)]])
    th = np.sqrt(np.sum(rv * rv, axis=-1))[..., None, None]
    K = np.zeros(rv.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -rv[..., 2], rv[..., 1], -rv[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)  # sin(th)/th and (1 - cos th)/th^2, series near 0
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> rotation vectors ``(..., 3)`` (angle in [0, pi]), through the unit
    quaternion (Shepperd's choice of the largest component, so it holds near pi as well as near 0)."""
    R = np.asarray(R, float)
    if R.shape == (3, 3):
        return _matrix_to_rotvec_one(R.tolist())
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cand = np.stack([tr, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], axis=-1)
    i = np.argmax(cand, axis=-1)
    q = np.empty(R.shape[:-2] + (4,))  # (w, x, y, z)
    for c in range(4):
        sel = i == c
        if not np.any(sel):
            continue
        M = R[sel]
        if c == 0:
            w = np.sqrt(1.0 + tr[sel]) / 2.0
            q[sel] = np.stack([w, (M[:, 2, 1] - M[:, 1, 2]) / (4 * w), (M[:, 0, 2] - M[:, 2, 0]) / (4 * w),
                               (M[:, 1, 0] - M[:, 0, 1]) / (4 * w)], axis=-1)
            continue
        j, k = c % 3, (c + 1) % 3  # the axis c-1 and the next two, cyclically
        a = c - 1
        v = np.sqrt(1.0 + 2.0 * M[:, a, a] - tr[sel]) / 2.0
        qq = np.empty((len(M), 4))
        qq[:, 1 + a] = v
        qq[:, 0] = (M[:, k, j] - M[:, j, k]) / (4 * v)
        qq[:, 1 + j] = (M[:, j, a] + M[:, a, j]) / (4 * v)
        qq[:, 1 + k] = (M[:, k, a] + M[:, a, k]) / (4 * v)
        q[sel] = qq
    q = np.where(q[..., :1] < 0, -q, q)  # w >= 0: the angle in [0, pi]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    vn = np.linalg.norm(q[..., 1:], axis=-1)
    ang = 2.0 * np.arctan2(vn, q[..., 0])
    scale = np.where(vn < 1e-12, 2.0, ang / np.where(vn < 1e-12, 1.0, vn))  # small angles: 2 v (w ~ 1)
    return q[..., 1:] * scale[..., None]


def _matrix_to_rotvec_one(m: list) -> np.ndarray:
    """:func:`matrix_to_rotvec` of one matrix given as nested lists, in Python floats."""
    tr = m[0][0] + m[1][1] + m[2][2]
    c = max(range(4), key=lambda i: (tr, m[0][0], m[1][1], m[2][2])[i])
    if c == 0:
        w = math.sqrt(1.0 + tr) / 2.0
        q = [w, (m[2][1] - m[1][2]) / (4 * w), (m[0][2] - m[2][0]) / (4 * w), (m[1][0] - m[0][1]) / (4 * w)]
    else:
        a = c - 1
        j, k = (a + 1) % 3, (a + 2) % 3
        v = math.sqrt(1.0 + 2.0 * m[a][a] - tr) / 2.0
        q = [0.0] * 4
        q[1 + a] = v
        q[0] = (m[k][j] - m[j][k]) / (4 * v)
        q[1 + j] = (m[j][a] + m[a][j]) / (4 * v)
        q[1 + k] = (m[k][a] + m[a][k]) / (4 * v)
    if q[0] < 0:
        q = [-x for x in q]
    n = math.sqrt(sum(x * x for x in q))
    w, x, y, z = (v / n for v in q)
    vn = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 if vn < 1e-12 else 2.0 * math.atan2(vn, w) / vn
    return np.array([x * scale, y * scale, z * scale])


def swing_twist_z(R: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """Split rotations into ``R = R_swing R_twist`` about z.

    Returns
    -------
    twist_rad : (n,) angle of the twist about z, in (-pi, pi].
    swing_rotvec : (n, 3) rotation vector of the swing (its z component is 0 up to rounding).
    """
    q = np.atleast_2d(R.as_quat())  # x y z w
    twist_rad = 2.0 * np.arctan2(q[:, 2], q[:, 3])
    twist_rad = (twist_rad + np.pi) % (2 * np.pi) - np.pi
    swing = Rotation.from_quat(q) * Rotation.from_rotvec(np.c_[np.zeros((len(q), 2)), twist_rad]).inv()
    return twist_rad, np.atleast_2d(swing.as_rotvec())


def relative_motion(rotations_w_c: Rotation, positions_w_m: np.ndarray) -> dict[str, np.ndarray]:
    """Per-step motion between consecutive poses (see module docstring); arrays of length ``n - 1``."""
    R = rotations_w_c
    p = np.asarray(positions_w_m, dtype=np.float64)
    R1, R2 = R[:-1], R[1:]
    t12 = R1.inv().apply(p[1:] - p[:-1])
    R12 = R1.inv() * R2
    roll, swing = swing_twist_z(R12)
    dist = np.linalg.norm(t12, axis=1) * np.where(t12[:, 2] >= 0, 1.0, -1.0)
    return {
        "distance_m": dist,
        "roll_rad": roll,
        "pitch_rad": swing[:, 0],
        "yaw_rad": swing[:, 1],
        "tilt_rad": np.linalg.norm(swing, axis=1),
        "t_c1_c2_m": t12,
    }

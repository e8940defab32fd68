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

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["swing_twist_z", "relative_motion"]


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

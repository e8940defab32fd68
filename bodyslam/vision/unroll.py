"""Image unrolling (inverse cylindrical projection), dissertation Sec. 3.2.3, Eq. 3.8-3.11.

Every pixel maps to its angle around the optical axis ``phi`` (Eq. 3.9) and its *angular depth* ``theta``, the
angle between its ray and the optical axis (Eq. 3.7: a wall point at axial distance ``D`` in a tube of radius ``R``
seen from the axis has ``theta = atan(R / D)``). The unrolled image is ``L`` (x', around) by ``H`` (y', depth):
``x' = L phi / (2 pi)`` (Eq. 3.8) and ``y' = H theta / eta`` with ``eta`` the half field of view.

Modes
-----
- ``exact`` (default): ``phi`` and ``theta`` come from the camera model's ray of the pixel
  (``phi = atan2(ray_y, ray_x)``, ``theta = acos(ray_z)``), right for any lens ``cv2.fisheye`` can express.
- ``thesis``: Eq. 3.9-3.11 literally: ``phi`` from the pixel offset to the principal point and ``theta`` linear in
  the pixel's image radius, ``theta ~= (r / r_max) eta`` (Eq. 3.11). Exact for an ideal equidistant fisheye,
  wrong for any other lens.

Angles follow SPEC.md's camera frame (x right, y down), so ``phi`` grows from +x toward +y (clockwise on screen).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from bodyslam.camera import CameraModel
from bodyslam.errors import ConfigError

__all__ = ["Unroller"]

MODES = ("exact", "thesis")


class Unroller:
    """Pixel <-> (phi, theta) and unrolled images for one camera.

    Parameters
    ----------
    camera : CameraModel
    length_px, height_px : size of the unrolled image (thesis: 500 x 300).
    mode : ``"exact"`` or ``"thesis"`` (see module docstring).
    """

    def __init__(self, camera: CameraModel, length_px: int = 500, height_px: int = 300, mode: str = "exact"):
        if mode not in MODES:
            raise ConfigError(f"unroll mode must be one of {MODES}, got {mode!r}")
        self.camera = camera
        self.L = int(length_px)
        self.H = int(height_px)
        self.mode = mode
        self.eta_rad = math.radians(camera.fov_deg) / 2.0
        cx, cy = getattr(camera, "cx", (camera.width - 1) / 2), getattr(camera, "cy", (camera.height - 1) / 2)
        self.center_px = np.array([cx, cy], float)
        # image radius of the field-of-view edge (for the thesis's linear Eq. 3.11), along +x
        edge = np.array([[math.sin(self.eta_rad), 0.0, math.cos(self.eta_rad)]])
        self.r_max_px = float(np.linalg.norm(camera.project(edge)[0][0] - self.center_px))
        self._maps = None

    # -- angles ---------------------------------------------------------------------------------------------
    def angles(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(phi_rad in [0, 2 pi), theta_rad)`` of pixel coordinates ``(n, 2)``."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.mode == "thesis":
            d = uv - self.center_px
            phi = np.arctan2(d[:, 1], d[:, 0])  # Eq. 3.9
            theta = np.hypot(d[:, 0], d[:, 1]) / self.r_max_px * self.eta_rad  # Eq. 3.10-3.11
        else:
            rays, _ = self.camera.unproject(uv)
            phi = np.arctan2(rays[:, 1], rays[:, 0])
            theta = np.arccos(np.clip(rays[:, 2], -1.0, 1.0))
        return np.mod(phi, 2 * math.pi), theta

    def to_unrolled(self, uv: np.ndarray) -> np.ndarray:
        """Unrolled coordinates ``(x', y')`` (Eq. 3.8) of pixel coordinates."""
        phi, theta = self.angles(uv)
        return np.c_[self.L * phi / (2 * math.pi), self.H * theta / self.eta_rad]

    def rays(self, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Unit rays (camera frame) with azimuth ``phi`` and angle ``theta`` from the optical axis."""
        st = np.sin(theta)
        return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)

    # -- images ---------------------------------------------------------------------------------------------
    def _remap_maps(self):
        if self._maps is None:
            xs = (np.arange(self.L) + 0.5) / self.L * 2 * math.pi
            ys = (np.arange(self.H) + 0.5) / self.H * self.eta_rad
            phi, theta = np.meshgrid(xs, ys)
            if self.mode == "thesis":
                r = theta / self.eta_rad * self.r_max_px
                uv = np.stack([self.center_px[0] + r * np.cos(phi), self.center_px[1] + r * np.sin(phi)], -1)
            else:
                uv, _ = self.camera.project(self.rays(phi.ravel(), theta.ravel()))
                uv = uv.reshape(self.H, self.L, 2)
            self._maps = (uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32))
        return self._maps

    def unroll(self, image: np.ndarray) -> np.ndarray:
        """The unrolled image (``H x L``): row ``y'`` is angular depth (0 at the top = image centre)."""
        mx, my = self._remap_maps()
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

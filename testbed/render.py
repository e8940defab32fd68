"""Rendering capsule frames: colour and range through any :class:`~bodyslam.camera.CameraModel`.

The default renderer casts one ray per pixel centre (Embree, through ``embreex``) against the tube mesh, so every
camera model -- fisheye included -- is exact: the pixel ``(u, v)`` shows the wall point where the camera model's
ray through ``(u, v)`` meets the mesh, and ``range_m`` is that ray's length. No GL is involved (headless by nature).
:mod:`testbed.render_gl` is the pyrender/OpenGL alternative.

Shading: the light sits at the camera centre (a capsule's LEDs ring its lens), so the incidence angle equals the
viewing angle. Irradiance falls off as ``1/d^2`` and with the LED emission profile ``cos(theta_ray)^m``; the wall
is Lambertian with a wet specular lobe ``cos(i)^shininess``; output is gamma-encoded 8-bit RGB. Far lumen is dark,
which draws the "tunnel" of real capsule frames. Sensor noise is separate (:class:`SensorNoise`).

Result data form: ``rgb uint8 (h, w, 3)``, ``range_m float32 (h, w)`` (distance from the camera centre along the
pixel's ray to the wall, metres; NaN where no wall is hit or outside the field of view).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel
from testbed.texture import Texture
from testbed.tube import Tube, TubeMesh

__all__ = ["Lighting", "RenderResult", "RaycastRenderer", "SensorNoise", "encode_range", "decode_range"]

RANGE_SCALE_M = 1e-4  # 16-bit range PNGs store units of 0.1 mm: 0.05 mm quantisation, 6.5 m span; 0 = no hit


@dataclass(frozen=True)
class Lighting:
    """Capsule illumination and exposure.

    ``intensity`` is the brightness of a Lambertian wall of albedo 1 seen head-on at ``ref_distance_m``.
    """

    intensity: float = 1.6
    ref_distance_m: float = 0.015
    led_exponent: float = 1.0
    specular: float = 0.35
    shininess: float = 60.0
    gamma: float = 2.2


@dataclass(frozen=True)
class SensorNoise:
    """Additive Gaussian read noise (std in 8-bit levels) and shot-like noise proportional to sqrt(signal)."""

    read_std: float = 1.5
    shot_std: float = 1.0

    def apply(self, rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if self.read_std <= 0 and self.shot_std <= 0:
            return rgb.copy()
        x = rgb.astype(np.float32)
        sigma = np.sqrt(self.read_std**2 + self.shot_std**2 * x / 16.0)
        x += rng.normal(size=x.shape).astype(np.float32) * sigma
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class RenderResult:
    rgb: np.ndarray
    range_m: np.ndarray


def encode_range(range_m: np.ndarray) -> np.ndarray:
    """Range in metres (NaN = none) to uint16 in units of ``RANGE_SCALE_M`` (0 = none)."""
    r = np.where(np.isfinite(range_m), np.rint(range_m / RANGE_SCALE_M), 0)
    return np.clip(r, 0, 65535).astype(np.uint16)


def decode_range(png16: np.ndarray) -> np.ndarray:
    r = png16.astype(np.float32) * RANGE_SCALE_M
    r[png16 == 0] = np.nan
    return r


class RaycastRenderer:
    """Exact per-pixel ray casting of a :class:`~testbed.tube.Tube`.

    Parameters
    ----------
    tube : Tube
    texture : Texture
    camera : CameraModel
    lighting : Lighting
    mesh : TubeMesh, optional, reuse an already built mesh.
    """

    def __init__(self, tube: Tube, texture: Texture, camera: CameraModel, lighting: Lighting = Lighting(),
                 mesh: TubeMesh | None = None):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.tube = tube
        self.texture = texture
        self.camera = camera
        self.lighting = lighting
        self.mesh = mesh if mesh is not None else tube.mesh()
        # Embree works in float32: express vertices relative to the mesh centre to keep precision (~10 nm here).
        self._origin = self.mesh.vertices_w.mean(axis=0)
        self._scene = rtcore_scene.EmbreeScene()
        self._tm = TriangleMesh(
            self._scene,
            np.ascontiguousarray(self.mesh.vertices_w - self._origin, dtype=np.float32),
            np.ascontiguousarray(self.mesh.faces, dtype=np.int32),
        )
        rays_c, valid = camera.pixel_rays()
        self._pix = np.nonzero(valid.ravel())[0]
        self._rays_c = rays_c.reshape(-1, 3)[self._pix]
        self._cos_axis = np.clip(self._rays_c[:, 2], 0.0, 1.0)
        self._pix_angle = self._pixel_angle(camera, valid)

    @staticmethod
    def _pixel_angle(camera: CameraModel, valid: np.ndarray) -> np.ndarray:
        """Angular size (rad) of each valid pixel: angle between rays one pixel apart (for texture filtering)."""
        uv = camera.pixel_grid().reshape(-1, 2)[np.nonzero(valid.ravel())[0]]
        r0, _ = camera.unproject(uv)
        r1, _ = camera.unproject(uv + [1.0, 0.0])
        r2, _ = camera.unproject(uv + [0.0, 1.0])
        a1 = np.arccos(np.clip(np.sum(r0 * r1, axis=1), -1, 1))
        a2 = np.arccos(np.clip(np.sum(r0 * r2, axis=1), -1, 1))
        return np.maximum(a1, a2)

    def cast(self, origins_w: np.ndarray, dirs_w: np.ndarray):
        """Cast rays; returns ``(range_m (n,), prim (n,) int, u (n,), v (n,))`` with ``prim = -1`` on a miss."""
        o = np.ascontiguousarray(origins_w - self._origin, dtype=np.float32)
        d = np.ascontiguousarray(dirs_w, dtype=np.float32)
        res = self._scene.run(o, d, output=1)
        prim = res["primID"].astype(np.int64)
        t = res["tfar"].astype(np.float64)
        miss = (prim < 0) | ~np.isfinite(t) | (t > 1e20)
        prim[miss] = -1
        t[miss] = np.nan
        return t, prim, res["u"].astype(np.float64), res["v"].astype(np.float64)

    def render(self, R_w_c: Rotation | np.ndarray, t_w_c: np.ndarray) -> RenderResult:
        """Render the view of a camera with pose ``T_w_c = (R_w_c, t_w_c)`` (``p_w = R_w_c p_c + t_w_c``)."""
        R = R_w_c.as_matrix() if isinstance(R_w_c, Rotation) else np.asarray(R_w_c, dtype=np.float64)
        t_w_c = np.asarray(t_w_c, dtype=np.float64).reshape(3)
        cam = self.camera
        dirs_w = self._rays_c @ R.T
        rng_m, prim, bu, bv = self.cast(np.broadcast_to(t_w_c, dirs_w.shape), dirs_w)
        hit = prim >= 0
        h, w = cam.height, cam.width
        rgb = np.zeros((h * w, 3), np.uint8)
        range_img = np.full(h * w, np.nan, np.float32)
        if hit.any():
            pix = self._pix[hit]
            tri = self.mesh.faces[prim[hit]]
            w1, w2 = bu[hit], bv[hit]
            w0 = 1.0 - w1 - w2
            bary = np.stack([w0, w1, w2], axis=1)[:, :, None]
            s = np.sum(bary[:, :, 0] * self.mesh.s_m[tri], axis=1)
            phi = np.sum(bary[:, :, 0] * self.mesh.phi_rad[tri], axis=1)
            n = np.sum(bary * self.mesh.normals_w[tri], axis=1)
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            d = dirs_w[hit]
            t = rng_m[hit]
            cos_i = np.clip(-np.sum(n * d, axis=1), 0.0, 1.0)
            footprint = t * self._pix_angle[hit] / np.maximum(cos_i, 0.2)
            albedo = self.texture.sample(s, phi, footprint)
            L = self.lighting
            irr = L.intensity * (L.ref_distance_m / t) ** 2 * self._cos_axis[hit] ** L.led_exponent
            col = albedo * (irr * cos_i)[:, None] + (L.specular * irr * cos_i**L.shininess)[:, None]
            col = np.clip(col, 0.0, 1.0) ** (1.0 / L.gamma)
            rgb[pix] = np.rint(col * 255.0).astype(np.uint8)
            range_img[pix] = t
        return RenderResult(rgb.reshape(h, w, 3), range_img.reshape(h, w))

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

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel
from testbed.texture import Texture
from testbed.tube import Tube, TubeMesh

__all__ = ["RENDER_BACKENDS", "make_renderer", "Lighting", "RenderResult", "RaycastRenderer", "TubeRenderer", "SensorNoise", "encode_range", "decode_range"]

RENDER_BACKENDS = ("raycast", "pyrender")
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
    # Automatic light control (capsules adapt LED power per frame): scale so that the given percentile of the
    # linear pixel values is at most ``auto_exposure_level``; only ever dims (0 = off, the default).
    auto_exposure_percentile: float = 0.0
    auto_exposure_level: float = 0.85


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
    exposure: float = 1.0  # the automatic light control's gain on this frame (Lighting.auto_exposure_percentile)


def encode_range(range_m: np.ndarray) -> np.ndarray:
    """Range in metres (NaN = none) to uint16 in units of ``RANGE_SCALE_M`` (0 = none)."""
    r = np.where(np.isfinite(range_m), np.rint(range_m / RANGE_SCALE_M), 0)
    return np.clip(r, 0, 65535).astype(np.uint16)


def decode_range(png16: np.ndarray) -> np.ndarray:
    r = png16.astype(np.float32) * RANGE_SCALE_M
    r[png16 == 0] = np.nan
    return r


class TubeRenderer:
    """Shared part of the tube renderers: per-pixel rays of the camera model and the shading model.

    Subclasses decide visibility (which triangle each pixel's ray meets first) in :meth:`_visible`; the colour of
    a hit is computed here from the exact ray, so every backend shades identically.
    """

    def __init__(self, tube: Tube, texture: Texture, camera: CameraModel, lighting: Lighting = Lighting(),
                 mesh: TubeMesh | None = None):
        self.tube = tube
        self.texture = texture
        self.camera = camera
        self.lighting = lighting
        self.mesh = mesh if mesh is not None else tube.mesh()
        # Work relative to the mesh centre: Embree and OpenGL are float32 (~10 nm here instead of ~0.1 um).
        self._origin = self.mesh.vertices_w.mean(axis=0)
        rays_c, valid = camera.pixel_rays()
        self._pix = np.nonzero(valid.ravel())[0]
        self._rays_c = rays_c.reshape(-1, 3)[self._pix]
        self._led = (np.clip(self._rays_c[:, 2], 0.0, 1.0) ** lighting.led_exponent).astype(np.float32)
        self._pix_angle = self._pixel_angle(camera, valid).astype(np.float32)
        self._attr = self._attributes(self.mesh)

    @staticmethod
    def _attributes(m: TubeMesh) -> np.ndarray:
        """Per-vertex ``(s_m, phi_rad, nx, ny, nz)`` in float32: one gather per triangle corner when shading."""
        return np.ascontiguousarray(np.c_[m.s_m, m.phi_rad, m.normals_w], dtype=np.float32)

    def set_mesh(self, mesh: TubeMesh) -> None:
        """Render from now on against ``mesh`` (a moving wall, :mod:`testbed.motility`: one mesh per frame)."""
        self.mesh = mesh
        self._attr = self._attributes(mesh)

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

    def _visible(self, R_w_c: np.ndarray, t_w_c: np.ndarray, dirs_w: np.ndarray):
        raise NotImplementedError

    def render(self, R_w_c: Rotation | np.ndarray, t_w_c: np.ndarray) -> RenderResult:
        """Render the view of a camera with pose ``T_w_c = (R_w_c, t_w_c)`` (``p_w = R_w_c p_c + t_w_c``)."""
        R = R_w_c.as_matrix() if isinstance(R_w_c, Rotation) else np.asarray(R_w_c, dtype=np.float64)
        t_w_c = np.asarray(t_w_c, dtype=np.float64).reshape(3)
        dirs_w = self._rays_c @ R.T
        rng_m, prim, bu, bv = self._visible(R, t_w_c, dirs_w)
        return self._shade(dirs_w, rng_m, prim, bu, bv)

    def _shade(self, dirs_w, rng_m, prim, bu, bv) -> RenderResult:
        """Colour and range images from per-ray hits (shared by every visibility backend)."""
        cam = self.camera
        hit = np.nonzero(prim >= 0)[0]
        h, w = cam.height, cam.width
        rgb = np.zeros((h * w, 3), np.uint8)
        range_img = np.full(h * w, np.nan, np.float32)
        exposure = 1.0
        if len(hit):
            attr = self._attr
            tri = self.mesh.faces[prim[hit]]
            w1 = bu[hit].astype(np.float32)[:, None]
            w2 = bv[hit].astype(np.float32)[:, None]
            # barycentric interpolation of (s, phi, normal) in float32 (s to ~0.2 um over 2.5 m: ample here)
            a = attr[tri[:, 0]]
            a += w1 * (attr[tri[:, 1]] - a) + w2 * (attr[tri[:, 2]] - a)
            s, phi, n = a[:, 0], a[:, 1], a[:, 2:5]
            d = dirs_w[hit].astype(np.float32)
            t = rng_m[hit].astype(np.float32)
            n_len = np.sqrt(np.einsum("ij,ij->i", n, n))
            cos_i = np.clip(-np.einsum("ij,ij->i", n, d) / n_len, 0.0, 1.0)
            footprint = t * self._pix_angle[hit] / np.maximum(cos_i, 0.2)
            albedo = self.texture.sample(s, phi, footprint)
            L = self.lighting
            irr = np.float32(L.intensity * L.ref_distance_m**2) / (t * t) * self._led[hit]
            diffuse = irr * cos_i
            col = albedo * diffuse[:, None]
            if L.specular > 0:
                col += (np.float32(L.specular) * irr * cos_i ** np.float32(L.shininess))[:, None]
            if L.auto_exposure_percentile > 0:
                level = float(np.percentile(col.max(axis=1), L.auto_exposure_percentile))
                if level > L.auto_exposure_level:
                    exposure = L.auto_exposure_level / level
                    col *= np.float32(exposure)
            np.clip(col, 0.0, 1.0, out=col)
            np.power(col, np.float32(1.0 / L.gamma), out=col)
            rgb[self._pix[hit]] = np.rint(col * np.float32(255.0)).astype(np.uint8)
            range_img[self._pix[hit]] = t
        return RenderResult(rgb.reshape(h, w, 3), range_img.reshape(h, w), float(exposure))


class RaycastRenderer(TubeRenderer):
    """Exact per-pixel ray casting of a :class:`~testbed.tube.Tube` with Embree (the default backend).

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
        super().__init__(tube, texture, camera, lighting, mesh)
        self._build_scene()

    def _build_scene(self) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self._scene = rtcore_scene.EmbreeScene()
        self._tm = TriangleMesh(
            self._scene,
            np.ascontiguousarray(self.mesh.vertices_w - self._origin, dtype=np.float32),
            np.ascontiguousarray(self.mesh.faces, dtype=np.int32),
        )

    def set_mesh(self, mesh: TubeMesh) -> None:
        super().set_mesh(mesh)
        self._build_scene()

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

    def _visible(self, R_w_c: np.ndarray, t_w_c: np.ndarray, dirs_w: np.ndarray):
        """Which triangle each valid pixel's ray hits first: ``(range_m, prim, u, v)`` (``prim = -1``: none)."""
        return self.cast(np.broadcast_to(t_w_c, dirs_w.shape), dirs_w)


def make_renderer(backend: str, tube: Tube, texture: Texture, camera: CameraModel, lighting: Lighting = Lighting(),
                  mesh: TubeMesh | None = None) -> TubeRenderer:
    """A renderer by backend name: ``"raycast"`` (Embree, CPU, default) or ``"pyrender"`` (OpenGL through EGL)."""
    if backend == "raycast":
        return RaycastRenderer(tube, texture, camera, lighting, mesh)
    if backend == "pyrender":
        from testbed.render_gl import PyrenderRenderer

        return PyrenderRenderer(tube, texture, camera, lighting, mesh)
    raise ValueError(f"unknown render backend {backend!r}; choose from {RENDER_BACKENDS}")

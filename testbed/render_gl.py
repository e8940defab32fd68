"""The pyrender/OpenGL rendering backend (headless EGL): rasterised visibility, the same shading as ray casting.

pyrender cameras are pinhole only and a capsule lens is a ~156-170 degree fisheye, so this backend rasterises a
*cube map*: one 90-degree pinhole view per cube face the camera's field of view reaches (five for a forward
fisheye under 180 degrees). Each face is drawn flat-shaded with every triangle's index encoded in its colour (a
24-bit "triangle-ID buffer"), and each fisheye pixel looks up the triangle its own ray falls on. The range and the
surface coordinates then come from intersecting that exact ray with that triangle (Moller-Trumbore), and the
colour from :meth:`testbed.render.TubeRenderer._shade`: geometry stays exact for any camera model and both
backends shade identically. Where the rasteriser and the exact ray disagree (pixels on a triangle edge or an
occlusion boundary) the neighbouring triangle's plane is used, which on a smooth tube differs by micrometres.

Facts this module relies on (measured, see STACK-NOTES.md): ``PYOPENGL_PLATFORM=egl`` must be set before pyrender
is imported; pyrender 0.1.45 still uses ``np.infty`` (removed in numpy 2), shimmed here; pyrender's multisampling
(4x MSAA) would blend triangle IDs on edges, so it is switched off for this backend's draws; ``znear`` is 1 mm
(pyrender's 5 cm default would clip the whole wall).

Speed: five face draws per frame make this backend slower than Embree ray casting (see
``benchmarks/bench_render.py``); it exists for GPU machines and for cross-checking the ray caster.
"""

from __future__ import annotations

import os

import numpy as np

from bodyslam.camera import CameraModel
from bodyslam.errors import ConfigError
from testbed.render import Lighting, TubeRenderer
from testbed.texture import Texture
from testbed.tube import Tube, TubeMesh

__all__ = ["PyrenderRenderer"]

# Cube faces as rotations R_c_f (columns: face x, y, z axes in the capsule camera frame; OpenCV convention).
_FACES = {
    "+z": np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
    "+x": np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float),
    "-x": np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float),
    "+y": np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float),
    "-y": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float),
    "-z": np.array([[-1, 0, 0], [0, 1, 0], [0, 0, -1]], float),
}
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes (x right, y down, z forward) -> OpenGL (y up, -z fwd)


def _import_pyrender():
    """Import pyrender headless, with the two compatibility fixes this backend needs."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if not hasattr(np, "infty"):
        np.infty = np.inf  # pyrender 0.1.45 uses the alias numpy 2 removed
    try:
        import pyrender
        import pyrender.renderer as prr
    except Exception as exc:  # noqa: BLE001 - any import failure means: no GL here
        raise ConfigError(f"the pyrender backend is unavailable: {exc}") from exc
    if not getattr(prr, "_bodyslam_no_msaa", False):
        from OpenGL import GL

        enable = prr.glEnable

        def _gl_enable(cap):
            if cap == GL.GL_MULTISAMPLE:  # on by default in GL: triangle IDs must not be blended across edges
                GL.glDisable(cap)
            else:
                enable(cap)

        prr.glEnable = _gl_enable
        prr._bodyslam_no_msaa = True
    return pyrender


_OFFSCREEN: dict = {}


def _offscreen(pyrender, size: int):
    """One offscreen EGL renderer per face size and process, kept for the process's life.

    pyrender's ``OffscreenRenderer.delete`` terminates the EGL display that every context of the process shares,
    which breaks any other renderer still alive; so renderers are cached here and never deleted.
    """
    key = (os.getpid(), size)
    if key not in _OFFSCREEN:
        _OFFSCREEN[key] = pyrender.OffscreenRenderer(size, size)
    return _OFFSCREEN[key]


class PyrenderRenderer(TubeRenderer):
    """Tube renderer whose visibility comes from pyrender (OpenGL through EGL) via a triangle-ID cube map.

    ``face_px`` is the side of each cube face in pixels; by default about 1.5 face pixels per camera pixel at the
    image centre, so every fisheye pixel's ray lands in its own face pixel.
    """

    def __init__(self, tube: Tube, texture: Texture, camera: CameraModel, lighting: Lighting = Lighting(),
                 mesh: TubeMesh | None = None, face_px: int | None = None):
        super().__init__(tube, texture, camera, lighting, mesh)
        pyrender = _import_pyrender()
        nf = len(self.mesh.faces)
        if nf >= 2**24 - 1:
            raise ConfigError(f"tube mesh has {nf} triangles; the ID buffer holds at most {2**24 - 2}")
        if face_px is None:
            # pixels per radian at the image centre of the camera, times 1.5, over the 90-degree face
            uv0 = np.array([[camera.width / 2.0, camera.height / 2.0]])
            r0, _ = camera.unproject(uv0)
            r1, _ = camera.unproject(uv0 + [1.0, 0.0])
            rad_per_px = float(np.arccos(np.clip(np.sum(r0 * r1), -1.0, 1.0)))
            face_px = int(np.ceil(1.5 * (np.pi / 2) / max(rad_per_px, 1e-6)))
        self.face_px = int(face_px)

        # Which face each pixel's ray belongs to, and where on that face it lands.
        self._face_of = {}  # face name -> bool mask over the valid rays
        self._face_pixel = {}  # face name -> flat face-pixel index of each of those rays
        for name, R_c_f in _FACES.items():
            d_f = self._rays_c @ R_c_f  # ray in face coordinates
            with np.errstate(divide="ignore", invalid="ignore"):
                x, y = d_f[:, 0] / d_f[:, 2], d_f[:, 1] / d_f[:, 2]
            on = (d_f[:, 2] > 0) & (np.abs(x) <= 1.0) & (np.abs(y) <= 1.0)
            on &= ~np.any([m for m in self._face_of.values()], axis=0) if self._face_of else True
            if not on.any():
                continue
            n = self.face_px
            col = np.clip(np.rint((x[on] + 1.0) * 0.5 * n - 0.5), 0, n - 1).astype(np.int64)
            row = np.clip(np.rint((y[on] + 1.0) * 0.5 * n - 0.5), 0, n - 1).astype(np.int64)
            self._face_of[name] = on
            self._face_pixel[name] = row * n + col

        # One flat-shaded primitive, triangle k coloured k + 1 (0 = background).
        tri = np.arange(1, nf + 1, dtype=np.int64)
        rgb = np.stack([tri & 255, (tri >> 8) & 255, (tri >> 16) & 255, np.full(nf, 255)], axis=1)
        colors = np.repeat(rgb.astype(np.float32) / 255.0, 3, axis=0)
        positions = (self.mesh.vertices_w - self._origin)[self.mesh.faces].reshape(-1, 3).astype(np.float32)
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0], alphaMode="OPAQUE",
                                                      doubleSided=True)
        prim = pyrender.Primitive(positions=positions, color_0=colors, material=material)
        self._pyrender = pyrender
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[0.0, 0.0, 0.0])
        self._scene.add(pyrender.Mesh([prim]))
        extent = float(np.ptp(self.mesh.vertices_w, axis=0).max())
        self._cam = pyrender.PerspectiveCamera(yfov=np.pi / 2, aspectRatio=1.0, znear=1e-3,
                                               zfar=max(1.0, 2.0 * extent))
        self._cam_node = self._scene.add(self._cam, pose=np.eye(4))
        self._gl = _offscreen(pyrender, self.face_px)
        self._flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.SKIP_CULL_FACES

    def set_mesh(self, mesh: TubeMesh) -> None:
        raise ConfigError("a moving wall ([motility]) needs the raycast backend: the pyrender backend uploads its "
                          "mesh once")

    def _visible(self, R_w_c: np.ndarray, t_w_c: np.ndarray, dirs_w: np.ndarray):
        n_rays = len(dirs_w)
        n = self.face_px
        prim = np.full(n_rays, -1, np.int64)
        # the 3x3 neighbourhood of each ray's face pixel: candidates where the ray is off its pixel's triangle
        cand = np.full((n_rays, 9), -1, np.int64)
        pose = np.eye(4)
        pose[:3, 3] = t_w_c - self._origin
        for name, on in self._face_of.items():
            pose[:3, :3] = R_w_c @ _FACES[name] @ _CV_TO_GL
            self._scene.set_pose(self._cam_node, pose)
            color, _ = self._gl.render(self._scene, flags=self._flags)
            c = color.astype(np.int64)
            ids = np.pad((c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16)) - 1, 1, constant_values=-1)
            idx = self._face_pixel[name]
            row, col = idx // n + 1, idx % n + 1
            prim[on] = ids[row, col]
            cand[on] = np.stack([ids[row + dr, col + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], axis=1)
        t, u, v, inside = self._intersect(t_w_c, dirs_w, prim)
        redo = np.nonzero((prim >= 0) & ~inside)[0]
        if len(redo):
            best_t = np.full(len(redo), np.inf)
            for j in range(9):
                pj = cand[redo, j]
                tj, uj, vj, ij = self._intersect(t_w_c, dirs_w[redo], pj.copy())
                better = ij & (tj < best_t)
                best_t[better] = tj[better]
                sel = redo[better]
                prim[sel], t[sel], u[sel], v[sel] = pj[better], tj[better], uj[better], vj[better]
        return t, prim, u, v

    def _intersect(self, t_w_c: np.ndarray, dirs_w: np.ndarray, prim: np.ndarray):
        """Exact ray/triangle-plane intersection (Moller-Trumbore): ``(range, u, v, inside_triangle)``.

        ``prim`` entries whose plane the ray does not meet in front of the camera are set to -1.
        """
        t = np.full(len(prim), np.nan)
        u = np.zeros(len(prim))
        v = np.zeros(len(prim))
        inside = np.zeros(len(prim), bool)
        hit = prim >= 0
        if hit.any():
            tri = self.mesh.faces[prim[hit]]
            p0 = self.mesh.vertices_w[tri[:, 0]] - t_w_c
            e1 = self.mesh.vertices_w[tri[:, 1]] - self.mesh.vertices_w[tri[:, 0]]
            e2 = self.mesh.vertices_w[tri[:, 2]] - self.mesh.vertices_w[tri[:, 0]]
            d = dirs_w[hit]
            pvec = np.cross(d, e2)
            det = np.sum(e1 * pvec, axis=1)
            ok = np.abs(det) > 1e-18
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tvec = -p0
            uu = np.sum(tvec * pvec, axis=1) * inv
            qvec = np.cross(tvec, e1)
            vv = np.sum(d * qvec, axis=1) * inv
            tt = np.sum(e2 * qvec, axis=1) * inv
            ok &= tt > 0
            eps = 1e-9
            ins = ok & (uu >= -eps) & (vv >= -eps) & (uu + vv <= 1 + eps)
            idx = np.nonzero(hit)[0]
            t[idx[ok]], u[idx[ok]], v[idx[ok]] = tt[ok], uu[ok], vv[ok]
            inside[idx] = ins
            prim[idx[~ok]] = -1
        return t, u, v, inside

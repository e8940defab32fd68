"""The intestine tube: a circle of the local lumen radius swept along a centre line.

Data form: a :class:`Tube` holds a :class:`~testbed.centerline.Centerline` and optional circular-fold geometry;
:meth:`Tube.mesh` gives a ring-grid triangle mesh (``vertices_w (n_rings * (sections + 1), 3)`` metres, faces
``(m, 3)`` int, per-vertex inward unit normals and surface coordinates ``(s_m, phi_rad)``). The seam at
``phi = 2 pi`` is duplicated so texture coordinates stay periodic around the circumference.

The surface point at arc length ``s`` and angle ``phi`` is
``c(s) + rho(s, phi) (cos(phi) n(s) + sin(phi) b(s))`` with ``(n, b)`` the rotation-minimising frame,
``rho = r(s) (1 - fold(s, phi))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bodyslam.errors import ConfigError
from testbed.centerline import Centerline

__all__ = ["Folds", "Tube", "TubeMesh"]


@dataclass(frozen=True)
class Folds:
    """Circular folds (plicae circulares) as a radial bulge into the lumen.

    ``depth_frac`` is the fold height as a fraction of the radius (0 disables), ``spacing_m`` the distance between
    folds along the lumen, ``width_m`` the fold's full width at half height, ``coverage`` the fraction of the
    circumference a fold spans (real folds are often crescents, not full rings).
    """

    depth_frac: float = 0.0
    spacing_m: float = 0.008
    width_m: float = 0.002
    coverage: float = 0.7
    # A partly collapsed lumen: ``lobes`` longitudinal folds make the cross-section star-shaped, the wall between
    # them pushed in by up to ``lobe_depth_frac`` of the radius; the star turns along the gut by
    # ``lobe_twist_rad_per_m`` (0 lobes: a round lumen).
    lobes: int = 0
    lobe_depth_frac: float = 0.0
    lobe_twist_rad_per_m: float = 15.0

    def __post_init__(self) -> None:
        if not (0 <= self.depth_frac < 0.8 and 0 <= self.lobe_depth_frac < 0.6):
            raise ConfigError(f"fold depth must be in [0, 0.8) and lobe depth in [0, 0.6) of the radius, got "
                              f"{self.depth_frac}, {self.lobe_depth_frac}")
        if self.lobes < 0 or self.lobes > 12:
            raise ConfigError(f"lobes must be 0-12, got {self.lobes}")

    def profile(self, s_m: np.ndarray, phi: np.ndarray, phase: float = 0.0) -> np.ndarray:
        """Fractional inward bulge at ``(s, phi)`` (circular folds and the lobes of a collapsed lumen, at most
        0.85 of the radius); broadcasting arrays."""
        out = self._folds(s_m, phi, phase)
        if self.lobes and self.lobe_depth_frac > 0:
            star = 0.5 + 0.5 * np.cos(self.lobes * (phi - self.lobe_twist_rad_per_m * s_m))
            out = np.minimum(out + self.lobe_depth_frac * star ** 2, 0.85)
        return out

    def _folds(self, s_m, phi, phase: float) -> np.ndarray:
        if self.depth_frac <= 0:
            return np.zeros(np.broadcast(s_m, phi).shape)
        k = np.round(s_m / self.spacing_m)
        d = s_m - k * self.spacing_m
        sigma = self.width_m / 2.3548
        along = np.exp(-0.5 * (d / sigma) ** 2)
        # Each fold k covers an arc centred at a pseudo-random angle (a hash of k), so folds look like crescents.
        centre = (np.sin(k * 12.9898 + phase) * 43758.5453) % (2 * math.pi)
        dphi = np.angle(np.exp(1j * (phi - centre)))
        half = math.pi * self.coverage
        around = np.clip((half - np.abs(dphi)) / 0.4, 0.0, 1.0) if self.coverage < 1 else 1.0
        return self.depth_frac * along * around


@dataclass(frozen=True, eq=False)
class TubeMesh:
    vertices_w: np.ndarray  # (nv, 3) float64, metres
    faces: np.ndarray  # (nf, 3) int32
    normals_w: np.ndarray  # (nv, 3) float64, unit, pointing into the lumen
    s_m: np.ndarray  # (nv,) arc length of each vertex
    phi_rad: np.ndarray  # (nv,) angle around the axis, in [0, 2 pi] (seam duplicated)


@dataclass(frozen=True, eq=False)
class Tube:
    centerline: Centerline
    folds: Folds = field(default_factory=Folds)
    sections: int = 96
    ring_spacing_m: float = 0.0015

    def __post_init__(self) -> None:
        if self.sections < 8:
            raise ConfigError(f"tube needs at least 8 sections around, got {self.sections}")
        if not (0 < self.ring_spacing_m < 0.05):
            raise ConfigError(f"ring spacing must be in (0, 0.05) m, got {self.ring_spacing_m}")

    def surface_point(self, s_m, phi_rad) -> np.ndarray:
        """World points ``(n, 3)`` of the wall at arc lengths ``s_m`` and angles ``phi_rad`` (broadcast, 1-D)."""
        s_m, phi = np.broadcast_arrays(np.atleast_1d(s_m).astype(float), np.atleast_1d(phi_rad).astype(float))
        p, R, r = self.centerline.frame_at(s_m)
        rho = r * (1.0 - self.folds.profile(s_m, phi))
        radial = np.cos(phi)[:, None] * R[:, :, 0] + np.sin(phi)[:, None] * R[:, :, 1]
        return p + rho[:, None] * radial

    def ring_s(self) -> np.ndarray:
        """Arc lengths of the mesh's rings (``ring_spacing_m`` apart, both ends included)."""
        n_rings = int(math.floor(self.centerline.length_m / self.ring_spacing_m)) + 1
        return np.linspace(0.0, self.centerline.length_m, n_rings)

    def mesh(self) -> TubeMesh:
        return self._grid_mesh(self.ring_s())

    def mesh_window(self, s_lo_m: float, s_hi_m: float, radius_factor=None) -> TubeMesh:
        """The mesh's rings with ``s_lo_m <= s <= s_hi_m`` (the same rings as :meth:`mesh`), each wall point pulled
        toward its centre-line point by ``radius_factor(s_m (n_rings,)) -> (n_rings,)`` when given: a moving wall
        (:mod:`testbed.motility`). Normals from the deformed grid."""
        s = self.ring_s()
        s = s[(s >= s_lo_m) & (s <= s_hi_m)]
        if len(s) < 2:
            raise ConfigError(f"no tube between s = {s_lo_m:.3f} and {s_hi_m:.3f} m")
        return self._grid_mesh(s, radius_factor)

    def _grid_mesh(self, s: np.ndarray, radius_factor=None) -> TubeMesh:
        n_rings = len(s)
        phi = np.linspace(0.0, 2 * math.pi, self.sections + 1)
        S, PHI = np.meshgrid(s, phi, indexing="ij")
        V = self.surface_point(S.ravel(), PHI.ravel()).reshape(n_rings, self.sections + 1, 3)
        if radius_factor is not None:
            c = self.centerline.frame_at(s)[0][:, None, :]
            V = c + (V - c) * np.asarray(radius_factor(s), dtype=np.float64)[:, None, None]
        # Normals from the grid: with n x b = t, dP/ds x dP/dphi = t x (r e_phi) = -r e_radial points into the lumen.
        dPds = np.gradient(V, s, axis=0)
        dPdphi = np.gradient(V, phi, axis=1)
        dPdphi[:, 0] = dPdphi[:, -1] = 0.5 * (
            (V[:, 1] - V[:, 0]) / (phi[1] - phi[0]) + (V[:, -1] - V[:, -2]) / (phi[-1] - phi[-2])
        )
        N = np.cross(dPds, dPdphi)
        N /= np.linalg.norm(N, axis=-1, keepdims=True)
        idx = np.arange(n_rings * (self.sections + 1)).reshape(n_rings, self.sections + 1)
        a, b = idx[:-1, :-1], idx[:-1, 1:]
        c, d = idx[1:, :-1], idx[1:, 1:]
        faces = np.concatenate([np.stack([a, d, b], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
        return TubeMesh(
            vertices_w=V.reshape(-1, 3),
            faces=faces.astype(np.int32),
            normals_w=N.reshape(-1, 3),
            s_m=S.ravel(),
            phi_rad=PHI.ravel(),
        )

    def locate(self, points_w: np.ndarray, s_hint_m: np.ndarray | None = None, window_m: float = 0.05):
        """Tube coordinates of points: ``(s_m, rho_m, phi_rad)`` of the nearest centre-line sample.

        With ``s_hint_m`` the search is limited to ``+-window_m`` around the hint (needed near loops that come
        close, where the globally nearest sample may belong to another loop).
        """
        cl = self.centerline
        pts = np.atleast_2d(points_w)
        out_s = np.empty(len(pts))
        for i, p in enumerate(pts):
            if s_hint_m is None:
                lo, hi = 0, len(cl.s_m)
            else:
                c = int(cl.index_at(np.atleast_1d(s_hint_m)[i]))
                w = int(window_m / cl.ds_m)
                lo, hi = max(0, c - w), min(len(cl.s_m), c + w + 1)
            d = cl.points_w[lo:hi] - p
            j = lo + int(np.argmin(np.einsum("ij,ij->i", d, d)))
            # refine along the tangent
            out_s[i] = np.clip(cl.s_m[j] + (p - cl.points_w[j]) @ cl.tangents_w[j], 0.0, cl.length_m)
        c, R, _ = cl.frame_at(out_s)
        rel = np.einsum("nji,nj->ni", R, pts - c)
        return out_s, np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0]) % (2 * math.pi)

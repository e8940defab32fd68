"""Lumen content: turbid fluid pooled in the gut and debris floating in it (issue 15, item 1 "Content").

Both are drawn into a rendered frame from the frame's own geometry -- the camera pose, its pixels' rays and the
range image (the distance to the wall along each ray) -- so they sit in 3-D, persist from frame to frame and are
hidden by the wall where the wall is nearer. ``depth/`` stays the range to the wall (the ground truth of the
lumen's shape); the pipeline sees content only as a capsule would, in the pixels.

:class:`Fluid` (``[fluid]``): chyme pools on the posterior (dependent) side of a supine patient, -y in the body
frame (SPEC.md: y anterior). Along the gut, wet stretches (``wet_length_m`` on average, ``wet_frac`` of the gut)
hold fluid up to a height ``fill_frac`` of the local lumen's diameter (drawn per stretch between 0 and
``fill_max``). A frame's fluid surface is the horizontal plane at that height above the lowest point of the lumen
at the capsule. Light from the capsule crosses the fluid to the wall and back: the wall's linear radiance is
attenuated by ``exp(-2 kappa L)`` (Beer-Lambert over the ray's length ``L`` below the surface), and the fluid
adds the light it scatters back, ``scatter_albedo kappa colour`` times the capsule's irradiance integrated along
that length with the same attenuation (:meth:`Fluid.apply`). Stated choices: ``kappa`` 25 /m by default (40 in
`realistic`: a 2 cm round trip keeps 20% of the wall), half of it scattering, a yellow-green colour as capsule
images of bile-stained chyme show.

:class:`Debris` (``[debris]``): particles of food residue and mucus, ``per_m`` per metre of gut, 0.3-2.5 mm across,
spread over the lumen's cross-section and drifting with the content (``drift_m_s``: a mean aboral drift with a
per-particle spread, and a slow wander of ~1 mm). Each is drawn as a lit, irregular dark blob where it lies in
front of the wall. Stated choices, no source: debris load varies widely between exams and with bowel preparation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from bodyslam.errors import ConfigError
from testbed.motility import draw_stretches

__all__ = ["Fluid", "Debris", "LumenContent"]

DOME_M = 0.005  # the capsule's dome around the lens: no fluid nearer than this


@dataclass(frozen=True)
class Fluid:
    wet_frac: float = 0.0  # 0: no fluid (the default)
    wet_length_m: float = 0.06
    fill_max: float = 0.5
    kappa_per_m: float = 25.0
    colour: tuple[float, float, float] = (0.62, 0.60, 0.22)
    scatter_albedo: float = 0.5  # the part of the extinction that is scattering (the rest is absorbed)
    stretches: tuple[tuple[float, float, float], ...] = ()  # (start, end, fill fraction), drawn per seed

    def __post_init__(self) -> None:
        if not (0.0 <= self.wet_frac <= 1.0 and 0.0 < self.fill_max <= 1.0 and self.kappa_per_m >= 0
                and 0.0 <= self.scatter_albedo <= 1.0
                and self.wet_length_m > 0 and len(self.colour) == 3 and all(0 <= c <= 1 for c in self.colour)):
            raise ConfigError("[fluid]: wet_frac in [0, 1], fill_max in (0, 1], kappa_per_m >= 0, scatter_albedo in "
                              "[0, 1], wet_length_m > 0, colour three numbers in [0, 1]")

    @property
    def active(self) -> bool:
        return self.wet_frac > 0

    def drawn(self, length_m: float, rng: np.random.Generator) -> "Fluid":
        if not self.active:
            return self
        spans = draw_stretches(length_m, self.wet_length_m, self.wet_frac, rng)
        fills = rng.uniform(0.1 * self.fill_max, self.fill_max, size=len(spans))
        return replace(self, stretches=tuple((a, b, float(f)) for (a, b), f in zip(spans, fills)))

    def fill_at(self, s_m: float) -> float:
        for a, b, f in self.stretches:
            if a <= s_m <= b:
                return f
        return 0.0

    def apply(self, lin: np.ndarray, dirs_w: np.ndarray, range_m: np.ndarray, p_w_c: np.ndarray,
              level_y_m: float, irradiance) -> None:
        """Attenuate and tint linear radiance ``lin (n, 3)`` of rays ``dirs_w (n, 3)`` from ``p_w_c`` that meet
        the wall at ``range_m (n,)``, below the surface ``y = level_y_m``; in place. ``irradiance(d_m)``: the
        capsule light's irradiance at distance ``d_m``.

        The ray's part below the surface is one interval ``[d0, d0 + L]`` (a plane cuts a segment once): the wall
        behind it is seen through ``exp(-2 kappa L)``, and the fluid adds the single-scattered light
        ``scatter_albedo kappa colour \\int irradiance(d) exp(-2 kappa (d - d0)) dd`` over it (8-point midpoint
        rule; nothing nearer than the capsule's dome, ``DOME_M``)."""
        y0 = p_w_c[1]
        y1 = y0 + dirs_w[:, 1] * range_m
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.clip((level_y_m - y0) / (y1 - y0), 0.0, 1.0)  # where the ray crosses the surface, in [0, 1]
        if y0 < level_y_m:  # submerged camera: the fluid is the ray's first part, up to the surface if it rises
            start, frac = np.zeros_like(u), np.where(y1 < level_y_m, 1.0, u)
        else:  # camera above: the part after the crossing, if the ray goes down
            start, frac = np.where(y1 < level_y_m, u, 1.0), np.where(y1 < level_y_m, 1.0 - u, 0.0)
        L = frac * range_m
        d0 = start * range_m
        T = np.exp(-2.0 * self.kappa_per_m * L)
        lin *= T[:, None].astype(np.float32)
        scattered = np.zeros_like(L)
        for m in range(8):
            d = d0 + (m + 0.5) / 8.0 * L
            scattered += irradiance(np.maximum(d, DOME_M)) * np.exp(-2.0 * self.kappa_per_m * (d - d0)) * (L / 8.0)
        lin += (self.scatter_albedo * self.kappa_per_m * scattered)[:, None].astype(np.float32) \
            * np.asarray(self.colour, np.float32)[None, :]


@dataclass(frozen=True)
class Debris:
    """Scenario section ``[debris]`` (module docstring); the particles themselves are drawn per seed
    (:meth:`LumenContent.draw`)."""

    per_m: float = 0.0  # 0: no debris (the default)
    size_m: tuple[float, float] = (0.0003, 0.0025)
    drift_m_s: tuple[float, float] = (0.0005, 0.001)  # mean aboral drift, per-particle spread
    wander_m: float = 0.001
    max_range_m: float = 0.08

    def __post_init__(self) -> None:
        if not (self.per_m >= 0 and 0 < self.size_m[0] <= self.size_m[1] <= 0.01 and self.drift_m_s[1] >= 0
                and self.wander_m >= 0 and self.max_range_m > 0):
            raise ConfigError("[debris]: per_m >= 0, 0 < size_m[0] <= size_m[1] <= 0.01, drift spread, wander and "
                              "max_range_m >= 0")

    @property
    def active(self) -> bool:
        return self.per_m > 0


@dataclass(frozen=True, eq=False)
class LumenContent:
    """This seed's fluid and particles, drawn into rendered frames (:meth:`apply`)."""

    fluid: Fluid
    debris: Debris
    particles: np.ndarray  # (n, 8): s0, radial fraction, phi, size, drift speed, wander phase, albedo, shape seed

    @classmethod
    def draw(cls, fluid: Fluid, debris: Debris, length_m: float, rng: np.random.Generator) -> "LumenContent":
        fluid = fluid.drawn(length_m, rng)
        n = int(rng.poisson(debris.per_m * length_m)) if debris.active else 0
        parts = np.c_[rng.uniform(0, length_m, n), 0.85 * np.sqrt(rng.uniform(0, 1, n)),
                      rng.uniform(0, 2 * math.pi, n),
                      np.exp(rng.uniform(math.log(debris.size_m[0]), math.log(debris.size_m[1]), n)),
                      rng.normal(debris.drift_m_s[0], debris.drift_m_s[1], n), rng.uniform(0, 2 * math.pi, n),
                      rng.uniform(0.15, 0.45, n), rng.integers(0, 2**31, n)]
        return cls(fluid, debris, parts.reshape(-1, 8))

    @property
    def active(self) -> bool:
        return self.fluid.active or len(self.particles) > 0

    def particle_points_w(self, tube, t_s: float, s_near_m: float) -> tuple[np.ndarray, np.ndarray]:
        """World positions at time ``t_s`` of the particles within ``max_range_m`` (along the gut) of
        ``s_near_m``, and their rows."""
        P = self.particles
        s = P[:, 0] + P[:, 4] * t_s
        rows = np.nonzero(np.abs(s - s_near_m) < self.debris.max_range_m)[0]
        if len(rows) == 0:
            return np.zeros((0, 3)), rows
        P = P[rows]
        w = self.debris.wander_m
        # a slow wander of ~w along the gut and around it (w over a ~1 cm radius, in radians), periods of 15-20 s
        s = np.clip(s[rows] + w * np.sin(0.4 * t_s + P[:, 5]), 0.0, tube.centerline.length_m)
        phi = P[:, 2] + (w / 0.01) * np.sin(0.3 * t_s + 2 * P[:, 5])
        c, R, r = tube.centerline.frame_at(s)
        rho = r * P[:, 1]
        radial = np.cos(phi)[:, None] * R[:, :, 0] + np.sin(phi)[:, None] * R[:, :, 1]
        return c + rho[:, None] * radial, rows

    def apply(self, rgb: np.ndarray, range_m: np.ndarray, renderer, R_w_c: np.ndarray, p_w_c: np.ndarray,
              t_s: float, s_capsule_m: float, exposure: float = 1.0) -> np.ndarray:
        """The rendered ``rgb (h, w, 3) uint8`` with fluid and debris drawn in (a new array). ``exposure``: the
        frame's light-control gain (:attr:`testbed.render.RenderResult.exposure`), applied to what is drawn in."""
        cam, L = renderer.camera, renderer.lighting
        k_irr = L.intensity * L.ref_distance_m ** 2 * exposure

        def irradiance(d):
            return (k_irr / np.maximum(d, 1e-3) ** 2).astype(np.float32)

        out = rgb
        if self.fluid.active:
            fill = self.fluid.fill_at(s_capsule_m)
            if fill > 0:
                c, _, r = renderer.tube.centerline.frame_at(np.array([s_capsule_m]))
                level = float(c[0, 1] - r[0] + 2.0 * r[0] * fill)
                flat = range_m.reshape(-1)
                pix = np.nonzero(np.isfinite(flat))[0]
                rays_c, _ = cam.pixel_rays()
                dirs_w = rays_c.reshape(-1, 3)[pix] @ R_w_c.T
                lin = (out.reshape(-1, 3)[pix].astype(np.float32) / 255.0) ** np.float32(L.gamma)
                self.fluid.apply(lin, dirs_w, flat[pix].astype(np.float64), p_w_c, level, irradiance)
                out = out.copy()
                out.reshape(-1, 3)[pix] = np.rint(np.clip(lin, 0, 1) ** np.float32(1.0 / L.gamma) * 255.0)
        if len(self.particles):
            out = self._draw_particles(out, range_m, renderer, R_w_c, p_w_c, t_s, s_capsule_m, irradiance)
        return out

    def _draw_particles(self, rgb, range_m, renderer, R_w_c, p_w_c, t_s, s_capsule_m, irradiance) -> np.ndarray:
        """Each visible particle as an irregular blob (a random 9-gon, soft edge, lighter core), lit by the
        capsule's light at its distance; far ones first, so near ones cover them."""
        cam, L = renderer.camera, renderer.lighting
        pts_w, rows = self.particle_points_w(renderer.tube, t_s, s_capsule_m)
        if len(rows) == 0:
            return rgb
        pc = (pts_w - p_w_c) @ R_w_c  # camera frame
        dist = np.linalg.norm(pc, axis=1)
        uv, ok = cam.project(pc)
        h, w = range_m.shape
        out = rgb.astype(np.float32)
        for i in np.argsort(-dist):
            if not ok[i] or dist[i] < 0.004 or pc[i, 2] <= 0:
                continue
            u, v = uv[i]
            iu, iv = int(round(u)), int(round(v))
            if not (0 <= iu < w and 0 <= iv < h) or not np.isfinite(range_m[iv, iu]) or range_m[iv, iu] < dist[i]:
                continue  # outside the picture, or behind the wall
            # the lens's local scale: pixels per radian, from a point 1 mrad off the particle's ray
            d1 = pc[i] / dist[i]
            side = np.cross(d1, [0.0, 0.0, 1.0] if abs(d1[2]) < 0.9 else [1.0, 0.0, 0.0])
            uv2, ok2 = cam.project((pc[i] + side / np.linalg.norm(side) * dist[i] * 1e-3)[None])
            if not ok2[0]:
                continue
            radius_px = 0.5 * self.particles[rows[i], 3] / dist[i] * float(np.linalg.norm(uv2[0] - uv[i]) / 1e-3)
            if radius_px < 0.7:
                continue
            rs = np.random.default_rng(int(self.particles[rows[i], 7]))  # the particle's own shape and colour
            ang = np.sort(rs.uniform(0, 2 * math.pi, 9))
            rad = radius_px * rs.uniform(0.6, 1.15, 9)
            stretch, turn = rs.uniform(0.5, 1.0), rs.uniform(0, math.pi)
            x, y = rad * np.cos(ang), rad * stretch * np.sin(ang)
            poly = np.c_[u + x * math.cos(turn) - y * math.sin(turn), v + x * math.sin(turn) + y * math.cos(turn)]
            pad = int(math.ceil(1.3 * radius_px)) + 3
            x0, y0 = max(iu - pad, 0), max(iv - pad, 0)
            x1, y1 = min(iu + pad + 1, w), min(iv + pad + 1, h)
            layer = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.fillPoly(layer, [np.rint((poly - [x0, y0]) * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
            core = np.zeros_like(layer)
            cv2.fillPoly(core, [np.rint((0.55 * (poly - [u, v]) + [u - x0, v - y0]) * 16).astype(np.int32)], 255,
                         cv2.LINE_AA, shift=4)
            if radius_px > 2:
                layer = cv2.GaussianBlur(layer, (0, 0), 0.6)
                core = cv2.GaussianBlur(core, (0, 0), 0.3 * radius_px)
            hue = rs.uniform()  # brown (food residue) to green-yellow (bile-stained mucus)
            albedo = float(self.particles[rows[i], 6]) * ((1 - hue) * np.array([0.50, 0.33, 0.16])
                                                          + hue * np.array([0.42, 0.42, 0.12]))
            lum = albedo * float(irradiance(np.array([dist[i]]))[0])
            shade = lum[None, None, :] * (0.7 + 0.5 * core[..., None].astype(np.float32) / 255.0)
            colour = np.clip(shade, 0, 1) ** (1.0 / L.gamma) * 255.0
            a = layer[..., None].astype(np.float32) / 255.0 * 0.95
            roi = out[y0:y1, x0:x1]
            out[y0:y1, x0:x1] = roi * (1 - a) + colour * a
        return np.rint(out).astype(np.uint8)

"""Exact-geometry checks of the renderer: what a pixel shows is where the camera model says it is."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.camera import FisheyeCamera
from testbed.centerline import Centerline
from testbed.render import RENDER_BACKENDS, Lighting, RaycastRenderer, decode_range, encode_range, make_renderer
from testbed.texture import Texture
from testbed.tube import Tube

pytestmark = pytest.mark.render
R_TUBE = 0.015


@pytest.fixture(scope="module")
def straight_tube():
    z = np.linspace(0.0, 0.4, 50)
    cl = Centerline.from_points(np.c_[0 * z, 0 * z, z], R_TUBE, ds_m=5e-4)
    return Tube(cl, sections=96, ring_spacing_m=0.002)


def uniform_texture(spots=()):
    """Albedo 0.6 everywhere, with dark Gaussian spots at (s_m, phi_rad) (sigma 0.35 mm on the wall)."""
    n_around, n_along, length = 512, 1024, 0.2
    a = np.full((n_around, n_along, 3), 0.6, np.float32)
    j, i = np.meshgrid(np.arange(n_along), np.arange(n_around))
    for s0, phi0 in spots:
        x0 = s0 / length * n_along - 0.5  # texel-index coordinates, as Texture.sample maps them
        y0 = phi0 / (2 * math.pi) * n_around - 0.5
        dx = (j - x0) * (length / n_along)
        dy = (i - y0) * (2 * math.pi * R_TUBE / n_around)
        a *= (1.0 - 0.8 * np.exp(-0.5 * (dx**2 + dy**2) / 0.00035**2))[..., None]
    return Texture(a, length)


def pose(rotvec, pos):
    R = Rotation.from_rotvec(rotvec)  # camera looking down +z (the tube axis), tilted by rotvec
    return R, np.asarray(pos, float)


POSES = [
    pose([0.0, 0.0, 0.3], [0.0, 0.0, 0.10]),
    pose([0.25, -0.15, 1.0], [0.004, -0.003, 0.12]),
    pose([-0.4, 0.3, -2.0], [-0.006, 0.002, 0.08]),
]


@pytest.mark.parametrize("backend", RENDER_BACKENDS)
@pytest.mark.parametrize("R, p", POSES)
def test_range_equals_ray_cylinder_intersection(straight_tube, R, p, backend):
    cam = FisheyeCamera.equidistant(160, 160, 156.0)
    r = make_renderer(backend, straight_tube, uniform_texture(), cam)
    res = r.render(R, p)
    rays_c, valid = cam.pixel_rays()
    d = R.apply(rays_c.reshape(-1, 3))
    # analytic: |p_xy + t d_xy| = R_TUBE, positive root
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (p[0] * d[:, 0] + p[1] * d[:, 1])
    c = p[0] ** 2 + p[1] ** 2 - R_TUBE**2
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    z_hit = p[2] + t * d[:, 2]
    inside = valid.ravel() & np.isfinite(t) & (z_hit > 0.01) & (z_hit < 0.39)
    if backend == "pyrender":
        # Rasterised visibility is decided at cube-face pixel centres, not on the exact ray: at the silhouette
        # of the far tube end (>15 cm, where a pixel spans ~3 mm of wall seen edge-on and the image is black)
        # it may pick a triangle the exact ray misses. Nearer, it is as exact as ray casting.
        inside &= t < 0.15
    got = res.range_m.ravel()[inside]
    assert np.isfinite(got).all()
    err = np.abs(got - t[inside])
    # Required: <= 1 mm. The mesh is a 96-gon (sagitta 0.008 mm at r = 15 mm); a ray meeting the wall at grazing
    # angle a turns that into 0.008 mm / sin(a), so far down the tube the error grows to ~0.2 mm, while most
    # pixels see the wall steeply and are within a few micrometres.
    assert err.max() <= 1e-3, err.max()
    assert np.percentile(err, 90) < 2e-5
    # the 16-bit file format keeps it within its 0.05 mm quantisation
    back = decode_range(encode_range(res.range_m)).ravel()[inside]
    assert np.abs(back - t[inside]).max() <= 1e-3


@pytest.mark.parametrize("backend", RENDER_BACKENDS)
@pytest.mark.parametrize("R, p", POSES)
def test_wall_point_renders_at_the_projected_pixel(straight_tube, R, p, backend):
    cam = FisheyeCamera.equidistant(320, 320, 156.0)
    rng = np.random.default_rng(0)
    # spots on the wall 1.5-4 cm ahead of the camera, at random angles, inside the field of view
    spots = []
    while len(spots) < 4:
        s0 = p[2] + rng.uniform(0.015, 0.04)
        phi0 = rng.uniform(0, 2 * math.pi)
        P = straight_tube.surface_point(s0, phi0)[0]
        uv, ok = cam.project(R.inv().apply(P - p)[None])
        if ok[0] and np.hypot(*(uv[0] - [cam.cx, cam.cy])) < 140:
            spots.append((s0, phi0, uv[0]))
    light = Lighting(specular=0.0)
    plain = make_renderer(backend, straight_tube, uniform_texture(), cam, light).render(R, p).rgb.astype(float)
    dotted = make_renderer(backend, straight_tube, uniform_texture([(s, f) for s, f, _ in spots]), cam, light)
    img = dotted.render(R, p).rgb.astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = np.nan_to_num(1.0 - img[..., 1] / plain[..., 1]).clip(0, 1)  # shading cancels in the ratio
    for _, _, uv in spots:
        u0, v0 = np.round(uv).astype(int)
        win = weight[v0 - 12 : v0 + 13, u0 - 12 : u0 + 13]
        vv, uu = np.mgrid[v0 - 12 : v0 + 13, u0 - 12 : u0 + 13]
        cu, cv = (win * uu).sum() / win.sum(), (win * vv).sum() / win.sum()
        # the spot's image centroid is at the camera model's projection of its centre (goal 0.5 px)
        assert math.hypot(cu - uv[0], cv - uv[1]) <= 0.5, (cu, cv, uv)


def test_outside_the_field_of_view_is_black(straight_tube):
    cam = FisheyeCamera.equidistant(64, 64, 156.0)
    res = RaycastRenderer(straight_tube, uniform_texture(), cam).render(*POSES[0])
    assert res.rgb[~cam.fov_mask()].max() == 0
    assert np.isnan(res.range_m[~cam.fov_mask()]).all()
    assert res.rgb[cam.fov_mask()].max() > 50  # and the wall inside is lit


def test_pyrender_backend_matches_the_ray_caster(straight_tube):
    """Both backends shade the same exact rays; they may differ only where rasterised visibility picks the
    neighbouring triangle (occlusion edges far down the tube)."""
    cam = FisheyeCamera.equidistant(160, 160, 156.0)
    a = RaycastRenderer(straight_tube, uniform_texture(), cam).render(*POSES[1])
    b = make_renderer("pyrender", straight_tube, uniform_texture(), cam).render(*POSES[1])
    near = a.range_m < 0.15  # see test_range_equals_ray_cylinder_intersection for the far silhouette
    assert np.isfinite(b.range_m[near]).all()
    diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int))
    assert (diff.max(axis=-1) > 2).mean() < 0.01
    assert np.abs(a.range_m - b.range_m)[near].max() < 1e-3

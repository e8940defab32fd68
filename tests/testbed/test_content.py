"""Lumen content (testbed.content): Beer-Lambert fluid below a level surface, and debris particles that sit in
3-D -- drawn where they are in front of the wall, hidden where the wall is nearer, drifting between frames."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.camera import FisheyeCamera
from bodyslam.errors import ConfigError
from testbed.centerline import Centerline
from testbed.content import Debris, Fluid, LumenContent
from testbed.render import RaycastRenderer
from testbed.scenario import build_world, load_scenario
from testbed.texture import Texture
from testbed.tube import Tube

KAPPA = 40.0
DIRS = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # down, up, level


def _through_fluid(p_y: float) -> np.ndarray:
    f = Fluid(wet_frac=1.0, kappa_per_m=KAPPA, colour=(0.0, 0.0, 0.0))  # no scattering: attenuation only
    lin = np.ones((3, 3), np.float32)
    f.apply(lin, DIRS, np.full(3, 0.015), np.array([0.0, p_y, 0.0]), 0.0, lambda d: np.ones_like(d, np.float32))
    return lin[:, 0]


def test_fluid_attenuates_by_the_path_below_its_surface():
    # camera 10 mm above the surface (y = 0), rays 15 mm long: down crosses 5 mm of fluid, the others none;
    # light crosses it twice (LEDs to wall and back)
    assert _through_fluid(0.01) == pytest.approx([np.exp(-2 * KAPPA * 0.005), 1.0, 1.0], rel=1e-5)
    # camera 10 mm below: the level ray is in fluid all the way, the upward one for its first 10 mm
    assert _through_fluid(-0.01) == pytest.approx([np.exp(-2 * KAPPA * 0.015), np.exp(-2 * KAPPA * 0.010),
                                                   np.exp(-2 * KAPPA * 0.015)], rel=1e-5)


def test_fluid_scatters_its_colour_where_it_hides_the_wall():
    f = Fluid(wet_frac=1.0, kappa_per_m=KAPPA, colour=(0.6, 0.6, 0.2))
    lin = np.zeros((1, 3), np.float32)  # a black wall: what is left is the fluid's own light
    f.apply(lin, DIRS[2:], np.array([0.02]), np.array([0.0, -0.01, 0.0]), 0.0,
            lambda d: np.full_like(d, 0.5, dtype=np.float32))
    # single scattering at constant irradiance: albedo kappa colour E int_0^L exp(-2 kappa d) dd, exactly
    # 0.5 kappa colour 0.5 (1 - exp(-2 kappa L)) / (2 kappa); the 8-point midpoint rule is within 0.2% of it
    want = 0.5 * np.array([0.6, 0.6, 0.2]) * 0.5 * (1 - np.exp(-2 * KAPPA * 0.02)) / 2
    assert lin[0] == pytest.approx(want, rel=3e-3)


def test_content_is_off_in_thesis_and_on_in_realistic():
    assert build_world(load_scenario("thesis"), 2, 5).content is None
    c = build_world(load_scenario("realistic"), 2, 5).content
    assert c.fluid.active and c.fluid.stretches and len(c.particles) > 100
    with pytest.raises(ConfigError, match="fluid"):
        Fluid(wet_frac=1.5)
    with pytest.raises(ConfigError, match="unknown key"):
        build_world(load_scenario("realistic", ["debris.colour=1"]), 2, 5)


@pytest.fixture(scope="module")
def straight():
    z = np.linspace(0.0, 0.4, 50)
    tube = Tube(Centerline.from_points(np.c_[0 * z, 0 * z, z], 0.012, ds_m=5e-4), sections=96, ring_spacing_m=0.002)
    cam = FisheyeCamera.equidistant(120, 120, 156.0)
    return tube, RaycastRenderer(tube, Texture(np.full((64, 64, 3), 0.6, np.float32), 0.1), cam)


def _one_particle(s0, rho_frac, size_m=0.002, drift=0.0):
    # columns: s0, radial fraction, phi, size, drift speed, wander phase, albedo, shape seed
    return LumenContent(Fluid(), Debris(per_m=1.0, wander_m=0.0),
                        np.array([[s0, rho_frac, 0.0, size_m, drift, 0.0, 0.3, 7.0]]))


@pytest.mark.render
def test_a_particle_in_front_of_the_wall_is_drawn_and_one_behind_it_is_not(straight):
    tube, r = straight
    p = np.array([0.0, 0.0, 0.10])
    res = r.render(Rotation.identity(), p)
    c = _one_particle(0.115, 0.3)  # 15 mm ahead, 3.6 mm off the axis: in the open lumen
    out = c.apply(res.rgb, res.range_m, r, np.eye(3), p, 0.0, 0.10)
    changed = np.any(out != res.rgb, axis=2)
    uv, _ = r.camera.project((c.particle_points_w(tube, 0.0, 0.10)[0] - p))
    assert changed.sum() > 10 and changed[int(round(uv[0, 1])), int(round(uv[0, 0]))]
    # the same particle seen through a wall that is nearer along its ray: hidden
    near = np.minimum(res.range_m, 0.005)
    assert np.array_equal(c.apply(res.rgb, near, r, np.eye(3), p, 0.0, 0.10), res.rgb)


def test_particles_persist_and_drift_between_frames(straight):
    tube, _ = straight
    c = _one_particle(0.12, 0.5, drift=0.0005)
    p0, _ = c.particle_points_w(tube, 0.0, 0.12)
    p1, _ = c.particle_points_w(tube, 4.0, 0.12)
    assert p1[0, 2] - p0[0, 2] == pytest.approx(0.002, abs=1e-9)  # 0.5 mm/s along the gut (wander off)
    assert np.hypot(*p0[0, :2]) == pytest.approx(0.006, abs=1e-6)  # half the 12 mm radius from the axis


@pytest.mark.render
def test_the_rear_camera_sees_the_same_content(tmp_path):
    from bodyslam.io import read_image
    from testbed.simulate import simulate

    base = ["rear_camera.enabled=true", "fluid.wet_frac=1.0", "fluid.fill_max=1.0", "debris.per_m=2000"]
    simulate(load_scenario("realistic", base), 9, tmp_path / "on", n_frames=2, jobs=1)
    simulate(load_scenario("realistic", base + ["fluid.wet_frac=0", "debris.per_m=0"]), 9, tmp_path / "off",
             n_frames=2, jobs=1)
    for cam in ("frames", "frames_rear"):
        on = read_image(tmp_path / "on" / cam / "000001.png").astype(int)
        off = read_image(tmp_path / "off" / cam / "000001.png").astype(int)
        assert np.mean(np.abs(on - off) > 10) > 0.01  # fluid and particles change >1% of either camera's pixels

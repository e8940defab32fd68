"""Peristalsis (testbed.motility): waves that travel, a capsule that holds the lumen open, and frames rendered
from the moved wall."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.camera import FisheyeCamera
from bodyslam.errors import ConfigError
from testbed.centerline import Centerline
from testbed.motility import Peristalsis, draw_stretches
from testbed.render import RaycastRenderer
from testbed.scenario import build_world, load_scenario
from testbed.texture import Texture
from testbed.tube import Tube

R_TUBE = 0.012
WAVES = Peristalsis(amplitude_frac=0.5, active_frac=1.0)  # waves everywhere (no stretches drawn: envelope 1)


def test_off_by_default_and_in_thesis():
    s = np.linspace(0, 1, 50)
    assert np.array_equal(Peristalsis().radius_factor(s, 3.0, 0.5), np.ones(50))
    assert not build_world(load_scenario("thesis"), 1, 5).motility.active
    assert build_world(load_scenario("realistic"), 1, 5).motility.active


def test_crests_travel_aborally_at_the_wave_speed():
    s = np.linspace(0.0, 0.3, 30001)  # 10 um grid
    far = 1.0  # capsule far away: no hold
    f0 = WAVES.radius_factor(s, 0.0, far)
    f1 = WAVES.radius_factor(s, 2.0, far)
    assert f0.min() == pytest.approx(0.5, abs=1e-6)  # a crest halves the radius
    crests0 = s[np.r_[False, (f0[1:-1] < f0[:-2]) & (f0[1:-1] <= f0[2:]), False]]
    crests1 = s[np.r_[False, (f1[1:-1] < f1[:-2]) & (f1[1:-1] <= f1[2:]), False]]
    assert np.diff(crests0) == pytest.approx(np.full(len(crests0) - 1, WAVES.spacing_m), abs=2e-5)
    # two seconds later every crest is 2 cm further along (toward larger s)
    shift = (crests1[0] - crests0[0]) % WAVES.spacing_m
    assert shift == pytest.approx(2.0 * WAVES.speed_m_s, abs=2e-5)


def test_the_capsule_holds_the_lumen_open_over_its_length():
    s = np.linspace(0.0, 0.3, 3001)
    s_cap = 0.15
    for t in np.linspace(0.0, 6.0, 13):  # whatever the wave's phase
        f = WAVES.radius_factor(s, t, s_cap)
        held = (s >= s_cap - WAVES.hold_back_m) & (s <= s_cap + WAVES.hold_ahead_m)
        assert np.all(f[held] == 1.0)
    assert WAVES.radius_factor(s, 0.0, s_cap).min() < 0.6  # elsewhere the waves do close the lumen


def test_active_stretches_cover_the_stated_fraction():
    rng = np.random.default_rng(0)
    spans = draw_stretches(100.0, 0.04, 0.5, rng)
    lengths = np.array([b - a for a, b in spans])
    # ~1250 stretches of mean 4 cm: their mean and the covered fraction within a few standard errors
    assert lengths.mean() == pytest.approx(0.04, rel=0.1)
    assert lengths.sum() / 100.0 == pytest.approx(0.5, abs=0.05)
    p = Peristalsis(amplitude_frac=0.5).drawn(100.0, np.random.default_rng(1))
    env = p.envelope(np.linspace(0.0, 100.0, 200001))
    assert env.mean() == pytest.approx(0.5, abs=0.05) and env.min() == 0.0 and env.max() == 1.0


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="amplitude_frac"):
        Peristalsis(amplitude_frac=0.95)
    with pytest.raises(ConfigError, match="drawn per seed"):
        build_world(load_scenario("realistic", ["motility.stretches=[[0.1, 0.2]]"]), 1, 5)
    with pytest.raises(ConfigError, match="raycast"):
        build_world(load_scenario("realistic", ["render.backend=pyrender"]), 1, 5)


@pytest.mark.render
def test_frames_show_the_moved_wall_exactly():
    """On a straight tube, each pixel's range lands on the wall at the radius the wave gives there (R f(s)),
    not at the resting radius."""
    z = np.linspace(0.0, 0.4, 50)
    tube = Tube(Centerline.from_points(np.c_[0 * z, 0 * z, z], R_TUBE, ds_m=5e-4), sections=96,
                ring_spacing_m=0.001)
    cam = FisheyeCamera.equidistant(120, 120, 156.0)
    r = RaycastRenderer(tube, Texture(np.full((64, 64, 3), 0.6, np.float32), 0.1), cam)
    s_cap, t = 0.10, 1.3
    r.set_mesh(tube.mesh_window(s_cap - 0.09, s_cap + 0.09, lambda s: WAVES.radius_factor(s, t, s_cap)))
    p = np.array([0.002, -0.001, s_cap])
    res = r.render(Rotation.identity(), p)
    rays_c, valid = cam.pixel_rays()
    hit = np.isfinite(res.range_m) & valid
    q = p + rays_c[hit] * res.range_m[hit][:, None]  # camera axes = world axes here
    rho = np.hypot(q[:, 0], q[:, 1])
    want = R_TUBE * WAVES.radius_factor(q[:, 2], t, s_cap)
    # the mesh is a ring every 1 mm, flat between its 96 corners: the polygon sits inside the circle by at most
    # R (1 - cos(pi / 96)) = 6.4 um, and linear interpolation between rings of the smooth wave adds < 5 um
    assert np.abs(rho - want).max() < 2e-5
    moved = np.abs(want - R_TUBE) > 1e-3
    assert moved.sum() > 100  # the check covers pixels where the wall moved by more than 1 mm
    assert math.isclose(res.exposure, 1.0)


def test_a_window_of_the_resting_mesh_is_the_mesh_itself():
    w = build_world(load_scenario("realistic"), 1, 5)
    full = w.tube.mesh()
    s = w.tube.ring_s()
    win = w.tube.mesh_window(s[100] - 1e-9, s[160] + 1e-9)
    n = w.tube.sections + 1
    assert np.array_equal(win.vertices_w, full.vertices_w[100 * n:161 * n])
    assert len(win.faces) == 60 * 2 * w.tube.sections
    # normals agree inside (np.gradient is one-sided at a window's first and last ring)
    assert np.allclose(win.normals_w[n:-n], full.normals_w[101 * n:160 * n], atol=1e-12)


@pytest.mark.render
def test_the_truths_occlusion_test_sees_the_moved_wall():
    """FT/FL truth casts a ray per frame toward the centre line ahead (testbed.motion.label_frames). Rings only
    close the lumen, so against the moved wall no such ray gets further than against the resting one, and where a
    ring stands in the way it stops short."""
    from testbed.motion import generate_motion
    from testbed.simulate import moving_wall_cast

    w = build_world(load_scenario("realistic", ["motility.amplitude_frac=0.8", "motility.active_frac=1.0"]), 5, 40)
    traj = generate_motion(w.tube, w.n_frames, w.motion, w.rngs["motion"])
    cl = w.tube.centerline
    ahead, _, _ = cl.frame_at(np.clip(traj.s_m + 0.03, 0.0, cl.length_m))  # 3 cm down the lumen
    u = ahead - traj.positions_w_m
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = RaycastRenderer(w.tube, w.texture, w.camera, w.lighting)
    rest = np.nan_to_num(r.cast(traj.positions_w_m, u)[0], nan=1.0)
    calls = []  # the progress it reports: one call per frame, the last one the whole
    moved = np.nan_to_num(moving_wall_cast(w, traj, r, lambda done, total: calls.append((done, total)))(
        traj.positions_w_m, u)[0], nan=1.0)
    assert calls == [(k + 1, w.n_frames) for k in range(w.n_frames)]
    assert np.all(moved <= rest + 1e-6)
    assert np.sum(moved < rest - 0.002) >= 3  # rings stop some rays at least 2 mm short
    # several rays per frame, frame after frame (the "view" label rule's bundle): each frame's meet its own wall
    two = moving_wall_cast(w, traj, r)(np.repeat(traj.positions_w_m, 2, axis=0), np.repeat(u, 2, axis=0))[0]
    assert np.array_equal(np.nan_to_num(two, nan=1.0), np.repeat(moved, 2))
    with pytest.raises(ValueError, match="same number of rays for each"):
        moving_wall_cast(w, traj, r)(traj.positions_w_m[:3], u[:3])

import numpy as np
import pytest

from bodyslam.geometry import relative_motion
from testbed.motion import FT, FL, generate_motion, label_frames
from testbed.render import RaycastRenderer
from testbed.scenario import build_world, load_scenario


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_thesis_motion_statistics(seed):
    world = build_world(load_scenario("thesis"), seed)
    traj = generate_motion(world.tube, 200, world.motion, world.rngs["motion"])
    m = relative_motion(traj.rotations_w_c, traj.positions_w_m)
    # issue 2's bars: mean step within 10% of 0.41 cm, roll within 20% of 7.8 deg, tilt within 20% of 4.3 deg
    assert abs(np.mean(np.abs(m["distance_m"])) - 0.0041) <= 0.1 * 0.0041
    assert abs(np.degrees(np.mean(np.abs(m["roll_rad"]))) - 7.8) <= 0.2 * 7.8
    assert abs(np.degrees(np.mean(m["tilt_rad"])) - 4.3) <= 0.2 * 4.3
    # it stops, and sometimes goes backward (Sec. 4.1: speed varies, the capsule often stops)
    assert np.sum(np.abs(m["distance_m"]) < 1e-9) >= 1
    assert np.sum(m["distance_m"] < -1e-4) >= 1
    # the camera stays inside the lumen, at least the wall margin away from the wall
    s, rho, _ = world.tube.locate(traj.positions_w_m, s_hint_m=traj.s_m)
    _, _, r = world.tube.centerline.frame_at(s)
    assert np.all(rho <= r - world.motion.wall_margin_m + 1e-6)


def test_labels_follow_the_geometric_rule():
    world = build_world(load_scenario("thesis", ["motion.fl_rate_per_frame=0.05"]), 3)
    traj = generate_motion(world.tube, 200, world.motion, world.rngs["motion"])
    caster = RaycastRenderer(world.tube, world.texture, world.camera, world.lighting)
    labels = label_frames(world.tube, traj, world.camera.fov_deg, caster.cast)
    assert set(labels) <= {FT, FL}
    # tilted 80-105 deg toward the wall, the lumen is out of view: held episode frames are FL, except where the
    # lumen itself bends the way the capsule tilted (then the camera does look down the lumen)
    assert traj.fl_episode.sum() > 0
    assert np.mean(labels[traj.fl_episode] == FL) >= 0.5  # seed 3: 9 of 13 (4 frames at a bend turning their way)
    # frames looking straight down a gently bending lumen are FT
    z = traj.rotations_w_c.apply([0, 0, 1])
    _, F, _ = world.tube.centerline.frame_at(traj.s_m)
    kappa = world.tube.centerline.curvature_per_m()[world.tube.centerline.index_at(traj.s_m).astype(int)]
    straight = (np.sum(z * F[:, :, 2], axis=1) > np.cos(np.radians(10))) & (kappa < 5.0)
    assert straight.sum() > 10 and np.all(labels[straight] == FT)



def test_view_rule_sees_the_lumen_past_a_fold():
    """``ft_rule = "view"`` (the realistic testbed's): a fold across the one line of sight to the centre-line point 4
    radii ahead makes the one-line rule call every frame FL; the bundle still sees the lumen past it wherever the
    one-line rule sees it without the fold, and the lumen's direction still decides the facing-the-wall frames."""
    world = build_world(load_scenario("thesis", ["motion.fl_rate_per_frame=0.05"]), 3)
    traj = generate_motion(world.tube, 200, world.motion, world.rngs["motion"])
    caster = RaycastRenderer(world.tube, world.texture, world.camera, world.lighting)

    def fold(origins_w, dirs_w):  # the wall as it is, and a fold 1 mm in front of the line to the point 4 radii ahead
        free = caster.cast(origins_w, dirs_w)[0].copy()
        m = len(origins_w) // len(traj.s_m)
        free[(0 if m == 1 else 7)::m] = 0.001  # the bundle's 8th line is that point's (3, 4, 5 radii; 7 lines each)
        return (free,)

    fov = world.camera.fov_deg
    plain = label_frames(world.tube, traj, fov, caster.cast, "ray")
    assert np.all(label_frames(world.tube, traj, fov, fold, "ray") == FL)
    view_fold = label_frames(world.tube, traj, fov, fold, "view")
    assert np.sum(plain == FT) > 100 and np.all(view_fold[plain == FT] == FT)
    view = label_frames(world.tube, traj, fov, caster.cast, "view")
    assert np.all(view[plain == FT] == FT)
    # facing the wall stays FL as often as with one line (the same angle on the lumen's direction decides it)
    assert np.mean(view[traj.fl_episode] == FL) >= 0.5
    with pytest.raises(ValueError, match="rule must be one of"):
        label_frames(world.tube, traj, fov, caster.cast, "cone")

def test_a_start_moved_in_for_early_backward_motion_stays_on_the_path():
    # classifier_realistic seed 510 backs up early: the start is moved in to exactly 0.02 m from the path's start,
    # and lo - min + min rounded to just below it ("the capsule would leave the path", s from 0.020)
    w = build_world(load_scenario("classifier_realistic"), 510, None)
    traj = generate_motion(w.tube, w.n_frames, w.motion, w.rngs["motion"])
    assert traj.s_m.min() >= 0.02 and traj.s_m.max() <= w.tube.centerline.length_m - 0.02


def test_a_capsule_that_only_wobbles_is_warned_about(caplog):
    """The calibrated mean step counts the lateral wobble: a mean step below the wobble's own leaves the capsule
    jittering in place (session 21: 0.5 cm from its start after 12.8 m of steps). That is said, with the remedy;
    the shipped thesis motion (advancing ~0.8 of its steps) is not warned about."""
    import logging

    with caplog.at_level(logging.WARNING, logger="testbed.motion"):
        world = build_world(load_scenario("thesis"), 11)
        generate_motion(world.tube, 200, world.motion, world.rngs["motion"])
    assert not [r for r in caplog.records if "advances" in r.getMessage()]
    world = build_world(load_scenario("thesis", ["motion.mean_step_m=0.0002", "motion.offset_std_frac=0.2",
                                                 "motion.mean_tilt_deg=0"]), 11)
    with caplog.at_level(logging.WARNING, logger="testbed.motion"):
        traj = generate_motion(world.tube, 200, world.motion, world.rngs["motion"])
    said = [r.getMessage() for r in caplog.records if "advances" in r.getMessage()]
    assert abs(traj.s_m[-1] - traj.s_m[0]) < 0.1 * 199 * 0.0002  # the case the warning is for
    assert len(said) == 1 and "offset_std_frac" in said[0]

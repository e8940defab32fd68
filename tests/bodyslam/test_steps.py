"""The one step type and its statuses (bodyslam.steps)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.steps import MEASURED, StepMotion, StepStatus, motion_from_transform


def test_which_statuses_carry_an_estimate():
    """ok and wall are measured from the pair's own matches, bridged is a share of a gap: all three give the
    filters a pose; every other status carries NaN and none."""
    s = motion_from_transform(Rotation.from_rotvec([0.0, 0.05, 0.1]), [0.0, 0.001, 0.004], 40, 2e-4, 0.01)
    for status in StepStatus:
        t = s.with_status(status)
        assert t.has_estimate == (status in ("ok", "wall", "bridged")), status
        assert t.ok == (status in ("ok", "wall")), status
        assert t.has_rotation == (status in ("ok", "wall", "bridged", "rotation", "rotation_slow")), status
    f = StepMotion.failed("no_lumen", n_matches=7)
    assert not f.has_estimate and math.isnan(f.distance_m) and f.n_matches == 7
    assert f.sigma_t_m > 0 and f.sigma_r_rad > 0  # the defaults for a file that states none


def test_an_unknown_status_is_refused_and_text_compares_equal():
    with pytest.raises(ValueError):
        StepMotion(status="facing_wall")
    assert StepStatus.WALL == "wall" and "wall" in MEASURED


def test_a_transform_gives_the_dissertations_quantities():
    """Distance signed by the optical axis (a step backwards is negative), roll about it, tilt the swing."""
    s = motion_from_transform(Rotation.from_rotvec([0.0, 0.0, 0.2]), [0.0, 0.0, -0.003])
    assert s.distance_m == pytest.approx(-0.003) and s.roll_rad == pytest.approx(0.2) and s.tilt_rad < 1e-12
    s = motion_from_transform(Rotation.from_rotvec([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 0.002]))
    assert s.tilt_rad == pytest.approx(0.1) and abs(s.roll_rad) < 1e-12


@pytest.mark.parametrize("status, lost", [("rotation", True), ("rotation_slow", False)])
def test_a_rotation_step_carries_its_rotation_and_no_translation(tmp_path, status, lost):
    """A step whose rotation alone was measured (status rotation: a fast one, lost to motion; rotation_slow: its
    frames overlap as a slow step's do, not lost to motion): the filters get its rotation, not a pose; motion.csv
    keeps the rotation and NaN for the distance and translation, and reads back the same."""
    from bodyslam.io import motion_row, read_motion_steps, write_motion_csv
    from bodyslam.steps import lost_to_motion, rotation_step

    R = Rotation.from_rotvec([0.02, -0.01, 0.15])
    s = StepMotion(math.nan, 0.15, 0.02, -0.01, 0.022, 120, status, R.as_matrix(), None, math.nan, 0.07)
    assert lost_to_motion(s) == lost
    assert rotation_step(R, 120, 0.07, slow=not lost).status == status
    assert s.has_rotation and not s.has_estimate and not s.ok
    row = motion_row(3, 1.5, s)
    assert math.isnan(row[2]) and all(math.isnan(v) for v in row[9:12])  # distance, tx, ty, tz
    write_motion_csv(tmp_path / "m.csv", [3], [1.5], [s])
    (back,) = read_motion_steps(tmp_path / "m.csv", [3])
    assert back.status == status and back.has_rotation and back.t_c1_c2_m is None
    assert lost_to_motion(back) == lost
    assert np.allclose(back.R_c1_c2, R.as_matrix(), atol=1e-9) and back.sigma_rotation_rad == pytest.approx(0.07)
    assert math.isnan(back.distance_m)


def test_step_lengths_percentile_is_within_one_bin_of_numpy_and_counts_only_lengths():
    """The running histogram's percentile agrees with numpy's within one log bin (2.3%) on a spread of lengths,
    ignores what is not a positive length, and is 0 before any."""
    from bodyslam.steps import StepLengths

    h = StepLengths()
    assert h.percentile(90) == 0.0
    x = np.random.default_rng(3).lognormal(np.log(3e-3), 0.8, 5000)
    for v in x:
        h.add(float(v))
    for bad in (0.0, -1e-3, float("nan"), float("inf")):
        h.add(bad)
    assert h.n == 5000
    for q in (50, 90, 95):
        assert h.percentile(q) == pytest.approx(np.percentile(x, q), rel=0.025)

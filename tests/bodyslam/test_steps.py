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

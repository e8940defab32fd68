"""The lumen's shape (testbed.tube): a collapsed, folded cross-section and a radius that varies along the gut on
the realistic testbed, a rigid cylinder on the ideal one (its RF channel ideal too)."""

import numpy as np
import pytest

from testbed.scenario import build_world, load_scenario
from testbed.tube import Folds


def test_collapsed_lumen_is_star_shaped_and_contractions_narrow_it():
    f = Folds(lobes=4, lobe_depth_frac=0.25)
    phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    bulge = f.profile(np.zeros_like(phi), phi)
    assert bulge.max() == pytest.approx(0.25, abs=1e-3) and bulge.min() == pytest.approx(0.0, abs=1e-3)
    # four lobes: the bulge peaks four times around the circumference
    peaks = np.sum((bulge > np.roll(bulge, 1)) & (bulge >= np.roll(bulge, -1)))
    assert peaks == 4
    w = build_world(load_scenario("realistic"), seed=3, n_frames=10)
    r = w.tube.centerline.radius_m
    assert 0.006 < r.min() < 0.010 and 0.013 < r.max() < 0.0165  # 0.8-1.6 cm with contracted segments
    ideal = build_world(load_scenario("thesis"), seed=3, n_frames=10)
    assert np.ptp(ideal.tube.centerline.radius_m) < 1e-12 and not ideal.optics.active
    assert ideal.rf["channel"].ideal and not w.rf["channel"].ideal

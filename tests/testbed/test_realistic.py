"""The realistic testbed's departures from the ideal world in a rendered sequence: the radius hidden from the
pipeline, real optics in the frames (the optics and the lumen's shape alone: test_artifacts.py, test_tube.py)."""

from __future__ import annotations

import json

import pytest

from bodyslam.io import read_image
from testbed.scenario import build_world, load_scenario


@pytest.mark.render
def test_realistic_sequence_hides_the_radius_and_shows_real_optics(tmp_path):
    from testbed.simulate import simulate

    simulate(load_scenario("realistic"), 4, tmp_path, n_frames=3)
    meta = json.loads((tmp_path / "meta.json").read_text())
    truth_r = build_world(load_scenario("realistic"), 4, 3).tube.centerline.radius_m.mean()
    assert meta["tube_radius_m"] == 0.0125 and abs(truth_r - 0.0125) > 1e-4  # a prior, not this gut's radius
    assert "prior" in meta["tube_radius_source"]
    assert meta["tube_radius_sd_m"] == 0.0025  # and the prior's spread, which the pipeline carries
    assert meta["lumen_shape_sd_rel"] == 0.13  # and the lumen's departure from a cylinder (0 on `thesis`)
    img = read_image(tmp_path / "frames" / "000000.png")
    assert img[:8, :8].max() < 20  # octagon corner (JPEG ringing stays below 20)
    rf_lines = (tmp_path / "rf.csv").read_text().splitlines()[1:]
    assert len(rf_lines) < 3 * 32  # dropouts: fewer lines than frames x sensors (seed 4 loses some of its 96)

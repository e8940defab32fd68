"""The realistic testbed's departures from the ideal world: each one present at its configured size, each off in
the ideal scenarios."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bodyslam.io import read_image
from testbed.artifacts import CameraOptics
from testbed.scenario import build_world, load_scenario
from testbed.tube import Folds


def test_camera_optics_stop_overlay_cast_and_jpeg():
    img = np.full((200, 200, 3), 180, np.uint8)
    opt = CameraOptics(colour_gain=(1.0, 0.8, 0.6), vignetting=0.3, field_stop="octagon", stop_radius_frac=0.9,
                       overlay_text="LOGO", jpeg_quality=70)
    out = opt.apply(img)
    stop = opt.stop_mask(200, 200)
    assert out[0, 0].max() < 16 and out[100, 100, 0] > out[100, 100, 2]  # black corner (JPEG ringing < 16); cast
    # an octagon, not a circle: on the diagonal it stops at its corner radius, on the axes at the side's
    assert stop[100, 100 + 88] and not stop[100, 100 + 92]
    d = int(88 / np.cos(np.pi / 8) / np.sqrt(2))  # a corner lies at 22.5 deg, the diagonal between two corners
    assert stop[100 + d - 6, 100 + d - 6]
    assert out[100, 100].sum() > out[100, 178].sum()  # vignetting darkens toward the rim
    assert (out[5:20, 5:60] > 200).any()  # the burned-in text
    assert CameraOptics().apply(img) is img  # off by default: the ideal scenarios are untouched


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

"""Field-of-view masks of real capsule frames, and matching that stays inside them."""

import numpy as np
import pytest

from bodyslam.camera import FisheyeCamera
from bodyslam.errors import ConfigError
from bodyslam.vision.matching import Matcher, detect_fov_mask, field_of_view


def capsule_like_frames(n=12, size=200, seed=0):
    """Textured disc that changes frame to frame, black border, and constant burned-in 'text' inside the disc."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    disc = (xx - 99.5) ** 2 + (yy - 99.5) ** 2 <= 90**2
    frames = []
    for _ in range(n):
        f = np.zeros((size, size, 3), np.uint8)
        tex = rng.integers(60, 200, (size, size, 1)).astype(np.uint8)
        f[disc] = np.repeat(tex, 3, axis=2)[disc]
        f[150:162, 20:70] = 255  # a timestamp: bright and constant
        f[60, 60] = f[61, 61] = f[120, 80] = 128  # specks that happen not to change (saturated mucosa)
        frames.append(f)
    return frames, disc


def test_detected_mask_is_the_disc_without_the_burned_in_text():
    frames, disc = capsule_like_frames()
    m = detect_fov_mask(frames)
    text = np.zeros_like(disc)
    text[150:162, 20:70] = True
    assert not m[text].any()
    assert not m[~disc].any()
    assert m[disc & ~text].mean() > 0.97  # all but the one-pixel rim ring the detector drops on purpose
    assert m[60, 60] and m[61, 61] and m[120, 80]  # a speck is not an overlay: it stays in the field


def test_the_field_of_view_is_the_image_circle_unless_the_frames_show_a_stop_or_overlay():
    frames, disc = capsule_like_frames()
    m, how = field_of_view(frames, disc)
    assert m is not None and not m[150:162, 20:70].any() and "overlay" in how  # burned-in text: detected
    plain = [f.copy() for f in frames]
    for f in plain:
        f[150:162, 20:70] = f[100:112, 100:150]  # no text: the detection agrees with the circle (IoU >= 0.98)
    m, how = field_of_view(plain, disc)
    assert m is None and "agrees" in how
    octagon = disc.copy()
    yy, xx = np.mgrid[:200, :200]
    octagon &= (np.abs(xx - 99.5) + np.abs(yy - 99.5)) < 115  # corners cut off: a field stop
    stopped = [np.where(octagon[..., None], f, 0).astype(np.uint8) for f in plain]
    m, _ = field_of_view(stopped, disc)
    assert m is not None and not m[~octagon].any()
    m, how = field_of_view([np.zeros((200, 200, 3), np.uint8)] * 3, disc)  # nothing to see: the circle
    assert m is None and "no field of view" in how


def test_black_frames_give_a_clear_error():
    with pytest.raises(ConfigError, match="field of view"):
        detect_fov_mask([np.zeros((64, 64, 3), np.uint8)] * 5)


def test_features_avoid_a_given_mask():
    frames, disc = capsule_like_frames()
    cam = FisheyeCamera.equidistant(200, 200, 156.0)
    mask = disc.copy()
    mask[:, :100] = False  # only the right half is valid
    mt = Matcher(cam, "sift", mask=mask)
    pts, _ = mt.keypoints(mt.features(frames[0]))
    assert len(pts) > 20 and (pts[:, 0] >= 100 - 0.5).all()
    with pytest.raises(ConfigError, match="mask is"):
        Matcher(cam, "sift", mask=np.ones((10, 10), bool))

"""The capsule camera's imaging chain (testbed.artifacts): field stop, burned-in overlay, colour cast,
vignetting and JPEG, off in the ideal scenarios."""

import numpy as np

from testbed.artifacts import CameraOptics


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

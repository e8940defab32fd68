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


def test_fast_mode_tries_tracking_then_coarse_then_full_descriptors():
    from pathlib import Path

    from bodyslam.io import read_image
    from bodyslam.meta import read_meta
    from bodyslam.vision.matching import COARSE_SCALE, RESCUE_FEATURES

    demo = Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0"
    cam = read_meta(demo).camera_model()
    f1, f2 = (read_image(demo / "frames" / f"{k:06d}.png") for k in (3, 4))
    mt = Matcher(cam, "fast")
    mt.lk_min_matches = 0  # (thesis motion: tracking verifies few tracks on this pair) offer them anyway
    a, b = mt.features(f1), mt.features(f2)
    tries = list(mt.cascade(a, b))
    # with the rescue on, the 0.7-scale try is skipped: tracking, 0.5 scale, then the full frame (session 70)
    assert [m.method for m in tries] == ["lk", "descriptors", "descriptors"]
    assert a.kp is None and b.kp is None  # the 0.7-scale keypoints were never detected
    # the coarse try detects on the frame scaled by COARSE_SCALE (fewer keypoints), in full-frame pixels
    (pc, _), (pr, _) = a.kp_coarse, a.kp_full
    assert 20 < len(pc) < len(pr)
    assert pc.max() > COARSE_SCALE * cam.width  # not left in the small image's pixels
    ij = np.rint(pc).astype(int)
    assert (mt.mask[ij[:, 1], ij[:, 0]] > 0).all()
    # the rescue: SIFT on the full frame, up to sift mode's keypoint budget (more than the 0.7-scale try keeps)
    assert mt.max_features < len(pr) <= RESCUE_FEATURES and tries[2].n_candidates > tries[1].n_candidates
    assert len(tries[1]) < 20 <= len(tries[2])  # a thesis-motion pair the coarse try fails on
    # without the rescue the cascade ends at the 0.7 scale instead: fewer keypoints than the full frame's
    nr = Matcher(cam, "fast", rescue=False)
    nr.lk_min_matches = 0
    c0, d0 = nr.features(f1), nr.features(f2)
    tries_nr = list(nr.cascade(c0, d0))
    assert [m.method for m in tries_nr] == ["lk", "descriptors", "descriptors"]
    (pf, _) = c0.kp
    assert len(pc) < len(pf) <= nr.max_features < len(pr) and c0.kp_full is None
    assert len(tries_nr[1]) < 20 <= len(tries_nr[2])  # 0.7 verifies enough where 0.5 does not
    # with the rescue, the 0.7 try is the last resort, after the cascade (session 72): the same matches as without
    last = mt.last_resort(a, b)
    assert last is not None and len(a.kp[0]) == len(pf) and len(last) == len(tries_nr[2])
    assert nr.last_resort(c0, d0) is None  # its cascade ends with that try already
    # tracking that verifies too few is not offered; a cascade stopped early detects nothing it did not need
    mt.lk_min_matches = len(tries[0]) + 1
    c, d = mt.features(f1), mt.features(f2)
    first = next(mt.cascade(c, d))
    assert first.method == "descriptors" and c.kp_coarse is not None and c.kp is None and c.kp_full is None
    sift = Matcher(cam, "sift")
    assert len(list(sift.cascade(sift.features(f1), sift.features(f2)))) == 1
    assert sift.last_resort(sift.features(f1), sift.features(f2)) is None
    with pytest.raises(ConfigError, match="coarse"):
        sift.keypoints(sift.features(f1), "coarse")
    with pytest.raises(ConfigError, match="level"):
        mt.keypoints(c, "huge")


def test_brightness_percentiles_from_the_histogram_are_numpys():
    # the normalisation's 1st / 99th percentiles come from a masked histogram; they must be np.percentile's numbers
    # exactly (the 8-bit lookup table truncates: a last-digit difference could change a pixel)
    from bodyslam.vision.matching import _masked_percentiles_u8

    rng = np.random.default_rng(1)
    for trial in range(400):
        h, w = rng.integers(1, 40, 2)
        g = (rng.integers(0, 256, (h, w)) if trial % 2 else rng.normal(120, 25, (h, w)).clip(0, 255)).astype(np.uint8)
        m = (rng.random((h, w)) < rng.random()).astype(np.uint8) * 255
        want = [float(x) for x in np.percentile(g[m > 0], (1, 99))] if (m > 0).any() else None
        assert _masked_percentiles_u8(g, m, (1.0, 99.0)) == want


def _sift_descriptors(seed=0, size=160):
    """Real SIFT descriptors (integer-valued floats, as OpenCV rounds them) of a random smoothed texture."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (size, size)).astype(np.uint8), (0, 0), 1.5)
    _, d = cv2.SIFT_create(contrastThreshold=0.01).detectAndCompute(img, None)
    return d


def test_knn_l2_is_opencvs_brute_force_matcher_exactly():
    import cv2

    from bodyslam.vision import matching

    d1, d2 = _sift_descriptors(0), _sift_descriptors(1)
    assert len(d1) > 100 and len(d2) > 100 and np.array_equal(d1, np.rint(d1))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=4)
    ref_idx = np.array([[m.trainIdx for m in ms] for ms in knn])
    ref_dist = np.array([[m.distance for m in ms] for ms in knn])
    idx, dist = matching.knn_l2(d1, d2, 4)
    assert np.array_equal(idx, ref_idx)  # the same neighbours in the same order (exact integer distances)
    assert np.array_equal(dist, ref_dist)
    small = matching.KNN_BLOCK_ROWS
    try:  # blocks of rows give the same answer as one block
        matching.KNN_BLOCK_ROWS = 7
        idx7, dist7 = matching.knn_l2(d1, d2, 4)
    finally:
        matching.KNN_BLOCK_ROWS = small
    assert np.array_equal(idx7, idx) and np.array_equal(dist7, dist)


def test_knn_l2_breaks_ties_to_the_lower_index_and_pads_short_sets():
    from bodyslam.vision.matching import knn_l2

    d2 = np.array([[3.0, 0], [1.0, 0], [1.0, 0], [0.0, 5]], np.float32)  # rows 1 and 2 tie for every query
    idx, dist = knn_l2(np.array([[0.0, 0], [2.0, 0]], np.float32), d2, 3)
    assert idx.tolist() == [[1, 2, 0], [0, 1, 2]]  # the second query is 1 from rows 0, 1 and 2
    assert np.allclose(dist, [[1, 1, 3], [1, 1, 1]])
    idx, dist = knn_l2(np.zeros((2, 2), np.float32), d2[:2], 4)  # fewer rows than k: -1 / inf
    assert (idx[:, 2:] == -1).all() and np.isinf(dist[:, 2:]).all() and (idx[:, :2] >= 0).all()
    idx, dist = knn_l2(np.zeros((0, 2), np.float32), d2, 4)
    assert idx.shape == (0, 4)


def test_flann_neighbours_come_out_as_the_matchers_lists():
    """The FLANN branch (asift, fast mode's rescue) turns OpenCV's lists of matches into arrays in flat passes: the
    same arrays as element by element, with -1 / inf where a list is short."""
    import cv2

    d1, d2 = _sift_descriptors(2), _sift_descriptors(3)
    m = Matcher(FisheyeCamera.equidistant(160, 160, 156.0), mode="asift")
    idx, dist = m._knn(d1, d2, 4, flann=True)
    cv2.setRNGSeed(0x5EED)
    knn = m._flann_matcher.knnMatch(d1, d2, k=4)
    for i, ms in enumerate(knn):
        assert idx[i, :len(ms)].tolist() == [x.trainIdx for x in ms]
        assert dist[i, :len(ms)].tolist() == [x.distance for x in ms]
        assert (idx[i, len(ms):] == -1).all() and np.isinf(dist[i, len(ms):]).all()
    assert idx.shape == (len(d1), 4)


def test_keypoint_positions_with_and_without_opencvs_convert(monkeypatch):
    import cv2

    from bodyslam.vision import matching

    kp = [cv2.KeyPoint(1.25, 2.5, 3.0), cv2.KeyPoint(40.75, 7.0, 2.0)]
    fast = matching._keypoint_xy(kp)
    monkeypatch.delattr(cv2.KeyPoint, "convert")  # a build without the static method: the list pass
    slow = matching._keypoint_xy(kp)
    assert fast.dtype == slow.dtype == np.float32 and np.array_equal(fast, slow)
    assert fast.tolist() == [[1.25, 2.5], [40.75, 7.0]] and matching._keypoint_xy([]).shape == (0, 2)


def _lit_pair(size=240, shift=(10.0, 6.0), seed=8, led=1.5, texture=0.1, noise=2.0):
    """Two frames of a faint wall texture (10% contrast) moved by ``shift`` px, under a capsule's light: four LED
    lobes and a fall-off toward the rim that stay where they are in the image while the wall moves (the realistic
    testbed's frames look so: docs/RESULTS.md, session 51). ``led=0``: an even light."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = sum(cv2.GaussianBlur(rng.normal(0.0, 1.0, (size + 40, size + 40)).astype(np.float32), (0, 0), s) * w
              for s, w in ((1.2, 1.0), (3.0, 2.0), (8.0, 3.0)))
    tex = 1.0 + texture * tex / tex.std()
    moved = cv2.warpAffine(tex, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), tex.shape[::-1])
    yy, xx = np.mgrid[:size, :size]
    c = (size - 1) / 2
    r = np.hypot(xx - c, yy - c) / (0.45 * size)
    ang = np.arctan2(yy - c, xx - c)
    lobes = sum(np.exp(-0.5 * (np.angle(np.exp(1j * (ang - a))) / 0.25) ** 2) for a in np.arange(4) * np.pi / 2)
    light = 150 * (1 - 0.5 * r**2) * (1 + led * lobes * np.clip(r, 0, 1))
    out = []
    for t in (tex, moved):
        f = t[20:-20, 20:-20] * light + rng.normal(0, noise, (size, size))
        f = np.where(r <= 1, np.clip(f, 0, 255), 0).astype(np.uint8)
        out.append(np.repeat(f[..., None], 3, axis=2))
    return out


def test_local_contrast_takes_out_smooth_shading():
    from bodyslam.vision.matching import local_contrast

    even, _ = _lit_pair(shift=(0.0, 0.0), noise=0.0, led=0.0)
    a = even[..., 0].astype(np.float32)
    ramp = np.linspace(0.6, 1.4, a.shape[1], dtype=np.float32)[None, :]  # a light falling off across the view
    b = np.clip(a * ramp + 20.0, 0, 255).astype(np.uint8)
    inner = np.zeros(a.shape, bool)
    inner[40:200, 40:200] = True  # away from the disc's rim
    raw = np.abs(a - b)[inner].mean()
    lc = np.abs(local_contrast(a.astype(np.uint8), 12.0).astype(float) - local_contrast(b, 12.0))[inner].mean()
    # the same wall under two lights: nearly the same local contrast (measured: 21 gray levels apart on the
    # brightness, ~1 on the local contrast; 0.15 leaves room for OpenCV's blurs across versions)
    assert raw > 15 and lc < 0.15 * raw
    assert local_contrast(b, 12.0).dtype == np.uint8


def test_tracking_holds_under_a_light_that_stays_in_the_image(monkeypatch):
    # Lucas-Kanade's coarse levels lock on to shading that stays put in the image while the wall moves (session 51:
    # a quarter of the realistic exam pairs lost their tracks; 3.5% on the local contrast). The same pair tracked on
    # the brightness itself (the rule before) keeps fewer tracks than tracking needs, so the test sees the change.
    import bodyslam.vision.matching as matching

    f1, f2 = _lit_pair()
    cam = FisheyeCamera.equidistant(240, 240, 156.0)
    mt = Matcher(cam, "fast")
    m = mt._track(mt.features(f1), mt.features(f2))
    assert m.method == "lk" and len(m) >= 2 * mt.lk_min_matches
    assert np.allclose(np.median(m.pts2_px - m.pts1_px, axis=0), (10.0, 6.0), atol=0.1)
    monkeypatch.setattr(matching, "local_contrast", lambda gray, sigma_px: gray)
    before = mt._track(mt.features(f1), mt.features(f2))
    assert len(before) < mt.lk_min_matches


def test_a_frame_wider_than_the_tracking_size_is_tracked_shrunk_and_answered_in_its_own_pixels():
    # the same lit pair at twice the size (480 px, moved by twice as many pixels) is tracked at TRACK_WORK_PX (240)
    # and its tracks come back in the 480-px frame's pixels: the shift is the 480-px one, not the shrunk image's
    from bodyslam.vision.matching import TRACK_WORK_PX

    f1, f2 = _lit_pair(size=480, shift=(20.0, 12.0))
    mt = Matcher(FisheyeCamera.equidistant(480, 480, 156.0), "fast")
    assert mt._track_scale == TRACK_WORK_PX / 480
    m = mt._track(mt.features(f1), mt.features(f2))
    assert m.method == "lk" and len(m) >= mt.lk_min_matches  # enough to be used (measured: 95 of 120 candidates)
    # the tracks' shift to a tenth of a shrunk pixel (0.2 px here), as the 240-px pair above holds 0.1
    assert np.allclose(np.median(m.pts2_px - m.pts1_px, axis=0), (20.0, 12.0), atol=0.2)
    assert m.pts1_px.max() > TRACK_WORK_PX  # in the frame's pixels (measured: up to 390), not the shrunk image's


def test_a_repeated_frame_verifies_all_its_matches_in_every_mode():
    # two frames without parallax (a capsule at rest, a frame an export repeats) have no essential matrix: USAC then
    # kept all or none of the matches by chance (demo frames 0-5 repeated: 12 of 18 pairs verified none before the
    # rotation check), and a step verified by none is lost to fast motion; a pure rotation keeps them all
    from pathlib import Path

    from bodyslam.io import read_image
    from bodyslam.meta import read_meta

    demo = Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0"
    cam = read_meta(demo).camera_model()
    for mode in ("fast", "sift", "asift"):
        mt = Matcher(cam, mode)
        for k in range(6):
            img = read_image(demo / "frames" / f"{k:06d}.png")
            m = mt.match_features(mt.features(img), mt.features(img.copy()))
            assert m.n_candidates >= 100 and len(m) == m.n_candidates, (mode, k, len(m), m.n_candidates)


def test_rotation_ransac_finds_the_rotation_among_outliers_and_says_none_without_rays():
    from scipy.spatial.transform import Rotation

    from bodyslam.vision.matching import rotation_ransac

    rng = np.random.default_rng(3)
    r1 = rng.normal(size=(200, 3))
    r1[:, 2] = np.abs(r1[:, 2]) + 0.3
    r1 /= np.linalg.norm(r1, axis=1)[:, None]
    R = Rotation.from_rotvec([0.02, -0.03, 0.4]).as_matrix()  # a capsule rolling 23 deg in place
    r2 = r1 @ R.T + rng.normal(scale=1e-4, size=r1.shape)  # ~0.006 deg of noise, well inside the 0.5 deg
    r2[:80] = rng.normal(size=(80, 3))  # 40% outliers
    r2 /= np.linalg.norm(r2, axis=1)[:, None]
    R_est, inl = rotation_ransac(r1, r2, np.radians(0.5))
    assert inl[80:].all() and inl[:80].sum() <= 2  # a random ray lands within 0.5 deg of its place ~1e-5 of times
    assert np.degrees(Rotation.from_matrix(R_est @ R.T).magnitude()) < 0.01
    valid = np.zeros(200, bool)
    valid[:2] = True
    R_none, none = rotation_ransac(r1, r2, np.radians(0.5), valid)
    assert R_none is None and not none.any()


def test_describing_only_the_kept_keypoints_gives_the_same_keypoints_and_descriptors(monkeypatch):
    # fast mode's shrunk tries may detect first and describe only the keypoints they keep (SPLIT_EXTRA_PER_PX, a
    # matter of time): the points, their order (by strength where capped) and their descriptors must be the
    # joint detectAndCompute's exactly, or steps would change with the choice
    f1, f2 = _lit_pair(size=480, texture=0.3, noise=3.0)
    cam = FisheyeCamera.equidistant(480, 480, 156.0)
    joint, split = Matcher(cam, "fast"), Matcher(cam, "fast")
    joint.max_features = split.max_features = 150  # well under what each level finds: the cap's choice is tested
    described = []

    class Counting:  # the split matcher's SIFT, counting the keypoints it is asked to describe
        sift = split._det

        def detect(self, img, mask):
            return self.sift.detect(img, mask)

        def detectAndCompute(self, img, mask):  # noqa: N802 (OpenCV's name)
            return self.sift.detectAndCompute(img, mask)

        def compute(self, img, kp):
            described.append(len(kp))
            return self.sift.compute(img, kp)

        def descriptorSize(self):  # noqa: N802
            return self.sift.descriptorSize()

    monkeypatch.setattr(split, "_det", Counting())
    for img in (f1, f2):
        a, b = joint.features(img), split.features(img)
        for level in ("coarse", "default"):
            split._split[level] = True  # forced (the rule would choose it from the frame before)
            (pa, da), (pb, db) = joint.keypoints(a, level), split.keypoints(b, level)
            assert len(pa) == 150 and np.array_equal(pa, pb) and np.array_equal(da, db), level
            assert split._split[level]  # the frame found many more than it keeps: the next one splits too
    assert described == [150] * 4  # each level described only what it kept
    # detection on the full frame is never split (it gained nothing at 576 px), and ASIFT never
    full = Matcher(cam, "fast")
    full.keypoints(full.features(f1), "full")
    assert full._split["full"] is False
    asift = Matcher(cam, "asift")
    asift.max_features = 150
    asift.features(f1)
    assert not asift._split.get("default", False)

"""SRM segmentation, region features, and the FT/FL kernel SVM with its non-executable model files."""

import json

import numpy as np
import pytest

from bodyslam.vision.classify import (FEATURES_9, FEATURES_RICH, P90_TARGET, TunnelClassifier, frame_features,
                                      frame_status, normalise_photometric, region_features, train)
from bodyslam.errors import ConfigError, InputError
from bodyslam.vision.segmentation import paint_regions, srm


def disc_frame(size=96, dark_radius=20, centre=(48, 48), seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    mask = (xx - 47.5) ** 2 + (yy - 47.5) ** 2 <= 46**2
    img = np.full((size, size, 3), (200, 120, 90), np.float64)
    dark = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= dark_radius**2
    img[dark] = (30, 15, 10)
    img += rng.normal(0, 3, img.shape)
    img[~mask] = 0
    return np.clip(img, 0, 255).astype(np.uint8), mask, dark & mask


def test_srm_separates_a_dark_tunnel_and_respects_the_mask():
    img, mask, dark = disc_frame()
    seg = srm(img, mask, Q=16, work_px=None)
    assert (seg.labels[~mask] == -1).all() and (seg.labels[mask] >= 0).all()
    big = np.argsort(seg.sizes)[::-1][:2]
    assert seg.sizes[big].sum() >= 0.97 * mask.sum()  # two regions: the wall and the tunnel (noise is merged)
    d = big[np.argmin(seg.means[big].sum(axis=1))]
    assert np.mean(seg.labels[dark] == d) > 0.97
    assert paint_regions(seg, (192, 192)).shape == (192, 192, 3)


def test_region_features_describe_the_darkest_region():
    img, mask, dark = disc_frame(dark_radius=15, centre=(60, 48))
    f = region_features(srm(img, mask, work_px=None))
    named = dict(zip(FEATURES_RICH, f))
    assert named["dark_size"] == pytest.approx(dark.sum() / mask.sum(), rel=0.05)
    diam = 2 * np.sqrt(mask.sum() / np.pi)
    assert named["dark_length"] == pytest.approx(30 / diam, rel=0.1)  # a circle: length = width = diameter
    assert named["dark_width"] == pytest.approx(30 / diam, rel=0.1)
    assert named["dark_r"] == pytest.approx(30 / 255, abs=0.02)
    assert named["rest_r"] == pytest.approx(200 / 255, abs=0.02)
    assert named["dark_offset"] == pytest.approx(12.5 / 46, abs=0.05)


def test_the_working_size_keeps_no_pixel_that_straddles_the_field_stop():
    # an octagon-like straight stop edge that falls inside a working pixel: that pixel averages in the black
    # outside, so it must be left out (session 29: such pixels made a dark line the classifier took for the tunnel)
    img = np.full((100, 100, 3), 150, np.uint8)
    mask = np.zeros((100, 100), bool)
    mask[:, :55] = True  # working pixels are 10 frame pixels wide: column 5 covers 50-59, half inside
    img[~mask] = 0
    seg = srm(img, mask, work_px=10)
    assert (seg.labels[:, :5] >= 0).all()
    assert (seg.labels[:, 5:] == -1).all()
    assert seg.means.min() > 140  # no region mixes in the black outside


def test_the_darkest_region_is_never_a_one_pixel_line():
    # a dark line one pixel wide (a straight field-stop edge; 70 pixels, more than 1% of the field) and a less dark
    # blob: the blob is the tunnel candidate
    img, mask, dark = disc_frame(dark_radius=12, centre=(48, 48))
    img[dark] = (90, 60, 50)
    edge = np.zeros_like(mask)
    edge[77] = mask[77]
    img[edge] = (5, 5, 5)
    seg = srm(img, mask, work_px=None)
    line = np.bincount(seg.labels[edge]).argmax()
    assert seg.sizes[line] >= 0.01 * mask.sum() and seg.means[line].max() < 20  # the line is its own dark region
    named = dict(zip(FEATURES_RICH, region_features(seg)))
    # the blob's size to 10% (SRM may take or leave its noisy rim pixels); the blob is 24 px across in a 92 px field
    # (width 0.26 of it), the line 0 wide, so 0.2 tells them apart
    assert named["dark_size"] == pytest.approx(dark.sum() / mask.sum(), rel=0.1)
    assert named["dark_width"] > 0.2 and named["dark_rim_share"] < 0.1


def test_frames_without_content_get_a_defined_answer():
    _, mask, _ = disc_frame()
    assert frame_status(np.zeros((96, 96, 3), np.uint8), mask) == "dark"
    assert frame_status(np.full((96, 96, 3), 255, np.uint8), mask) == "saturated"
    grey = disc_frame()[0][..., 0]
    assert len(frame_features(grey, mask)) == len(FEATURES_RICH)  # grey frames are read as RGB
    with pytest.raises(InputError, match="too small"):
        frame_features(np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), bool))
    with pytest.raises(InputError, match="mask"):
        frame_features(disc_frame()[0], np.ones((50, 50), bool))


@pytest.fixture(scope="module")
def toy_model():
    rng = np.random.default_rng(1)
    n = 120
    X = rng.normal(size=(n, len(FEATURES_RICH)))
    y = np.where(X[:, 0] + 0.5 * X[:, 3] ** 2 > 0.3, "FT", "FL")
    return train(X, y, FEATURES_RICH, folds=3), X, y


def test_decision_function_equals_scikit_learn(toy_model):
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    model, X, y = toy_model
    ref = make_pipeline(StandardScaler(), SVC(kernel="rbf", C=model.info["C"], gamma=model.gamma))
    ref.fit(X, np.where(y == "FT", 1, -1))
    assert np.allclose(model.decision(X), ref.decision_function(X), atol=1e-8)
    assert np.mean(model.predict(X) == y) > 0.9


def test_model_files_round_trip_and_refuse_tampering(toy_model, tmp_path):
    model, X, _ = toy_model
    p = tmp_path / "m.npz"
    model.save(p)
    back = TunnelClassifier.load(p)
    assert np.array_equal(back.decision(X), model.decision(X)) and back.features == model.features
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="not a readable model"):
        TunnelClassifier.load(tmp_path / "junk.npz")
    # an archive holding a pickled object array: refused, never unpickled
    np.savez(tmp_path / "obj.npz", support_vectors=np.array([object()], dtype=object), dual_coef=np.zeros(1),
             scaler_mean=np.zeros(1), scaler_scale=np.ones(1), header=np.zeros(1, np.uint8))
    with pytest.raises(InputError):
        TunnelClassifier.load(tmp_path / "obj.npz")
    # a foreign format, and arrays that do not fit the header
    hdr = {"format": "someone-else/1", "features": list(FEATURES_9), "gamma": 0.1, "intercept": 0.0}
    np.savez(tmp_path / "foreign.npz", support_vectors=np.zeros((2, 9)), dual_coef=np.zeros(2),
             scaler_mean=np.zeros(9), scaler_scale=np.ones(9),
             header=np.frombuffer(json.dumps(hdr).encode(), np.uint8))
    with pytest.raises(InputError, match="format"):
        TunnelClassifier.load(tmp_path / "foreign.npz")
    hdr["format"] = "bodyslam-tunnel-svm/1"
    np.savez(tmp_path / "shape.npz", support_vectors=np.zeros((2, 5)), dual_coef=np.zeros(2),
             scaler_mean=np.zeros(9), scaler_scale=np.ones(9),
             header=np.frombuffer(json.dumps(hdr).encode(), np.uint8))
    with pytest.raises(InputError, match="inconsistent"):
        TunnelClassifier.load(tmp_path / "shape.npz")
    with pytest.raises(InputError, match="not found"):
        TunnelClassifier.load(tmp_path / "missing.npz")


def test_a_model_is_used_at_the_working_size_it_was_trained_at(toy_model, tmp_path):
    """The size a model records (info ``work_px``) survives its file and is what the pipeline classifies at,
    unless the settings say otherwise; a model that does not record one keeps the old rule (96 px, fast 64)."""
    from dataclasses import replace

    from bodyslam.vision.odometry import MotionSettings, classify_work_px

    model = toy_model[0]
    sized = replace(model, info={**model.info, "work_px": 64})
    sized.save(tmp_path / "m.npz")
    back = TunnelClassifier.load(tmp_path / "m.npz")
    assert back.work_px == 64 and model.work_px is None
    assert classify_work_px(MotionSettings(), back) == 64 == classify_work_px(MotionSettings(match_mode="fast"), back)
    assert classify_work_px(MotionSettings(classify_px=48), back) == 48
    assert classify_work_px(MotionSettings(), model) == 96 and classify_work_px(MotionSettings(match_mode="fast")) == 64


def test_balanced_training_weights_the_rare_class():
    """With one class rare (~10% FL, as on thesis-like motion), class weighting finds more of it than plain
    training on the same data (recall on the training frames themselves: what the weighting changes)."""
    rng = np.random.default_rng(3)
    X = rng.normal(size=(300, len(FEATURES_RICH)))
    y = np.where(X[:, 0] + 0.6 * rng.normal(size=300) > 1.2, "FL", "FT")
    plain, bal = train(X, y, FEATURES_RICH, folds=3), train(X, y, FEATURES_RICH, folds=3, balanced=True)
    recall = [np.mean(m.predict(X)[y == "FL"] == "FL") for m in (plain, bal)]
    assert 0.05 < np.mean(y == "FL") < 0.2 and recall[1] > recall[0]
    assert bal.info["class_weight"] == "balanced" and plain.info["class_weight"] == "none"


def _cast(img, gains):
    return np.clip(img.astype(np.float64) * np.asarray(gains), 0, 255).astype(np.uint8)


def test_photometric_normalisation_takes_out_exposure_and_colour_cast():
    """``channel_p90`` gives the same frame (to the rounding of the 8-bit levels: <= 1 on average, 3 at most) under
    any gain per channel; ``exposure_p90`` under a common gain, and keeps the cast; features follow. Without it the
    darker frame's features move (what made the shipped model call darker real lumen frames FL)."""
    img, mask, _ = disc_frame(size=128, dark_radius=25, centre=(60, 58), seed=4)
    img = np.clip(img.astype(np.float64) + 0.3 * np.random.default_rng(5).normal(0, 20, img.shape), 0, 255)
    img = np.where(mask[..., None], img, 0).astype(np.uint8)
    darker_cast = _cast(img, [0.55, 0.7, 0.9])
    darker = _cast(img, [0.6, 0.6, 0.6])
    a, b = normalise_photometric(img, mask, "channel_p90"), normalise_photometric(darker_cast, mask, "channel_p90")
    diff = np.abs(a.astype(int) - b.astype(int))[mask]
    assert diff.mean() <= 1.0 and diff.max() <= 3
    assert np.allclose(np.percentile(a[mask], 90, axis=0), P90_TARGET, atol=1.0)
    c, d = normalise_photometric(img, mask, "exposure_p90"), normalise_photometric(darker, mask, "exposure_p90")
    diff = np.abs(c.astype(int) - d.astype(int))[mask]
    assert diff.mean() <= 1.0 and diff.max() <= 3
    # the cast is kept: the channels' means keep their order and ratio (red ~2.2x blue here)
    m = c[mask].mean(axis=0)
    assert m[0] > m[1] > m[2] and abs(m[0] / m[2] - img[mask].mean(axis=0)[0] / img[mask].mean(axis=0)[2]) < 0.1
    assert normalise_photometric(img, mask, "none") is img
    f = [frame_features(x, mask, photometric="channel_p90") for x in (img, darker_cast)]
    raw = [frame_features(x, mask) for x in (img, darker_cast)]
    # the RGB means of the darkest region and of the rest (/255): 0.02 is 5 grey levels, against 0.004 measured
    # after the normalisation (rounding); without it the rest's red moves by 0.35 here (the darkening itself)
    colours = slice(3, 9)
    assert np.abs(f[0][colours] - f[1][colours]).max() < 0.02 < np.abs(raw[0][colours] - raw[1][colours]).max()
    with pytest.raises(ConfigError, match="photometric"):
        normalise_photometric(img, mask, "histogram")
    from bodyslam.cli import PHOTOMETRIC_CHOICES
    from bodyslam.vision.classify import PHOTOMETRIC_MODES

    assert PHOTOMETRIC_CHOICES == PHOTOMETRIC_MODES  # the CLI's choices, written out for a light --help


def test_a_model_is_used_with_the_photometric_normalisation_it_was_trained_with(toy_model, tmp_path, monkeypatch):
    """The ``photometric`` entry survives the model file and the pipeline's frame classification applies it; a model
    without it (trained before) is used on the frames as they are; an unknown one is refused on load."""
    from dataclasses import replace

    from bodyslam.camera import FisheyeCamera
    from bodyslam.vision.odometry import MotionSettings, VisualOdometry

    model = toy_model[0]
    assert model.photometric == "none"
    norm = replace(model, info={**model.info, "photometric": "channel_p90"})
    norm.save(tmp_path / "m.npz")
    back = TunnelClassifier.load(tmp_path / "m.npz")
    assert back.photometric == "channel_p90"
    img, mask, _ = disc_frame(size=128, dark_radius=25, centre=(60, 58), seed=4)
    cam = FisheyeCamera.equidistant(128, 128, 156.0)
    engine = VisualOdometry(cam, MotionSettings(model=str(tmp_path / "m.npz")), radius_m=0.0125, mask=mask)
    assert engine.classifier.photometric == "channel_p90"
    seen = []
    import bodyslam.vision.classify as classify_mod

    real = classify_mod.frame_features

    def spy(rgb, m, Q=16.0, work_px=96, photometric="none"):
        seen.append(photometric)
        return real(rgb, m, Q, work_px, photometric)

    monkeypatch.setattr(classify_mod, "frame_features", spy)
    engine.classify(img)
    assert seen == ["channel_p90"]
    bad = replace(model, info={**model.info, "photometric": "histogram"})
    bad.save(tmp_path / "bad.npz")
    with pytest.raises(InputError, match="photometric"):
        TunnelClassifier.load(tmp_path / "bad.npz")


def test_photometric_normalisation_is_the_per_pixel_scaling_it_replaces():
    """The looked-up normalisation (session 66, for speed) gives exactly the pixels of the direct form it replaced:
    each channel's masked 90th percentile by ``np.percentile``, the image scaled in float32, rounded and saturated;
    also for a non-contiguous view, a mask that is not boolean, gains that saturate, and an empty mask."""
    import cv2

    def direct(rgb, mask, mode):
        sel = mask.astype(bool)
        if mode == "channel_p90":
            p90 = [float(np.percentile(rgb[:, :, c][sel], 90)) if sel.any() else 0.0 for c in range(3)]
            gains = np.array([P90_TARGET / max(p, 1.0) for p in p90], np.float32)
        else:
            value = np.max(rgb, axis=2)
            gains = np.full(3, P90_TARGET / max(float(np.percentile(value[sel], 90)) if sel.any() else 0.0, 1.0),
                            np.float32)
        return cv2.convertScaleAbs(rgb.astype(np.float32) * gains)

    rng = np.random.default_rng(7)
    for k in range(12):
        rgb = (rng.integers(0, 256, (90, 110, 3)) // (1 + 3 * k)).astype(np.uint8)  # darker and darker: gains to 30
        masks = [rng.random(rgb.shape[:2]) > 0.4, (rng.random(rgb.shape[:2]) > 0.5).astype(np.uint8) * 255,
                 np.zeros(rgb.shape[:2], bool)]
        for mask in masks:
            for mode in ("channel_p90", "exposure_p90"):
                out = normalise_photometric(rgb, mask, mode)
                assert out.dtype == np.uint8 and np.array_equal(out, direct(rgb, mask, mode)), (k, mode)
        view = rgb[:, ::2]
        assert np.array_equal(normalise_photometric(view, masks[0][:, ::2], "channel_p90"),
                              direct(view, masks[0][:, ::2], "channel_p90"))

"""Facing the tunnel (FT) or facing the lumen wall (FL): region features of an SRM segmentation and a kernel SVM
(dissertation Sec. 3.2.1).

Features (:func:`region_features`), from the segmentation inside the valid field of view:

- the dissertation's nine: size of the darkest region (fraction of the field of view), its length and width
  (major and minor axis of its second moments, as fractions of the field's diameter), its RGB mean and the RGB
  mean of the remaining regions (both /255). "Darkest" is the region of lowest mean luminance among those covering
  at least 1% of the field (a dark speck of a few pixels is not a tunnel) and at least :data:`MIN_WIDTH_PX` across
  (a line along the field stop is not one either);
- five more (``rich`` set): the darkest region's centroid distance from the image centre and its share of
  pixels on the field's rim (both fractions), its luminance over the rest's, its fill of the ellipse of its
  moments, and log(1 + number of regions).

Photometric normalisation (:func:`normalise_photometric`, the model's ``photometric`` entry), before segmentation:
``channel_p90`` scales each colour channel so that its 90th percentile inside the field of view reaches
:data:`P90_TARGET`; ``exposure_p90`` scales all three by one factor, so that the 90th percentile of each pixel's
brightest channel (HSV's value) does (the colour cast is kept, and the red of mucosa is not clipped). A capsule's
exposure (its light control, the distance to the wall) and colour response differ from exam to exam and from
capsule to capsule, and features of absolute colour learnt on one look mis-call another (session 62: the real
PillCam frames made 40% darker turned the shipped model's four lumen-facing frames FL). ``channel_p90`` makes the
features the same under any gain per channel (up to clipping), ``exposure_p90`` under any common gain. Models that
record no ``photometric`` entry (those trained before) are used without it (``none``).

Model files are numpy ``.npz`` archives loaded with ``allow_pickle=False``: support vectors, dual coefficients,
intercept, RBF gamma, scaler mean and scale, and a JSON header (feature list, format, versions, training
summary) stored as bytes. Loading cannot run code; a tampered or foreign file gets an :class:`InputError`. The
decision function is evaluated here with numpy (``sum_i a_i exp(-gamma |x - s_i|^2) + b``), so a model does not
depend on the scikit-learn version that trained it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from bodyslam.errors import ConfigError, InputError
from bodyslam.vision.segmentation import Segmentation, srm

log = logging.getLogger(__name__)

__all__ = ["FEATURES_9", "FEATURES_RICH", "PHOTOMETRIC_MODES", "normalise_photometric", "region_features",
           "frame_features", "TunnelClassifier", "train"]

FEATURES_9 = ("dark_size", "dark_length", "dark_width", "dark_r", "dark_g", "dark_b", "rest_r", "rest_g", "rest_b")
FEATURES_RICH = FEATURES_9 + ("dark_offset", "dark_rim_share", "dark_contrast", "dark_fill", "log_regions")
FORMAT = "bodyslam-tunnel-svm/1"
LABELS = ("FL", "FT")  # decision < 0: FL, > 0: FT
# photometric normalisation before segmentation (normalise_photometric): none; each channel's 90th percentile inside
# the field of view scaled to P90_TARGET (8-bit); or that of each pixel's brightest channel, all channels by the
# same factor. The 90th percentile is the lit wall on every frame with the lumen in view (the dark tunnel holds
# 1-40% of the field), below the specular spots (a few percent); 200 leaves headroom under 255 for the brighter
# tenth
PHOTOMETRIC_MODES = ("none", "channel_p90", "exposure_p90")
P90_TARGET = 200.0


# the least width (working pixels: the minor axis of a region's second moments, 4 standard deviations) of a region
# that can be the darkest (region_features): a line one pixel wide has 0, a strip two pixels wide 2
MIN_WIDTH_PX = 1.5


def _axes(lab: np.ndarray, k: int) -> tuple[float, float]:
    """``(length, width)`` of region ``k`` (pixels): 4 standard deviations along the major and minor axes of its
    second moments (1, 1 for a single pixel)."""
    ys, xs = np.nonzero(lab == k)
    if len(xs) < 2:
        return 1.0, 1.0
    ev = np.sort(np.maximum(np.linalg.eigvalsh(np.cov(np.stack([xs, ys]).astype(float))), 0.0))[::-1]
    return 4.0 * math.sqrt(ev[0]), 4.0 * math.sqrt(ev[1])


def region_features(seg: Segmentation, min_region_frac: float = 0.01) -> np.ndarray:
    """The ``FEATURES_RICH`` vector of one segmentation (the first nine are the dissertation's)."""
    lab = seg.labels
    valid = lab >= 0
    n_valid = int(valid.sum())
    lum = seg.means @ np.array([0.299, 0.587, 0.114])
    big = seg.sizes >= max(1, min_region_frac * n_valid)
    cand = np.nonzero(big)[0] if big.any() else np.arange(seg.n_regions)
    # the darkest candidate that is no sliver (a region under MIN_WIDTH_PX across, a line along the field stop, say,
    # is not a tunnel); the darkest of all where none is that wide. Candidates are measured darkest first (ties: the
    # lower label, as argmin) until one is wide enough
    d = None
    for k in cand[np.argsort(lum[cand], kind="stable")]:
        length, width = _axes(lab, int(k))
        if width >= MIN_WIDTH_PX:
            d = int(k)
            break
    if d is None:
        d = int(cand[np.argmin(lum[cand])])
        length, width = _axes(lab, d)
    ys, xs = np.nonzero(lab == d)
    vy, vx = np.nonzero(valid)
    cy, cx = vy.mean(), vx.mean()
    diam = 2.0 * math.sqrt(n_valid / math.pi)
    w_rest = seg.sizes.astype(float).copy()
    w_rest[d] = 0.0
    rest_mean = (seg.means * w_rest[:, None]).sum(axis=0) / w_rest.sum() if w_rest.sum() > 0 else seg.means[d]
    r_pix = np.hypot(xs - cx, ys - cy)
    rim = float(np.mean(r_pix > 0.8 * diam / 2.0)) if len(xs) else 0.0
    lum_rest = float(rest_mean @ np.array([0.299, 0.587, 0.114]))
    size = seg.sizes[d] / n_valid
    fill = seg.sizes[d] / max(math.pi / 4.0 * length * width, 1.0)
    return np.array([
        size, length / diam, width / diam, *(seg.means[d] / 255.0), *(rest_mean / 255.0),
        math.hypot(xs.mean() - cx, ys.mean() - cy) / (diam / 2.0) if len(xs) else 0.0,
        rim, (lum[d] + 1.0) / (lum_rest + 1.0), min(fill, 2.0), math.log1p(seg.n_regions),
    ])


def normalise_photometric(rgb: np.ndarray, mask: np.ndarray, mode: str = "channel_p90") -> np.ndarray:
    """``rgb`` (8-bit, h x w x 3) scaled so that the 90th percentile inside ``mask`` of each channel
    (``channel_p90``) or of each pixel's brightest channel (``exposure_p90``, one factor for all three) is
    :data:`P90_TARGET`, clipped at 255 (module docstring); ``none``: ``rgb`` itself."""
    if mode == "none":
        return rgb
    if mode == "channel_p90":
        rgb, mask8 = np.ascontiguousarray(rgb), mask.astype(np.uint8)
        gains = np.array([P90_TARGET / max(_masked_p90_u8(rgb, mask8, c), 1.0) for c in range(3)], np.float32)
    elif mode == "exposure_p90":
        value = np.max(rgb, axis=2)  # HSV's value
        gains = np.full(3, P90_TARGET / max(_masked_p90_u8(value, mask), 1.0), np.float32)
    else:
        raise ConfigError(f"photometric normalisation must be one of {PHOTOMETRIC_MODES}, got {mode!r}")
    # each channel's 256 values scaled exactly as the whole image would be (float32 product, rounded and saturated
    # to 0-255 by convertScaleAbs), then looked up: the same pixels (the whole normalisation of a 576-px frame 6.3 ->
    # 1.4 ms, session 66)
    lut = cv2.convertScaleAbs(np.arange(256, dtype=np.float32)[:, None] * gains[None, :])
    return cv2.LUT(np.ascontiguousarray(rgb), lut.reshape(256, 1, 3))


def _masked_p90_u8(image: np.ndarray, mask: np.ndarray, channel: int = 0) -> float:
    """``np.percentile(image[..., channel][mask], 90)`` of an 8-bit image (its linear method), from the masked
    histogram of that channel (read in place: no copy of it)."""
    from bodyslam.vision.matching import _percentiles_from_hist

    counts = cv2.calcHist([np.ascontiguousarray(image)], [channel], mask.astype(np.uint8, copy=False), [256], [0, 256])
    v = _percentiles_from_hist(counts.ravel(), (90,))
    return 0.0 if v is None else float(v[0])


def frame_features(rgb: np.ndarray, mask: np.ndarray, Q: float = 16.0, work_px: int = 96,
                   photometric: str = "none") -> np.ndarray:
    """Features of one frame, after the photometric normalisation ``photometric`` (:data:`PHOTOMETRIC_MODES`; a
    model's :attr:`TunnelClassifier.photometric`). Frames that cannot be segmented meaningfully raise
    :class:`InputError`."""
    if rgb.ndim == 2:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_GRAY2RGB)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(f"frames must be 8-bit RGB or grey, got shape {rgb.shape} dtype {rgb.dtype}")
    if rgb.shape[:2] != mask.shape:
        raise InputError(f"frame is {rgb.shape[1]}x{rgb.shape[0]}, the field-of-view mask is "
                         f"{mask.shape[1]}x{mask.shape[0]}")
    if min(rgb.shape[:2]) < 16:
        raise InputError(f"frame of {rgb.shape[1]}x{rgb.shape[0]} is too small to classify")
    return region_features(srm(normalise_photometric(rgb, mask, photometric), mask, Q=Q, work_px=work_px))


@dataclass
class TunnelClassifier:
    """An RBF-kernel SVM on standardised region features; ``decision(x) > 0`` means FT."""

    features: tuple[str, ...]
    support_vectors: np.ndarray
    dual_coef: np.ndarray
    intercept: float
    gamma: float
    scaler_mean: np.ndarray
    scaler_scale: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def feature_index(self) -> np.ndarray:
        return np.array([FEATURES_RICH.index(f) for f in self.features])

    @property
    def work_px(self) -> int | None:
        """The SRM working size the model was trained at (its features are measured at that size), if recorded."""
        v = self.info.get("work_px")
        return int(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 16 else None

    @property
    def photometric(self) -> str:
        """The photometric normalisation the model's features were measured after (:data:`PHOTOMETRIC_MODES`;
        ``none`` for a model that does not record it)."""
        return str(self.info.get("photometric", "none"))

    def decision(self, X_rich: np.ndarray) -> np.ndarray:
        """Decision values for rows of ``FEATURES_RICH`` vectors (the model picks its own columns)."""
        X = np.atleast_2d(np.asarray(X_rich, float))[:, self.feature_index]
        Z = (X - self.scaler_mean) / self.scaler_scale
        d2 = (np.sum(Z * Z, axis=1)[:, None] + np.sum(self.support_vectors**2, axis=1)[None, :]
              - 2.0 * Z @ self.support_vectors.T)
        return np.exp(-self.gamma * np.maximum(d2, 0.0)) @ self.dual_coef + self.intercept

    def predict(self, X_rich: np.ndarray) -> np.ndarray:
        return np.where(self.decision(X_rich) > 0, "FT", "FL")

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        from bodyslam.io import atomic_path

        header = {"format": FORMAT, "features": list(self.features), "gamma": self.gamma,
                  "intercept": self.intercept, **self.info}
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, support_vectors=self.support_vectors, dual_coef=self.dual_coef,
                         scaler_mean=self.scaler_mean, scaler_scale=self.scaler_scale,
                         header=np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TunnelClassifier":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("support_vectors", "dual_coef", "scaler_mean", "scaler_scale", "header")}
        except FileNotFoundError:
            raise InputError(f"{path}: model file not found") from None
        except KeyError as exc:
            raise InputError(f"{path}: not a tunnel classifier model (missing {exc})") from None
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:  # not an npz, object arrays, truncated
            raise InputError(f"{path}: not a readable model file ({exc})") from None
        try:
            header = json.loads(arrays["header"].tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise InputError(f"{path}: model header is not JSON") from None
        if header.get("format") != FORMAT:
            raise InputError(f"{path}: model format {header.get('format')!r}, expected {FORMAT!r}")
        feats = tuple(header.get("features", ()))
        if not feats or any(f not in FEATURES_RICH for f in feats):
            raise InputError(f"{path}: unknown feature list {feats}")
        sv, dc = arrays["support_vectors"], arrays["dual_coef"]
        mu, sc = arrays["scaler_mean"], arrays["scaler_scale"]
        n = len(feats)
        ok = (sv.ndim == 2 and sv.shape[1] == n and dc.shape == (sv.shape[0],) and mu.shape == (n,)
              and sc.shape == (n,) and all(np.issubdtype(a.dtype, np.floating) for a in (sv, dc, mu, sc)))
        if not ok:
            raise InputError(f"{path}: model arrays have inconsistent shapes or types")
        try:
            gamma, intercept = float(header["gamma"]), float(header["intercept"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: model header lacks gamma/intercept") from None
        if not (np.isfinite(sv).all() and np.isfinite(dc).all() and np.isfinite(mu).all()
                and np.isfinite(sc).all() and (sc > 0).all() and math.isfinite(gamma) and gamma > 0):
            raise InputError(f"{path}: model contains non-finite or invalid values")
        info = {k: v for k, v in header.items() if k not in ("format", "features", "gamma", "intercept")}
        if info.get("photometric", "none") not in PHOTOMETRIC_MODES:
            raise InputError(f"{path}: unknown photometric normalisation {info.get('photometric')!r} "
                             f"(known: {', '.join(PHOTOMETRIC_MODES)})")
        return cls(feats, sv, dc, intercept, gamma, mu, sc, info)

    @classmethod
    def default(cls) -> "TunnelClassifier":
        p = Path(__file__).with_name("models") / "tunnel_svm.npz"
        if not p.exists():
            raise ConfigError(f"the default classifier model is missing ({p}); train one with "
                              "`bodyslam train-classifier`")
        return cls.load(p)


def train(X_rich: np.ndarray, y: np.ndarray, features: tuple[str, ...] = FEATURES_RICH, folds: int = 5,
          seed: int = 0, info: dict | None = None, balanced: bool = False) -> TunnelClassifier:
    """Fit scaler + RBF SVM, ``C`` and ``gamma`` chosen by stratified k-fold cross-validation (accuracy).
    ``balanced``: weight each class by the inverse of its frequency and choose by balanced accuracy (the mean of
    the FT and FL recalls): for training sets where one class is rare (a thesis-like motion faces the tunnel
    almost always)."""
    import sklearn
    from sklearn.model_selection import GridSearchCV, StratifiedKFold
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    y = np.asarray(y)
    if set(np.unique(y)) != {"FL", "FT"}:
        raise InputError(f"training needs both FT and FL frames, got {sorted(set(y.tolist()))}")
    cols = np.array([FEATURES_RICH.index(f) for f in features])
    X = np.asarray(X_rich, float)[:, cols]
    yy = np.where(y == "FT", 1, -1)
    svc = SVC(kernel="rbf", class_weight="balanced" if balanced else None)
    pipe = Pipeline([("scale", StandardScaler()), ("svm", svc)])
    grid = {"svm__C": [0.3, 1, 3, 10, 30, 100], "svm__gamma": [0.01, 0.03, 0.1, 0.3, 1.0]}
    n_min = int(min(np.sum(yy == 1), np.sum(yy == -1)))
    if n_min < 2:  # a class with one frame cannot be split for cross-validation: sklearn's fits failed, a model came out
        raise InputError(f"training needs at least 2 frames of each class to cross-validate, got "
                         f"{int(np.sum(yy == 1))} FT and {int(np.sum(yy == -1))} FL")
    cv = StratifiedKFold(n_splits=max(2, min(folds, n_min)), shuffle=True, random_state=seed)
    search = GridSearchCV(pipe, grid, cv=cv, scoring="balanced_accuracy" if balanced else "accuracy", n_jobs=1)
    search.fit(X, yy)
    best = search.best_estimator_
    svm, sc = best.named_steps["svm"], best.named_steps["scale"]
    meta = {"cv_accuracy": float(search.best_score_), "C": float(search.best_params_["svm__C"]),
            "class_weight": "balanced" if balanced else "none",
            "n_train": int(len(y)), "n_train_ft": int(np.sum(yy == 1)), "n_train_fl": int(np.sum(yy == -1)),
            "sklearn_version": sklearn.__version__, "numpy_version": np.__version__, **(info or {})}
    # sklearn's decision_function: sum dual_coef * K + intercept, positive for classes_[1] (= +1: FT)
    sign = 1.0 if svm.classes_[1] == 1 else -1.0
    return TunnelClassifier(tuple(features), svm.support_vectors_.astype(float),
                            sign * svm.dual_coef_[0].astype(float), sign * float(svm.intercept_[0]),
                            float(svm._gamma), sc.mean_.astype(float), sc.scale_.astype(float), meta)


# -- frames in bulk -----------------------------------------------------------------------------------------------
def frame_status(rgb: np.ndarray, mask: np.ndarray) -> str:
    """``ok``, or why a frame has no meaningful segmentation: ``dark`` (mean luminance < 8/255 in the field of
    view) or ``saturated`` (over 90% of the field at >= 250)."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    v = g[mask]
    if v.size == 0 or v.mean() < 8:
        return "dark"
    if np.mean(v >= 250) > 0.9:
        return "saturated"
    return "ok"


def _features_chunk(args):
    paths, mask, Q, work_px, photometric = args
    from bodyslam.io import read_image

    cv2.setNumThreads(1)  # one worker per core
    out = []
    for p in paths:
        try:
            img = read_image(p)
        except InputError as exc:
            out.append(("unreadable", str(exc), None))
            continue
        if img.shape[:2] != mask.shape:
            out.append(("bad_size", f"{p}: {img.shape[1]}x{img.shape[0]}, expected {mask.shape[1]}x{mask.shape[0]}",
                        None))
            continue
        st = frame_status(img, mask)
        if st != "ok":
            out.append((st, "", None))
            continue
        out.append(("ok", "", frame_features(img, mask, Q, work_px, photometric)))
    return out


def features_of_frames(paths: list[Path], mask: np.ndarray, jobs: int | None = None, Q: float = 16.0,
                       work_px: int = 96, chunk: int = 32, progress=None,
                       photometric: str = "none") -> list[tuple[str, str, np.ndarray | None]]:
    """``(status, message, features)`` per frame path, in order, over ``jobs`` processes (streamed in chunks);
    ``photometric``: :func:`frame_features`'."""
    from bodyslam.parallel import imap_tasks

    if photometric not in PHOTOMETRIC_MODES:
        raise ConfigError(f"photometric normalisation must be one of {PHOTOMETRIC_MODES}, got {photometric!r}")
    tasks = [(paths[i:i + chunk], mask, Q, work_px, photometric) for i in range(0, len(paths), chunk)]
    results = []
    for r in imap_tasks(_features_chunk, tasks, jobs):
        results.extend(r)
        if progress:
            progress(len(results), len(paths))
    return results

"""Feature matching between consecutive capsule frames (dissertation Sec. 3.2.2).

Modes
-----
- ``asift`` (the thesis's matcher): ``cv2.AffineFeature`` over SIFT -- SIFT on affine-warped views of the frame,
  2-NN matching with Lowe's ratio test. Views (``asift_views``): ``compact`` (default) -- the frame and two views
  tilted by sqrt(2), along the image rows and along the columns; ``standard`` -- Morel and Yu's sampling, tilts
  sqrt(2)^k up to ``asift_max_tilt`` with rolls every 72/t degrees (five views at sqrt(2)). Measured on 85 thesis
  pairs at 320x320 (one core): compact 122 ms detection per frame against 268, coverage 73/85 against 69/85, step
  errors 0.0019 cm / 0.023 / 0.103 deg against 0.0023 / 0.063 / 0.132 (a capsule's view of the wall tilts by a few
  degrees per step: the extra rolls add keypoints, not matches); 20 seeds in the README.
- ``sift``: plain SIFT, same matching (a middle ground).
- ``fast`` (whole exams): pyramidal Lucas-Kanade tracking of up to 300 corners (forward-backward check,
  specular highlights masked) first, on the frames' local contrast (:func:`local_contrast`: a capsule's light
  stays where it is in the image while the wall moves, and on the brightness itself the pyramid's coarse levels
  lock on to it: 25% of a realistic exam's pairs lost their tracks, 3.5% on the local contrast; session 51), on
  frames shrunk to at most :data:`TRACK_WORK_PX` wide (its numbers are pixels; session 57);
  when fewer than 60 tracks verify, or the step's fit fails on them, SIFT
  detected on the frame scaled by :data:`COARSE_SCALE` = 0.5, at most 800 keypoints, at most 200 matches to
  verify (:meth:`Matcher.cascade`). The 0.5 try costs ~30 ms per pair against ~75 for ``detect_scale`` = 0.7
  (both frames' detection, matching, fit; one core; SIFT doubles its input, so most of its cost is the first
  octave) and fits all 25 of the 250 first whole-exam pairs tracking fails on (distance error 0.0067 cm against
  0.0059). Where it fails, the *rescue* (``rescue``, on by default):
  SIFT on the full frame, at most :data:`RESCUE_FEATURES` = 3000 keypoints, FLANN, at most 400 matches to verify
  (``sift`` mode's budget), and guided matching (:mod:`bodyslam.vision.guided`) on those keypoints. Without the
  rescue the 0.7-scale try follows the 0.5 one instead. With it, the 0.7 try comes last (:meth:`Matcher.last_resort`),
  only for the pairs whose rescue verified enough matches and did not fit
  (:meth:`~bodyslam.vision.odometry.VisualOdometry.estimate_pair`): before the rescue it decided 3 of the 304
  pairs of thesis seed 7 and 7 of the 206 of realistic tuning seed 595 (the rest went on to the rescue) while its
  detection was about a quarter of fast mode's detection time; session 70 dropped it (thesis seed 7 8% faster),
  which cost fresh realistic seeds 916-919 ten of their 574 fitted steps; in this order 573 (session 72, the same
  speed within the runs' spread; docs/RESULTS.md). The rescue costs only
  the pairs the cheaper tries fail on, and gives fast mode ``sift`` mode's coverage on fast motion (realistic
  tuning seeds 504-506, 200 frames each: steps with an estimate 64 / 61 / 63% -> 65 / 70 / 70%, ``sift`` 68 / 71 /
  69%; steps lost to motion 132 -> 65; thesis seed 7: 80.9 -> 85.6%, ``asift`` 83%; docs/RESULTS.md).
  Cheaper detectors were measured on a thesis frame pair (420x420) and fail on capsule motion:
  ORB found 13-17 verified matches of 1500 keypoints; pyramidal Lucas-Kanade kept 44 of 600 corners in the image
  and 22 of 400 in the unrolled image (a capsule rolls ~8 degrees and the near wall's angular depth jumps by up to
  ~20 degrees per frame at 2 frames/s); SIFT on the half-resolution image verified 32. Dense DIS optical flow
(OpenCV) was measured on 320x320 thesis frames: it misses the roll (error 7.6 deg of 7.8) and, with the roll
removed by the true value, still misses the forward motion (distance error 0.54 cm of 0.41).

Matching is 2-NN with Lowe's ratio test; the second neighbour must lie more than 2 px from the first
(ASIFT finds one scene point in several affine views, and a ratio against the same point's twin rejects good
matches: measured on 40 pairs, distance error 0.030 -> 0.007 cm). Nearest neighbours: FLANN kd-trees (4 trees,
32 checks) in ``asift`` mode and fast mode's rescue (3000 keypoints), exact otherwise (``sift``: the reference;
``fast``'s coarse and default tries). FLANN's trees are random: OpenCV's RNG is re-seeded before every match, so a
pair's matches do not depend on which pairs a process matched before (chunked and resumed runs give the same
result as one run). The exact neighbours are :func:`knn_l2`'s (session 28): one matrix product per block of rows;
SIFT's integer descriptors make it OpenCV's brute-force matcher to the bit (tested), in a quarter of the time (one
thread, per pair: 1.5 ms for 500 keypoints a frame against 5.7, 2.1 for 800 against 8.8, 28 for 2,760 against
114). Exact neighbours at 3000 keypoints would also beat FLANN's time (26 ms against 32 per pair; FLANN's nearest
was the true one for 57% of the keypoints), and they let more fast steps through: on thesis seed 7 (320x320, 300
frames) ``asift`` went from 0.819 to 0.856 of the steps estimated, but the distance error from 0.0027 to 0.0094
cm, one of the new steps fitted at zero distance where the capsule moved 1.12 cm (docs/RESULTS.md). Not adopted.

Every mode keeps features inside the valid field-of-view mask (eroded by ``border_px``: the rim of the image
circle is a strong edge that moves with the lens, not with the scene), and verifies matches geometrically with a
RANSAC essential matrix on the camera model's unit rays (any lens, not only pinhole; OpenCV's USAC: 1.2 ms per
pair against 13 ms for its classic RANSAC, with as many inliers), or a pure rotation where the essential matrix
keeps too few: two frames without parallax (a capsule at rest, a frame repeated by the export) have none
(:data:`ROTATION_CHECK_SHARE`).

Data form: :class:`Matches` holds pixel coordinates ``pts1_px``, ``pts2_px`` ``(n, 2)`` float64 (column, row) of
verified matches, and how many candidates there were before verification.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from bodyslam.camera import CameraModel
from bodyslam.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["MATCH_MODES", "ASIFT_VIEWS", "Matches", "FrameFeatures", "Matcher", "detect_fov_mask", "essential_ransac",
           "knn_l2", "rotation_ransac", "squared_distances"]

from bodyslam.choices import MATCH_MODES  # noqa: E402
ASIFT_VIEWS = ("compact", "standard")
# per mode: (detect_scale, max_features, max_matches); see the module docstring
MODE_DEFAULTS = {"asift": (0.85, 3000, 400), "sift": (1.0, 3000, 400), "fast": (0.7, 800, 200)}
# fast mode's first SIFT try: detection on the frame scaled by 0.5, before ``detect_scale`` (module docstring)
COARSE_SCALE = 0.5
# fast mode's rescue, its last try where the cheaper ones fail (module docstring): SIFT on the full frame, at most
# as many keypoints and matches to verify as ``sift`` mode
RESCUE_FEATURES, RESCUE_MATCHES = MODE_DEFAULTS["sift"][1:]
# fast mode tracks on the frame's local contrast (local_contrast) over this angle (x the camera's focal length in
# pixels: 12 px on the testbed's 320 px frames). Chosen on realistic frames (the first 600 pairs of
# bench_batch.py's 2,000-frame realistic_exam render, and the first 300 of slow tuning renders 587 and 588): the
# pairs with fewer than 60 verified tracks, 25.0 / 27.8 / 31.8% on the brightness, were 5.2 / - / - % at 6 px,
# - / 4.7 / 13.0% at 8, 3.5 / 4.3 / 10.7% at 12, - / 5.7 / 10.4% at 16 and - / 6.7 / 11.4% at 24
TRACK_CONTRAST_SIGMA_RAD = 0.1
# fast mode tracks on frames no wider than this (pixels; wider ones shrunk, their aspect kept): the tracking's window,
# pyramid reach, corner spacing and forward-backward check are in pixels, so a frame's size changed what they meant.
# Chosen on realistic_exam tuning renders (`bodyslam batch` on its defaults, 300-400 frames; per-step distance error,
# the mean over runs): 587-593 at 320 px 0.0197 cm tracked at the frame's own size, 0.0176 at 240, 0.0170 at 200;
# 588-590 rendered at 576 px 0.0272 / 0.0180 / 0.0168 cm (tilt 0.39 / 0.28 / 0.25 deg; ~20% less time). The ideal
# `exam` look at 576 px (tuning 595-596) keeps 0.0022-0.0024 cm, its roll 0.010 / 0.017 / 0.032 deg. 240 is the
# compromise between the two looks (docs/RESULTS.md, session 57)
TRACK_WORK_PX = 240
# A pair whose essential matrix keeps fewer than this share of its matches is also checked against a pure
# rotation (rotation_ransac), and verifies with the rotation's inliers where they are more: two frames without
# parallax (a capsule at rest, a frame repeated by the export) have no essential matrix, and OpenCV's USAC then
# keeps all or none of the matches by chance (a real clip whose frames were each written three times: 4 of its 24
# repeated pairs verified none, were read as lost to fast motion and filled as jumps, the path +90%)
ROTATION_CHECK_SHARE = 0.5
# rotations tried (each from two random matches): with half the matches outliers, one of 64 pairs is clean but for
# (3/4)^64 ~ 1e-8
ROTATION_HYPOTHESES = 64
# SIFT's descriptors are ~2/3 of its time. Where a level that detects on a shrunk frame (fast mode's coarse and
# default tries) found more keypoints on the last frame than it keeps by over SPLIT_EXTRA_PER_PX per pixel of the
# shrunk image, the next frame's are detected first and only the kept ones described: the same descriptors (tested),
# for a second scale space. Measured per frame, one thread, the field of view detected (session 58; the excess per
# pixel in brackets): thesis at 576 px, 0.7 scale (1/66) 83 -> 62-66 ms, 0.5 scale (1/126) 29 -> 24-27;
# realistic_exam at 576 px (1/72, 1/154) 78 -> 60-68 and 27 -> 24-26; thesis at 420 px, 0.7 scale (1/99) 35 -> 26-27
# (docs/RESULTS.md, session 58). On the full frame (`sift` mode, fast mode's rescue) it gained nothing at 576 px
# (1/119-1/156: 156 -> 151-159 and 151 -> 160 ms), so full-size detection is never split; at 320 px few or none are
# left out. Not for ASIFT: cv2.AffineFeature describes given keypoints by warping every view again (120 -> 202 ms).
SPLIT_EXTRA_PER_PX = 1.0 / 180.0
# keypoint levels and where a frame keeps each (:meth:`Matcher.keypoints`)
LEVELS = {"default": "kp", "coarse": "kp_coarse", "full": "kp_full"}


@dataclass(frozen=True, eq=False)
class Matches:
    pts1_px: np.ndarray
    pts2_px: np.ndarray
    n_candidates: int
    method: str = "descriptors"  # how they were found: "descriptors" (SIFT/ASIFT) or "lk" (tracking)

    def __len__(self) -> int:
        return len(self.pts1_px)


@dataclass(eq=False)
class FrameFeatures:
    """One frame's matching inputs: the brightness-normalised gray image (for tracking), the raw gray image
    (for the specular mask), and keypoints ``(pts_px (n, 2), descriptors)`` computed on first use."""

    gray: np.ndarray
    raw_gray: np.ndarray
    kp: tuple[np.ndarray, np.ndarray | None] | None = None
    corners: np.ndarray | None = None
    kp_coarse: tuple[np.ndarray, np.ndarray | None] | None = None  # fast mode's first SIFT try (COARSE_SCALE)
    kp_full: tuple[np.ndarray, np.ndarray | None] | None = None  # fast mode's last try (full size, RESCUE_FEATURES)
    track: np.ndarray | None = None  # fast mode's tracking image (local_contrast of gray), computed on first use
    track_gray: np.ndarray | None = None  # gray at the tracking size (Matcher._track_gray), computed on first use


MIN_OVERLAY_PIXELS = 16  # a constant blob inside the field smaller than this is a speck, not burned-in text


def detect_fov_mask(frames: list[np.ndarray], threshold: int = 12, min_fraction: float = 0.02) -> np.ndarray:
    """The valid field of view of real capsule frames: pixels that are not (nearly) black in most frames and not
    constant across frames (burned-in text, logos and timestamps do not change with the scene).

    ``frames``: a few dozen RGB frames of one exam. Returns a bool mask (h, w).
    """
    if not frames:
        raise ConfigError("need at least one frame to detect the field-of-view mask")
    stack = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) if f.ndim == 3 else f for f in frames]).astype(np.float32)
    bright = (stack > threshold).mean(axis=0) > 0.5
    varying = stack.std(axis=0) > 1.0 if len(frames) >= 3 else np.ones_like(bright)
    mask = bright & varying
    # keep the largest connected region and fill its holes (dark lumen in the middle is still field of view)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1 or stats[1:, cv2.CC_STAT_AREA].max() < min_fraction * mask.size:
        raise ConfigError("could not find the field of view: frames are (nearly) all black or constant")
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = (lab == big).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    hull = cv2.convexHull(np.concatenate(contours))
    filled = np.zeros_like(region)
    cv2.fillConvexPoly(filled, hull, 1)
    filled = cv2.erode(filled, np.ones((3, 3), np.uint8))  # the polygon is drawn over the rim pixels: drop them
    # text inside the hull stays excluded: constant pixels are not field of view -- but only where they form
    # strokes; a few isolated pixels that happened not to change (saturated or flat mucosa over a short clip:
    # measured on the four real frames: 0.25% of the field as specks, all but a few under 16 pixels) are field of view
    constant = (filled.astype(bool) & bright & ~varying).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(constant, connectivity=8)
    strokes = np.isin(lab, 1 + np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= MIN_OVERLAY_PIXELS)[0])
    return filled.astype(bool) & ~strokes


# the detected field agrees with the calibration's image circle when it leaves out at most 1% of the circle
# inside a 2-pixel rim (the detector drops the dark rim on purpose) and adds at most 1% outside it; then the exact
# circle is used. Measured: the ideal testbed's frames (demo, thesis 502) leave out 0.0% inside the rim; the
# realistic testbed's octagonal stop and label 8%; the five real PillCam frames 9%.
FOV_AGREE_FRACTION = 0.01


def field_of_view(frames: list[np.ndarray], circle: np.ndarray) -> tuple[np.ndarray | None, str]:
    """The valid field of view of an exam's frames: ``(mask or None, how)``. Detected from the frames
    (:func:`detect_fov_mask`: field stops, burned-in text and logos); ``None`` -- the calibration's image circle
    ``circle`` -- where the detection agrees with it (:data:`FOV_AGREE_FRACTION`) or finds nothing."""
    try:
        m = detect_fov_mask(frames)
    except ConfigError as exc:
        return None, f"the image circle (no field of view detected: {exc})"
    core = cv2.erode(circle.astype(np.uint8), np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0).astype(bool)
    left_out = float((core & ~m).sum() / max(core.sum(), 1))
    added = float((m & ~circle).sum() / max(circle.sum(), 1))
    if left_out <= FOV_AGREE_FRACTION and added <= FOV_AGREE_FRACTION:
        return None, f"the image circle (the detected field agrees: {100 * left_out:.1f}% left out)"
    return m, (f"detected from {len(frames)} frame(s): {100 * left_out:.0f}% of the image circle left out, "
               f"{100 * added:.0f}% added (a field stop or overlay)")


def _masked_percentiles_u8(gray: np.ndarray, mask: np.ndarray, percents) -> list[float] | None:
    """``np.percentile(gray[mask > 0], percents)`` (its default linear method, the same floating-point steps, so
    the same numbers) from the masked 256-bin histogram: 0.09 ms on a 320x320 frame instead of 0.95 for the
    selection and partial sort. None for an empty mask."""
    return _percentiles_from_hist(cv2.calcHist([gray], [0], mask, [256], [0, 256]).ravel(), percents)


def _percentiles_from_hist(counts: np.ndarray, percents) -> list[float] | None:
    """:func:`_masked_percentiles_u8` from the 256-bin histogram ``counts`` of the pixels (None: no pixel)."""
    cum = np.cumsum(counts.astype(np.int64))
    n = int(cum[-1])
    if n == 0:
        return None
    out = []
    for p in percents:
        q = float(p) / 100.0
        virtual = (n - 1) * q  # numpy's virtual index for its linear method
        prev = math.floor(virtual)
        nxt = min(prev + 1, n - 1)
        t = virtual - prev
        a = int(np.searchsorted(cum, prev, side="right"))  # the value at rank prev of the sorted pixels
        b = int(np.searchsorted(cum, nxt, side="right"))
        d = b - a  # numpy's _lerp
        out.append(float(b - d * (1.0 - t)) if t >= 0.5 else float(a + d * t))
    return out


class Matcher:
    """Matches consecutive frames of one camera.

    Parameters
    ----------
    camera : CameraModel, for the field of view and geometric verification.
    mode : ``"asift"``, ``"sift"`` or ``"fast"``.
    mask : optional bool (h, w) valid-field mask (given or from :func:`detect_fov_mask`); default: the camera's.
    ratio : Lowe's ratio for 2-NN matching.
    ransac_deg : inlier threshold of the essential-matrix RANSAC, degrees of ray angle.
    detect_scale, max_features, max_matches : detect on the frame resized by ``detect_scale`` (keypoints come back
        in full-frame pixels), keep the strongest ``max_features``, verify at most ``max_matches`` (an even
        subset); ``None``: the mode's default (``MODE_DEFAULTS``).
    asift_views, asift_max_tilt : ASIFT's simulated views (module docstring): ``compact`` or ``standard`` (tilts
        up to ``asift_max_tilt``).
    rescue : fast mode's last try where the cheaper ones fail (module docstring); ignored in other modes.
    """

    def __init__(self, camera: CameraModel, mode: str = "asift", mask: np.ndarray | None = None,
                 ratio: float = 0.8, ransac_deg: float = 0.5, border_px: int = 4, asift_max_tilt: float = 1.42,
                 max_matches: int | None = None, max_features: int | None = None,
                 detect_scale: float | None = None, asift_views: str = "compact", rescue: bool = True):
        if mode not in MATCH_MODES:
            raise ConfigError(f"match mode must be one of {MATCH_MODES}, got {mode!r}")
        d_scale, d_feat, d_match = MODE_DEFAULTS[mode]
        self.camera = camera
        self.mode = mode
        self.ratio = float(ratio)
        self.ransac_rad = np.radians(ransac_deg)
        self.max_matches = int(d_match if max_matches is None else max_matches)
        self.max_features = int(d_feat if max_features is None else max_features)
        self.detect_scale = float(d_scale if detect_scale is None else detect_scale)
        if not 0.2 <= self.detect_scale <= 1.0:
            raise ConfigError(f"detect_scale must be in [0.2, 1], got {self.detect_scale}")
        m = camera.fov_mask() if mask is None else np.asarray(mask, bool)
        if m.shape != (camera.height, camera.width):
            raise ConfigError(f"mask is {m.shape[1]}x{m.shape[0]}, frames are {camera.width}x{camera.height}")
        m8 = m.astype(np.uint8) * 255
        if border_px > 0:
            # outside the image counts as outside the field of view (cv2's default border would not erode there)
            m8 = cv2.erode(m8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * border_px + 1,) * 2),
                           borderType=cv2.BORDER_CONSTANT, borderValue=0)
        self.mask = m8
        self._mask_small = self._scaled_mask(self.detect_scale)
        self._mask_coarse = self._scaled_mask(COARSE_SCALE) if mode == "fast" else None
        # contrastThreshold 0.01: rendered and real mucosa are low-contrast (OpenCV's 0.04 finds ~50 points)
        if mode == "asift":
            if asift_views not in ASIFT_VIEWS:
                raise ConfigError(f"asift_views must be one of {ASIFT_VIEWS}, got {asift_views!r}")
            k = max(0, int(round(2 * np.log2(max(asift_max_tilt, 1.0)))))  # tilts sqrt(2)^0 .. sqrt(2)^k
            self._det = cv2.AffineFeature_create(cv2.SIFT_create(contrastThreshold=0.01), maxTilt=k)
            if asift_views == "compact":
                t = float(np.sqrt(2.0))
                self._det.setViewParams([1.0, t, t], [0.0, 0.0, 90.0])
        else:
            self._det = cv2.SIFT_create(contrastThreshold=0.01)
        # fast mode's last try (:data:`RESCUE_FEATURES`), where tracking and the smaller detections fail
        self.rescue = mode == "fast" and rescue
        self._flann = mode == "asift"
        self._split: dict[str, bool] = {}  # per keypoint level: describe only the kept keypoints (keypoints())
        self._flann_matcher = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=32))
        # fast mode tracks first (module docstring): at most lk_corners corners, forward-backward check
        self.lk_corners, self.lk_fb_px, self.lk_min_matches = 300, 0.5, 60
        # 11 x 11 windows, 2 pyramid levels: 3.3 ms per exam pair instead of 5.0 (15 x 15, 3 levels); pairs
        # verified: 272 of 300 exam and 40 of 150 thesis pairs against 274 and 43, step errors the same (README)
        # frames wider than TRACK_WORK_PX are tracked shrunk to it (_track_size)
        self._track_scale = min(1.0, TRACK_WORK_PX / camera.width)
        self._track_wh = self._scaled_size(self._track_scale)
        self._track_mask = self._track_size(self.mask, cv2.INTER_NEAREST)
        self._lk = dict(winSize=(11, 11), maxLevel=2,
                        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))

    # -- features -------------------------------------------------------------------------------------------
    def features(self, rgb: np.ndarray) -> "FrameFeatures":
        """Per-frame features, computed once (lazily) and reused for both pairs a frame belongs to."""
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
        if gray.shape != self.mask.shape:
            raise ConfigError(f"frame is {gray.shape[1]}x{gray.shape[0]}, camera is "
                              f"{self.mask.shape[1]}x{self.mask.shape[0]}")
        if gray.dtype != np.uint8:
            raise ConfigError(f"frames must be 8-bit, got {gray.dtype}")
        f = FrameFeatures(self._normalise(gray), gray)
        if self.mode != "fast":
            self.keypoints(f)
        return f

    def _scaled_size(self, scale: float) -> tuple[int, int]:
        """``(width, height)`` of a frame scaled by ``scale`` (at most 1)."""
        h, w = self.mask.shape
        return (w, h) if scale >= 1.0 else (max(1, round(w * scale)), max(1, round(h * scale)))

    def _scaled_mask(self, scale: float) -> np.ndarray:
        if scale >= 1.0:
            return self.mask
        return cv2.resize(self.mask, self._scaled_size(scale), interpolation=cv2.INTER_NEAREST)

    def keypoints(self, f: "FrameFeatures", level: str = "default") -> tuple[np.ndarray, np.ndarray | None]:
        """``(pts_px (n, 2), descriptors)`` of a frame, detected once per level: ``default``, on the frame scaled
        by ``detect_scale``; fast mode's ``coarse`` (:data:`COARSE_SCALE`) and ``full`` (the full frame, at most
        :data:`RESCUE_FEATURES` keypoints)."""
        if level not in LEVELS:
            raise ConfigError(f"keypoint level must be one of {LEVELS}, got {level!r}")
        if level != "default" and self.mode != "fast":
            raise ConfigError(f"{level} keypoints are fast mode's, this matcher is {self.mode!r}")
        attr = LEVELS[level]
        cached = getattr(f, attr)
        if cached is not None:
            return cached
        gray = f.gray
        small_mask = {"coarse": self._mask_coarse, "full": self.mask}.get(level, self._mask_small)
        if small_mask.shape != self.mask.shape:
            small = cv2.resize(gray, small_mask.shape[::-1], interpolation=cv2.INTER_AREA)
            s_xy = np.array([self.mask.shape[1] / small.shape[1], self.mask.shape[0] / small.shape[0]])
        else:
            small, s_xy = gray, None
        cap = RESCUE_FEATURES if level == "full" else self.max_features
        # a shrunk frame's SIFT describes only the keypoints it keeps where it finds many more (SPLIT_EXTRA_PER_PX)
        may_split = s_xy is not None and self.mode != "asift"
        split = may_split and self._split.get(level, False)
        if split:
            kp, desc = self._det.detect(small, small_mask), None
        else:
            kp, desc = self._det.detectAndCompute(small, small_mask)
        # the next frame's choice (time only: the outputs are the same either way)
        self._split[level] = may_split and len(kp) - cap > SPLIT_EXTRA_PER_PX * small.shape[0] * small.shape[1]
        # positions as one array (a rescaled KeyPoint object per point cost ~1 us: ~3 ms a frame at 3000 points)
        pts = _keypoint_xy(kp)
        if s_xy is not None:  # pixel centres: full = (small + 0.5) * s - 0.5, kept in float32 as a KeyPoint keeps it
            pts = ((pts.astype(np.float64) + 0.5) * s_xy - 0.5).astype(np.float32)
        pts = pts.astype(np.float64).reshape(-1, 2)
        resp = np.array([k.response for k in kp], np.float32) if len(kp) > cap else None
        keep = np.arange(len(pts))  # the kept keypoints' indices, in their order of detection or of strength
        if len(pts):  # ASIFT detects in warped views and may land a point on the mask's edge: enforce the mask
            ij = np.rint(pts).astype(int)
            h, w = self.mask.shape
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
            inside[inside] &= self.mask[ij[inside, 1], ij[inside, 0]] > 0
            keep = keep[inside]
        if len(keep) > cap:  # ASIFT finds ~12k on a 420x420 frame: keep the strongest
            keep = keep[np.argsort(-resp[keep], kind="stable")[:cap]]
        pts = pts[keep]
        if not split:
            desc = None if desc is None else desc[keep]
        elif len(keep):
            chosen = [kp[i] for i in keep]
            computed, desc = self._det.compute(small, chosen)
            if desc is None or len(computed) != len(chosen) or len(desc) != len(chosen):
                # SIFT describes every keypoint it is given; should it not, never pair points with the wrong rows
                log.warning("SIFT described %s of %d keypoints: detecting again",
                            0 if desc is None else len(desc), len(chosen))
                self._split[level] = False
                return self.keypoints(f, level)
        elif len(kp):  # all outside the field: no rows, as detectAndCompute's subset has
            desc = np.zeros((0, self._det.descriptorSize()), np.float32)
        out = (pts, desc)
        setattr(f, attr, out)
        return out

    def match_features(self, f1: "FrameFeatures", f2: "FrameFeatures", method: str | None = None) -> Matches:
        """Verified matches from frame 1 to frame 2. ``method``: ``"lk"`` (tracking), ``"descriptors"``,
        ``"coarse"`` (fast mode: descriptors detected at :data:`COARSE_SCALE`), ``"full"`` (fast mode's rescue: on
        the full frame, :data:`RESCUE_FEATURES`), or ``None``: the mode's first
        choice (fast: tracking, then descriptors when tracking verifies too few)."""
        if method is None:
            if self.mode == "fast":
                m = self._track(f1, f2)
                if len(m) >= self.lk_min_matches:
                    return m
            method = "descriptors"
        if method == "lk":
            return self._track(f1, f2)
        if method not in ("descriptors", "coarse", "full"):
            raise ConfigError(f"match method must be 'lk', 'coarse', 'descriptors' or 'full', got {method!r}")
        level = "default" if method == "descriptors" else method
        (pts1, d1), (pts2, d2) = self.keypoints(f1, level), self.keypoints(f2, level)
        if d1 is None or d2 is None or len(pts1) < 2 or len(pts2) < 2:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), 0)
        q, t = self._ratio_matches(d1, d2, pts2, flann=self._flann or level == "full")
        if len(q) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), 0)
        p1, p2 = pts1[q], pts2[t]
        # one match per point of frame 2 (ASIFT finds the same point in several views)
        _, keep = np.unique(np.round(p2, 1), axis=0, return_index=True)
        p1, p2 = p1[np.sort(keep)], p2[np.sort(keep)]
        return self.verify(p1, p2, level)

    def cascade(self, f1: "FrameFeatures", f2: "FrameFeatures") -> Iterator[Matches]:
        """The matches to try for a pair, cheapest first; the caller stops at the first its estimator accepts.
        Fast mode: the Lucas-Kanade tracks (when at least ``lk_min_matches`` verify), then descriptors detected
        at :data:`COARSE_SCALE`, then on the full frame (``rescue``; :meth:`last_resort` follows where that fails),
        or at ``detect_scale`` without the rescue (module docstring); other modes: their descriptors."""
        if self.mode != "fast":
            yield self.match_features(f1, f2, "descriptors")
            return
        m = self._track(f1, f2)
        if len(m) >= self.lk_min_matches:
            yield m
        yield self.match_features(f1, f2, "coarse")
        yield self.match_features(f1, f2, "full" if self.rescue else "descriptors")

    def last_resort(self, f1: "FrameFeatures", f2: "FrameFeatures") -> Matches | None:
        """Fast mode with the rescue: the matches of the 0.7-scale try (``detect_scale``), for a pair the whole
        cascade failed on (module docstring); None in the other modes and in fast mode without the rescue, whose
        cascade ends with that try."""
        return self.match_features(f1, f2, "descriptors") if self.rescue else None

    def match(self, rgb1: np.ndarray, rgb2: np.ndarray) -> Matches:
        return self.match_features(self.features(rgb1), self.features(rgb2))

    def verify(self, p1: np.ndarray, p2: np.ndarray, level: str = "default") -> Matches:
        """The matches ``p1 -> p2`` (pixels) that a RANSAC essential matrix keeps (at most ``max_matches``, an
        even subset, are tried: enough for a 10-parameter fit; :data:`RESCUE_MATCHES` for matches of ``full``
        keypoints); ``n_candidates`` counts the tried ones."""
        cap = RESCUE_MATCHES if level == "full" else self.max_matches
        if len(p1) > cap:
            sel = np.linspace(0, len(p1) - 1, cap).astype(int)
            p1, p2 = p1[sel], p2[sel]
        inl = self._verify(p1, p2)
        return Matches(p1[inl], p2[inl], len(p1))

    # -- internals ------------------------------------------------------------------------------------------
    def _track(self, f1: FrameFeatures, f2: FrameFeatures) -> Matches:
        """Pyramidal Lucas-Kanade tracking of frame 1's corners into frame 2, kept when the track back lands
        within ``lk_fb_px`` of its start, then verified like descriptor matches. Corners avoid specular
        highlights (they move with the capsule's light, not with the wall). Frames wider than
        :data:`TRACK_WORK_PX` are tracked shrunk to it; the tracks come back in the frame's pixels."""
        if f1.corners is None:
            mask = self._track_mask
            spec = f1.raw_gray >= 245
            if spec.any():
                mask = self.mask.copy()
                mask[cv2.dilate(spec.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0] = 0
                mask = self._track_size(mask, cv2.INTER_NEAREST)
            c = cv2.goodFeaturesToTrack(self._track_gray(f1), self.lk_corners, 0.005, 7, mask=mask)
            f1.corners = np.zeros((0, 1, 2), np.float32) if c is None else c
        p0 = f1.corners
        empty = Matches(np.zeros((0, 2)), np.zeros((0, 2)), 0, "lk")
        if len(p0) < 8:
            return empty
        g1, g2 = self._track_image(f1), self._track_image(f2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(g1, g2, p0, None, **self._lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(g2, g1, p1, None, **self._lk)
        a, b = p0.reshape(-1, 2).astype(np.float64), p1.reshape(-1, 2).astype(np.float64)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(pb.reshape(-1, 2) - a, axis=1) < self.lk_fb_px)
        if self._track_scale != 1.0:  # tracked on the smaller image: back to the frame's pixel centres
            a, b = (a + 0.5) / self._track_scale - 0.5, (b + 0.5) / self._track_scale - 0.5
        h, w = self.mask.shape
        ij = np.rint(b).astype(int)
        ok &= (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        ok[ok] &= self.mask[ij[ok, 1], ij[ok, 0]] > 0
        a, b = a[ok], b[ok]
        if len(a) > self.max_matches:
            sel = np.linspace(0, len(a) - 1, self.max_matches).astype(int)
            a, b = a[sel], b[sel]
        inl = self._verify(a, b)
        return Matches(a[inl], b[inl], len(a), "lk")

    def _track_size(self, img: np.ndarray, interpolation: int) -> np.ndarray:
        """``img`` at the size tracking works at (:data:`TRACK_WORK_PX`)."""
        if self._track_scale == 1.0:
            return img
        return cv2.resize(img, self._track_wh, interpolation=interpolation)

    def _track_image(self, f: FrameFeatures) -> np.ndarray:
        """The image Lucas-Kanade tracks on: :func:`local_contrast` of the frame's gray image, at
        :data:`TRACK_CONTRAST_SIGMA_RAD` (x the camera's focal length in pixels), at the tracking size, computed
        once per frame."""
        if f.track is None:
            f.track = local_contrast(self._track_gray(f),
                                     TRACK_CONTRAST_SIGMA_RAD * float(self.camera.fx) * self._track_scale)
        return f.track

    def _track_gray(self, f: FrameFeatures) -> np.ndarray:
        """The frame's gray image at the tracking size (corners are found on it, :meth:`_track_image` is made from
        it), shrunk once per frame."""
        if f.track_gray is None:
            f.track_gray = self._track_size(f.gray, cv2.INTER_AREA)
        return f.track_gray

    def _ratio_matches(self, d1: np.ndarray, d2: np.ndarray, pts2: np.ndarray, k: int = 4,
                       min_sep_px: float = 2.0, flann: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``(query, train)`` passing the ratio test against the nearest neighbour that is a different
        point of frame 2 (more than ``min_sep_px`` away); a match with no such neighbour among ``k`` passes."""
        idx, dist = self._knn(d1, d2, k, flann)
        have = idx[:, 0] >= 0
        idx, dist = idx[have], dist[have]
        query = np.nonzero(have)[0]
        if len(query) == 0:
            return query, query
        p_best = pts2[idx[:, 0]]
        p_all = pts2[np.where(idx >= 0, idx, 0)]
        distinct = (np.linalg.norm(p_all - p_best[:, None, :], axis=2) > min_sep_px) & (idx >= 0)
        distinct[:, 0] = False
        first = np.where(distinct.any(axis=1), distinct.argmax(axis=1), -1)
        second = np.where(first >= 0, dist[np.arange(len(dist)), np.maximum(first, 0)], np.inf)
        good = dist[:, 0] < self.ratio * second
        return query[good], idx[good, 0]

    def _knn(self, d1: np.ndarray, d2: np.ndarray, k: int, flann: bool) -> tuple[np.ndarray, np.ndarray]:
        """``(idx, dist)`` ``(n1, k)`` of each descriptor's ``k`` nearest in ``d2`` (``flann``: FLANN's kd-trees,
        else exact: :func:`knn_l2`); -1 / inf where fewer."""
        k = min(k, len(d2))
        if not flann:
            return knn_l2(d1, d2, k)
        cv2.setRNGSeed(0x5EED)  # FLANN's random trees: the same for every pair (module docstring)
        knn = self._flann_matcher.knnMatch(d1, d2, k=k)
        idx = np.full((len(knn), k), -1, np.int64)
        dist = np.full((len(knn), k), np.inf)
        # the lists into arrays in three flat passes (element by element took ~7 ms a pair at 3000 keypoints)
        n_each = np.fromiter((len(ms) for ms in knn), np.int64, len(knn))
        filled = np.arange(k)[None, :] < n_each[:, None]  # row-major, as the flat passes run
        idx[filled] = np.fromiter((m.trainIdx for ms in knn for m in ms), np.int64, int(n_each.sum()))
        dist[filled] = np.fromiter((m.distance for ms in knn for m in ms), np.float64, int(n_each.sum()))
        return idx, dist

    def _normalise(self, gray: np.ndarray) -> np.ndarray:
        """Stretch the field of view's 1st-99th brightness percentiles to the full 8-bit range.

        SIFT's contrast threshold is absolute: a capsule's light control dims a frame when the wall is near,
        and the same mucosa then yields a tenth of the keypoints (measured: 155 vs 1585 on testbed frames).
        """
        lo_hi = _masked_percentiles_u8(gray, self.mask, (1.0, 99.0))
        if lo_hi is None:
            return gray
        lo, hi = lo_hi
        if hi - lo < 8:  # a flat (black, saturated) frame: nothing to stretch
            return gray
        lut = np.clip((np.arange(256) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
        return cv2.LUT(gray, lut)

    def _verify(self, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
        """Inliers of a RANSAC essential matrix between the unit rays of the matches, or of a pure rotation
        (:func:`rotation_ransac`) where that keeps more: a pair without parallax (a capsule at rest, a repeated
        frame) has no essential matrix (:data:`ROTATION_CHECK_SHARE`)."""
        n = len(p1)
        if n < 8:
            return np.zeros(n, bool)
        r1, v1 = self.camera.unproject(p1)
        r2, v2 = self.camera.unproject(p2)
        inl = essential_ransac(r1, r2, self.ransac_rad, v1 & v2)[4]
        if inl.sum() < ROTATION_CHECK_SHARE * n:
            rot = rotation_ransac(r1, r2, self.ransac_rad, v1 & v2)[1]
            if rot.sum() > inl.sum():
                return rot
        return inl


def local_contrast(gray: np.ndarray, sigma_px: float, floor: float = 4.0, gain: float = 40.0) -> np.ndarray:
    """``gray`` with its local mean taken out and its local spread divided out (both Gaussian-weighted over
    ``sigma_px``), as 8-bit about 128: ``128 + gain (g - mean) / (sd + floor)``. Shading that changes smoothly
    across the image (a capsule's own light, vignetting, light control) leaves it nearly unchanged, so tracking that
    assumes a constant brightness follows the wall instead of the light. The two smooth fields are worked out on the
    image shrunk by ``sigma_px / 3`` and brought back by linear interpolation: 1.2 ms on a 320 px frame against 3.5
    for full-size blurs, within 0.5 of their gray levels on average."""
    g = gray.astype(np.float32)
    h, w = g.shape
    f = max(1, min(int(sigma_px / 3.0), h // 16, w // 16))
    size = (max(1, round(w / f)), max(1, round(h / f)))

    def smooth(a):
        if f == 1:
            return cv2.GaussianBlur(a, (0, 0), sigma_px)
        small = cv2.GaussianBlur(cv2.resize(a, size, interpolation=cv2.INTER_AREA), (0, 0), sigma_px / f)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)

    d = g - smooth(g)
    sd = smooth(d * d)
    np.sqrt(np.maximum(sd, 0.0, out=sd), out=sd)
    sd += floor
    d *= gain
    d /= sd
    d += 128.0
    return np.clip(d, 0, 255).astype(np.uint8)


def _keypoint_xy(kp) -> np.ndarray:
    """``(n, 2)`` float32 positions of OpenCV keypoints: ``cv2.KeyPoint.convert`` (one C++ pass), or a list pass where
    a build lacks it."""
    if not kp:
        return np.zeros((0, 2), np.float32)
    convert = getattr(cv2.KeyPoint, "convert", None)
    if convert is not None:
        return np.asarray(convert(kp), np.float32).reshape(-1, 2)
    return np.array([k.pt for k in kp], np.float32).reshape(-1, 2)


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances ``(n1, n2)`` between the rows of two float32 descriptor arrays: one matrix
    product, then in place on its result, ``max(-2 a.b + |a|^2 + |b|^2, 0)`` (a temporary array per operation took
    3x as long at 3000 x 3000). SIFT descriptors are integers (OpenCV rounds them) with squared norms about 512^2,
    so every value is an integer below 2^24, exact in float32 in any order of operations."""
    sq = a @ b.T
    sq *= -2.0
    sq += (a * a).sum(axis=1)[:, None]
    sq += (b * b).sum(axis=1)
    return np.maximum(sq, 0.0, out=sq)


KNN_BLOCK_ROWS = 512  # knn_l2's rows per block: 512 x 3000 float32 distances, 6 MB


def knn_l2(d1: np.ndarray, d2: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact Euclidean ``k`` nearest neighbours ``(idx, dist)`` ``(n1, k)`` of each row of ``d1`` among the rows of
    ``d2``, nearest first, ties to the lower index; -1 / inf where ``d2`` has fewer than ``k`` rows.

    :func:`squared_distances` per block of rows, exact on SIFT's integer descriptors: the neighbours and distances
    are OpenCV's brute-force matcher's (tests/bodyslam/vision/test_matching.py), which with its lists of matches
    takes ~4x as long (800 keypoints a frame: 2.1 ms per pair against 8.8, one thread). Other descriptors get the
    same neighbours up to float32 rounding."""
    a, b = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
    n1, n2 = len(a), len(b)
    idx = np.full((n1, k), -1, np.int64)
    dist = np.full((n1, k), np.inf)
    k_ = min(k, n2)
    if n1 == 0 or k_ == 0:
        return idx, dist
    for r0 in range(0, n1, KNN_BLOCK_ROWS):
        blk = a[r0:r0 + KNN_BLOCK_ROWS]
        rows = np.arange(len(blk))
        sq = squared_distances(blk, b)
        for j in range(k_):  # k is small (4): k arg-min passes beat a partition; argmin takes the lowest index
            c = sq.argmin(axis=1)
            idx[r0 + rows, j] = c
            dist[r0 + rows, j] = np.sqrt(sq[rows, c])
            sq[rows, c] = np.inf
    return idx, dist


def rotation_ransac(r1: np.ndarray, r2: np.ndarray, threshold_rad: float, valid: np.ndarray | None = None,
                    n_hypotheses: int = ROTATION_HYPOTHESES) -> tuple[np.ndarray | None, np.ndarray]:
    """The pure rotation ``R`` (``r2 ~= R r1``) that the most matched unit rays ``r1``, ``r2`` (n, 3) follow to
    within ``threshold_rad``, and those rays (``(R, inliers (n,) bool)``; ``(None, all False)`` with fewer than 3
    ``valid`` rays): rotations of random pairs of matches (Kabsch, ``n_hypotheses``, a fixed seed so that a pair
    always verifies alike), the best refitted on its inliers. The model of a pair without parallax, where the
    essential matrix is undefined."""
    r1 = np.asarray(r1, float)
    r2 = np.asarray(r2, float)
    n = len(r1)
    use = np.ones(n, bool) if valid is None else np.asarray(valid, bool).copy()
    inliers = np.zeros(n, bool)
    idx = np.nonzero(use)[0]
    if len(idx) < 3:
        return None, inliers
    rng = np.random.default_rng(0)
    pick = rng.integers(0, len(idx), size=(n_hypotheses, 2))
    pick = pick[pick[:, 0] != pick[:, 1]]
    a, b = r1[idx[pick]], r2[idx[pick]]  # (k, 2, 3)
    Rs = _kabsch(np.einsum("kpi,kpj->kij", a, b))
    cos_thr = math.cos(threshold_rad)
    votes = (np.einsum("kij,nj,ni->kn", Rs, r1[idx], r2[idx]) > cos_thr).sum(axis=1)
    best = int(np.argmax(votes)) if len(votes) else None
    if best is None:
        return None, inliers
    R = Rs[best]
    for _ in range(2):  # refit on the inliers, then take the rays that rotation keeps
        ok = use & (np.einsum("ij,nj,ni->n", R, r1, r2) > cos_thr)
        if ok.sum() < 3:
            return None, inliers
        R = _kabsch(np.einsum("pi,pj->ij", r1[ok], r2[ok])[None])[0]
    inliers = use & (np.einsum("ij,nj,ni->n", R, r1, r2) > cos_thr)
    return R, inliers


def _kabsch(H: np.ndarray) -> np.ndarray:
    """Rotations ``R`` (k, 3, 3) with ``b ~= R a`` in the least-squares sense for rays ``a`` and ``b``, from their
    ``H = sum a b^T`` (k, 3, 3): Kabsch's SVD, a reflection turned into a rotation."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.transpose(Vt, (0, 2, 1)) @ np.transpose(U, (0, 2, 1))))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    return np.transpose(Vt, (0, 2, 1)) @ D @ np.transpose(U, (0, 2, 1))


def essential_ransac(r1: np.ndarray, r2: np.ndarray, threshold_rad: float, valid: np.ndarray | None = None):
    """OpenCV's USAC essential matrix of matched unit rays ``r1``, ``r2`` (n, 3), on the normalised plane of the
    rays in front of both cameras (z > 0.05) and ``valid``. Returns ``(E, x1, x2, used, inliers)``: ``E`` None
    when fewer than 8 rays are used or none is found; ``x1``, ``x2`` the used rays' normalised coordinates;
    ``used`` and ``inliers`` (n,) bool. The matcher's check and the tube fit's start
    (:func:`bodyslam.vision.motion.essential_start`) both call it."""
    used = (r1[:, 2] > 0.05) & (r2[:, 2] > 0.05)
    if valid is not None:
        used &= valid
    inliers = np.zeros(len(r1), bool)
    if used.sum() < 8:
        return None, None, None, used, inliers
    x1 = (r1[used, :2] / r1[used, 2:]).astype(np.float64)
    x2 = (r2[used, :2] / r2[used, 2:]).astype(np.float64)
    # threshold on the normalised plane ~ angle; rays far off-axis are stretched by 1/cos^2, so use a median
    E, inl = cv2.findEssentialMat(x1, x2, focal=1.0, pp=(0.0, 0.0), method=cv2.USAC_DEFAULT, prob=0.999,
                                  threshold=float(threshold_rad), maxIters=300)
    if E is None or inl is None:
        return None, x1, x2, used, inliers
    inliers[np.nonzero(used)[0]] = inl.ravel() > 0
    return E, x1, x2, used, inliers

"""Visual motion over a whole sequence (streamed, both cores) and dead reckoning (dissertation Eq. 3.16-3.18).

:func:`sequence_motion` reads a sequence directory frame by frame and estimates the motion of every consecutive
pair. Work is split into contiguous chunks of frames processed in parallel worker processes; each frame's
features are computed once per chunk and only the previous frame's features are kept, so memory does not grow
with the exam's length. Rows come back in frame order.

:func:`dead_reckon` accumulates per-step motion into poses ``T_w_c``. The world frame of a dead-reckoned
trajectory is the first frame's camera frame. Composition (written correctly): ``R_w_k = R_w_(k-1) R_(k-1)_k`` and
``p_w_k = p_w_(k-1) + R_w_(k-1) t_(k-1)_k``. The dissertation's Eq. 3.17, ``R = R R_t R^-1``, is a similarity
transform of the previous orientation, not an accumulation: with it the orientation never changes when the step
rotation commutes with it, so it is not used. The thesis estimator gives no translation direction, so its step
is ``d`` along the first frame's optical axis and its rotation ``R_swing(pitch, yaw) R_z(roll)`` (the convention
of :mod:`bodyslam.geometry`, which Eq. 3.18's matrix approximates for small angles). A step with no estimate
(``status != ok``: facing the wall, too few matches) contributes no motion -- a capsule facing the wall is mostly
stopped against it -- and is counted in the summary, never hidden.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel, camera_from_dict
from bodyslam.errors import ConfigError, InputError
from bodyslam.io import frame_name, read_image, read_meta
from bodyslam.matching import FrameFeatures, Matcher, Matches, detect_fov_mask
from bodyslam.motion import ESTIMATORS, StepMotion, estimate_thesis, estimate_tube, motion_from_transform
from bodyslam.parallel import imap_tasks
from bodyslam.unroll import Unroller

log = logging.getLogger(__name__)

__all__ = ["MotionSettings", "sequence_motion", "estimate_pair", "estimate_step", "classify_work_px", "find_gaps", "split_motion", "dead_reckon", "MOTION_COLUMNS", "motion_row", "motion_rows"]

MOTION_COLUMNS = ["frame", "t", "distance_m", "roll_rad", "pitch_rad", "yaw_rad", "tilt_rad", "n_matches", "status",
                  # beyond SPEC's minimum: the full step (translation in the first frame's camera axes, rotation
                  # vector of R_c1_c2) and its 1-sigma uncertainties, so fusion can run from the file alone
                  "tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad", "sigma_distance_m", "sigma_rotation_rad"]


@dataclass(frozen=True)
class MotionSettings:
    match_mode: str = "sift"
    estimator: str = "tube"
    unroll_mode: str = "exact"  # for the thesis estimator: "exact" angles or the linear Eq. 3.11 ("thesis")
    min_matches: int = 20  # a 10-parameter fit on fewer verified matches fails on big jumps (measured)
    mask: str | None = None  # valid field of view: None = the camera's image circle, "auto" = detected from the
    #                          frames (black border, burned-in text), or a PNG path (non-zero = valid)
    classify: bool = True  # FT/FL per frame (kernel SVM); steps touching an FL frame get status no_lumen
    model: str | None = None  # classifier model file (default: the shipped one)
    classify_px: int | None = None  # SRM working size for classification; None: 64 px in fast mode, else 96
    bridge_gaps: int = 15  # runs of up to this many steps without an estimate are bridged by matching their
    #                        end frames directly (0: off); see README "gap bridging"

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ConfigError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")


@dataclass(frozen=True)
class Sequence:
    """What the pipeline may read of a sequence directory: frames, timestamps, calibration, tube radius."""

    path: Path
    camera: CameraModel
    n_frames: int
    frame_rate_hz: float
    radius_m: float
    frames_dir: Path
    camera_name: str = "front"
    T_body_cam: tuple[Rotation, np.ndarray] | None = None  # extrinsics of a non-front camera (body = front)

    @classmethod
    def open(cls, seq_dir: str | os.PathLike, radius_m: float | None = None, camera: str = "front") -> "Sequence":
        seq = Path(seq_dir)
        meta = read_meta(seq)
        r = radius_m if radius_m is not None else meta.get("tube_radius_m")
        if r is None:
            raise InputError(f"{seq}/meta.json: no tube_radius_m; give the lumen radius (--radius-m)")
        extr = None
        if camera == "front":
            cam = camera_from_dict(meta["camera"])
            frames_dir = seq / meta.get("frames", {}).get("dir", "frames")
        elif camera == "rear":
            rear = meta.get("rear_camera")
            if not isinstance(rear, dict):
                raise InputError(f"{seq}/meta.json: no rear_camera (a single-camera capsule)")
            try:
                cam = camera_from_dict(rear["camera"])
                frames_dir = seq / rear.get("frames", {}).get("dir", "frames_rear")
                T = rear["T_front_rear"]
                extr = (Rotation.from_quat(T["q_xyzw"]), np.asarray(T["t_m"], float).reshape(3))
            except (KeyError, TypeError, ValueError) as exc:
                raise InputError(f"{seq}/meta.json: malformed rear_camera ({exc})") from None
        else:
            raise ConfigError(f"camera must be 'front' or 'rear', got {camera!r}")
        if not frames_dir.is_dir():
            raise InputError(f"{frames_dir}: frames directory not found")
        return cls(seq, cam, int(meta["n_frames"]), float(meta["frame_rate_hz"]), float(r), frames_dir, camera,
                   extr)

    def to_body(self, s: StepMotion) -> StepMotion:
        """A step measured by this camera, as the motion of the capsule body (front camera) frame."""
        if self.T_body_cam is None or not s.ok or s.R_c1_c2 is None:
            return s
        R_bc, t_bc = self.T_body_cam
        R = R_bc * Rotation.from_matrix(s.R_c1_c2) * R_bc.inv()
        t = R_bc.apply(s.t_c1_c2_m) + t_bc - R.apply(t_bc)
        return motion_from_transform(R, t, s.n_matches)

    def frame(self, k: int) -> np.ndarray:
        img = read_image(self.frames_dir / frame_name(k))
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(f"{self.frames_dir / frame_name(k)}: size {img.shape[1]}x{img.shape[0]} is not the "
                             f"camera's {self.camera.width}x{self.camera.height}")
        return img

    def stamp(self, k: int) -> float:
        return k / self.frame_rate_hz


def estimate_step(settings, matches, camera, unroller, radius_m) -> StepMotion:
    """The settings' estimator (``estimator``, ``min_matches``: MotionSettings or BatchSettings) on one pair."""
    if settings.estimator == "tube":
        return estimate_tube(matches, camera, radius_m, min_matches=settings.min_matches)
    return estimate_thesis(matches, unroller, radius_m, min_matches=settings.min_matches)


def estimate_pair(matcher: Matcher, f1: FrameFeatures, f2: FrameFeatures,
                  estimate: Callable[[Matches], StepMotion]) -> StepMotion:
    """Match two frames and estimate the step; in fast mode a tracked pair (Lucas-Kanade) whose estimate
    fails (too few matches, uncertain) is matched again by descriptors, so tracking never costs coverage."""
    m = matcher.match_features(f1, f2)
    s = estimate(m)
    if not s.ok and m.method == "lk":
        s = estimate(matcher.match_features(f1, f2, "descriptors"))
    return s


def _chunk_motion(args) -> list[tuple[int, StepMotion]]:
    """Steps ``a+1 .. b`` (pairs (k-1, k)) of one chunk, features computed once per frame."""
    seq_dir, radius_m, settings, a, b, camera, mask = args
    import cv2

    cv2.setNumThreads(1)  # one worker per core
    seq = Sequence.open(seq_dir, radius_m, camera)
    matcher = Matcher(seq.camera, settings.match_mode, mask=mask)
    unroller = Unroller(seq.camera, mode=settings.unroll_mode)
    fov = seq.camera.fov_mask() if mask is None else mask
    classifier = None
    if settings.classify:
        from bodyslam.classify import TunnelClassifier

        classifier = (TunnelClassifier.load(settings.model) if settings.model else TunnelClassifier.default())
    out = []
    prev = prev_class = None
    for k in range(a, b + 1):
        try:
            img = seq.frame(k)
            feats = matcher.features(img)
            cls = _frame_class(classifier, img, fov, classify_work_px(settings))
        except InputError as exc:
            log.warning("%s", exc)
            feats = cls = None
        if k > a:
            if prev is None or feats is None:
                out.append((k, StepMotion(status="bad_frame")))
            elif prev_class != "FT" or cls != "FT":
                # the geometric model needs the lumen in view in both frames (dissertation Sec. 3.2.1)
                out.append((k, StepMotion(status="no_lumen")))
            else:
                s = estimate_pair(matcher, prev, feats,
                                  lambda m: estimate_step(settings, m, seq.camera, unroller, seq.radius_m))
                out.append((k, seq.to_body(s)))
        prev, prev_class = feats, cls
    return out


def classify_work_px(settings) -> int:
    """SRM working size of the classifier: 48 px in fast mode (2.5 ms instead of 9.7 per frame at 96 px; the
    same accuracy on the classifier benchmark's unseen seeds 101-104 and an exam, 400 frames each: 0.988
    against 0.987 at 96 and 0.985 at 64, see README), 96 px otherwise, unless the settings say."""
    if settings.classify_px:
        return int(settings.classify_px)
    return 48 if settings.match_mode == "fast" else 96


def _frame_class(classifier, img: np.ndarray, fov: np.ndarray, work_px: int = 96) -> str:
    """FT or FL by the kernel SVM (FT for every frame when classification is off); dark/saturated frames: FL."""
    if classifier is None:
        return "FT"
    from bodyslam.classify import frame_features, frame_status

    if frame_status(img, fov) != "ok":
        return "FL"
    return str(classifier.predict(frame_features(img, fov, work_px=work_px)[None])[0])


def sequence_motion(seq_dir: str | os.PathLike, settings: MotionSettings = MotionSettings(),
                    jobs: int | None = None, radius_m: float | None = None, chunk_frames: int = 50,
                    progress: Callable[[int, int], None] | None = None, camera: str = "front") -> list[StepMotion]:
    """Per-step motion of every consecutive pair of a sequence (``n_frames - 1`` steps, in order).

    ``camera="rear"`` uses a dual-camera capsule's rear frames; its steps are reported as the motion of the
    capsule body (front camera) frame, through the rear camera's extrinsics in meta.json.
    """
    seq = Sequence.open(seq_dir, radius_m, camera)
    n = seq.n_frames
    if n < 2:
        raise InputError(f"{seq_dir}: need at least 2 frames, meta.json says {n}")
    bounds = list(range(0, n - 1, chunk_frames)) + [n - 1]
    mask = resolve_mask(seq, settings.mask)
    tasks = [(str(seq.path), seq.radius_m, settings, bounds[i], bounds[i + 1], camera, mask)
             for i in range(len(bounds) - 1)]
    steps: list[StepMotion] = []
    for chunk in imap_tasks(_chunk_motion, tasks, jobs):
        steps.extend(s for _, s in chunk)
        if progress:
            progress(len(steps), n - 1)
    if settings.bridge_gaps and settings.estimator == "tube":
        gaps = find_gaps(steps, settings.bridge_gaps)
        if gaps:
            btasks = [(str(seq.path), seq.radius_m, settings, a, b, camera, mask) for a, b in gaps]
            for (a, b), T in zip(gaps, imap_tasks(_bridge_task, btasks, jobs)):
                if T is not None:
                    for k, s in zip(range(a + 1, b + 1), split_motion(T, b - a)):
                        steps[k - 1] = s
    return steps


def find_gaps(steps: list[StepMotion], max_len: int) -> list[tuple[int, int]]:
    """Runs of steps without an estimate, as frame pairs ``(a, b)``: steps ``a+1..b`` have none, steps ``a``
    and ``b+1`` have one (so frames ``a`` and ``b`` face the tunnel and are readable); at most ``max_len``."""
    out, k, n = [], 0, len(steps)
    while k < n:
        if steps[k].ok:
            k += 1
            continue
        j = k
        while j < n and not steps[j].ok:
            j += 1
        # steps k..j-1 (0-based) are the moves into frames k+1..j: the gap spans frames a = k .. b = j
        if k > 0 and j < n and j - k <= max_len and all(s.status != "bad_frame" for s in steps[k:j]):
            out.append((k, j))
        k = j
    return out


def _bridge_task(args) -> StepMotion | None:
    """The motion from frame ``a`` straight to frame ``b`` (a gap's ends), or None."""
    seq_dir, radius_m, settings, a, b, camera, mask = args
    import cv2

    cv2.setNumThreads(1)
    seq = Sequence.open(seq_dir, radius_m, camera)
    matcher = Matcher(seq.camera, settings.match_mode, mask=mask)
    try:
        fa, fb = matcher.features(seq.frame(a)), matcher.features(seq.frame(b))
    except InputError:
        return None
    s = estimate_pair(matcher, fa, fb, lambda m: estimate_tube(m, seq.camera, seq.radius_m,
                                                                min_matches=settings.min_matches))
    return seq.to_body(s) if s.ok else None


def split_motion(total: StepMotion, n: int) -> list[StepMotion]:
    """``n`` equal steps whose composition is ``total`` (constant twist: rotation ``R^(1/n)``, translation on
    the screw), each with status ``bridged`` and a 1-sigma of ``total``'s over sqrt(n) (independent steps)."""
    R = Rotation.from_matrix(total.R_c1_c2)
    rv = R.as_rotvec() / n
    dR = Rotation.from_rotvec(rv)
    # find t_s with sum_{i<n} dR^i t_s = t_total
    A = np.zeros((3, 3))
    Ri = np.eye(3)
    for _ in range(n):
        A += Ri
        Ri = Ri @ dR.as_matrix()
    t_s = np.linalg.solve(A, np.asarray(total.t_c1_c2_m, float))
    out = []
    for _ in range(n):
        s = motion_from_transform(dR, t_s, total.n_matches)
        out.append(replace(s, status="bridged", sigma_distance_m=total.sigma_distance_m / math.sqrt(n),
                           sigma_rotation_rad=total.sigma_rotation_rad / math.sqrt(n)))
    return out


def resolve_mask(seq: Sequence, mask: str | None, n_sample: int = 30) -> np.ndarray | None:
    """The valid field-of-view mask a sequence's matcher uses (see :attr:`MotionSettings.mask`)."""
    if mask is None:
        return None
    if mask == "auto":
        ks = np.unique(np.linspace(0, seq.n_frames - 1, min(n_sample, seq.n_frames)).astype(int))
        frames = []
        for k in ks:
            try:
                frames.append(seq.frame(int(k)))
            except InputError as exc:
                log.warning("%s (skipped for mask detection)", exc)
        m = detect_fov_mask(frames)
        log.info("detected field of view: %d of %d pixels", int(m.sum()), m.size)
        return m
    img = read_image(mask, unchanged=True)
    if img.ndim == 3:
        img = img.max(axis=2)
    if img.shape != (seq.camera.height, seq.camera.width):
        raise InputError(f"{mask}: mask is {img.shape[1]}x{img.shape[0]}, frames are "
                         f"{seq.camera.width}x{seq.camera.height}")
    return img > 0


def motion_row(frame: int, t_s: float, s: StepMotion) -> list:
    """One ``motion.csv`` row (``MOTION_COLUMNS``) for the step into ``frame`` (plain Python numbers)."""
    t = s.t_c1_c2_m if s.t_c1_c2_m is not None else np.full(3, np.nan)
    rv = Rotation.from_matrix(s.R_c1_c2).as_rotvec() if s.R_c1_c2 is not None else np.full(3, np.nan)
    return [int(frame), float(t_s), float(s.distance_m), float(s.roll_rad), float(s.pitch_rad), float(s.yaw_rad),
            float(s.tilt_rad), int(s.n_matches), s.status, *map(float, t), *map(float, rv),
            float(s.sigma_distance_m), float(s.sigma_rotation_rad)]


def motion_rows(steps: list[StepMotion], frame_rate_hz: float) -> list[list]:
    """Rows of ``motion.csv`` (SPEC.md): step ``k`` is the motion from frame ``k-1`` to frame ``k``."""
    return [motion_row(k, k / frame_rate_hz, s) for k, s in enumerate(steps, start=1)]


def _step_transform(s: StepMotion) -> tuple[Rotation, np.ndarray]:
    if not (s.ok or s.has_estimate):
        return Rotation.identity(), np.zeros(3)
    if s.R_c1_c2 is not None and s.t_c1_c2_m is not None:
        return Rotation.from_matrix(s.R_c1_c2), np.asarray(s.t_c1_c2_m, float)
    pitch = 0.0 if np.isnan(s.pitch_rad) else s.pitch_rad
    yaw = 0.0 if np.isnan(s.yaw_rad) else s.yaw_rad
    R = Rotation.from_rotvec([pitch, yaw, 0.0]) * Rotation.from_rotvec([0.0, 0.0, s.roll_rad])
    return R, np.array([0.0, 0.0, s.distance_m])


def dead_reckon(steps: list[StepMotion]) -> tuple[np.ndarray, Rotation]:
    """Poses ``T_w_c`` of frames ``0..n`` from ``n`` steps (module docstring); world = first camera frame."""
    pos = np.zeros((len(steps) + 1, 3))
    quats = np.zeros((len(steps) + 1, 4))
    R = Rotation.identity()
    quats[0] = R.as_quat()
    for k, s in enumerate(steps, start=1):
        dR, dt = _step_transform(s)
        pos[k] = pos[k - 1] + R.apply(dt)
        R = R * dR
        quats[k] = R.as_quat()
    return pos, Rotation.from_quat(quats)

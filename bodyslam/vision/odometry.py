"""Visual odometry: the one engine that turns frames into steps (dissertation Sec. 3.2), for every command.

:class:`VisualOdometry` holds what a worker needs for one camera and :class:`MotionSettings` -- the matcher
(:mod:`bodyslam.vision.matching`), the FT/FL classifier (:mod:`bodyslam.vision.classify`), the field-of-view mask, the
unroller and the estimator (:mod:`bodyslam.vision.motion`) -- and :meth:`VisualOdometry.run` turns a range of frames
from a :class:`bodyslam.frames.FrameSource` into per-frame records (class, status) and steps
(:class:`bodyslam.steps.StepMotion`). The classifier gate, masks, unroll mode, estimator and the fast mode's
fall-back live here and nowhere else. ``bodyslam motion`` / ``track`` (:func:`sequence_motion`), ``bodyslam
batch`` (:mod:`bodyslam.exam.batch`, resumable chunks) and ``testbed evaluate`` all call it, so the same frames and
settings give the same ``motion.csv`` whichever command ran (tested).

Chunks: positions ``a .. b`` give the steps into ``a+1 .. b`` (frame ``a`` belongs to the previous chunk unless
``a == 0``); features are computed once per frame and only the previous frame's are kept, so memory does not
grow with the exam. Results do not depend on the chunking or the number of workers (tested).

Gap bridging (second pass, :func:`find_gaps`, :meth:`VisualOdometry.bridge`, :func:`split_motion`): a run of up
to ``bridge_gaps`` steps without an estimate *between* two estimated steps is measured end to end by matching
the frame before the run with the frame after it, and split into equal shares (status ``bridged``). Runs at the
start or end of an exam have only one estimated neighbour: they are not bridged, and the path-travelled rule
(:func:`bodyslam.vision.tracking.path_travelled`) treats both ends alike.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel, camera_from_dict
from bodyslam.choices import CAMERAS, ESTIMATORS, MATCH_MODES, UNROLL_MODES
from bodyslam.errors import ConfigError, InputError
from bodyslam.frames import Frame, FrameSource
from bodyslam.io import read_image
from bodyslam.meta import read_meta
from bodyslam.steps import (LOST_TO_MOTION, MEASURED, StepMotion, StepStatus, lost_step_floor_m, motion_from_transform,
                            rotation_step)

log = logging.getLogger(__name__)

__all__ = ["MotionSettings", "VisualOdometry", "ChunkResult", "Sequence", "sequence_motion", "with_lumen_uncertainty",
           "pair_motions", "consistency_pairs", "consistency_diagnostic", "step_consistency", "find_gaps",
           "split_motion", "resolve_mask", "fov_from_frames", "write_mask", "classify_work_px", "bridge_gaps",
           "bridged_shares", "bridge_inside",
           "WALL_SIGMA_FACTOR", "WALL_STEPS", "BESIDE_WALL_RADII", "ACROSS_TILT_RAD", "BESIDE_WALL_SIGMA_RADII",
           "BESIDE_WALL_ROTATION_FACTOR", "BESIDE_WALL_HELD_AXIS",
           "LOST_MIN_KEYPOINTS_FRAC", "LOST_MAX_MATCHES", "BRIDGE_MIN_LOST_SHARE"]


WALL_STEPS = ("estimate", "drop")
# factor on the 1-sigma (the fit's and the lumen shape's share; not the radius's, which the fusion's scale state
# carries) of a step estimated although a frame of the pair faces the wall (status ``wall``): such steps err more
# than that 1-sigma says. Chosen on the realistic scenario's tuning seeds 503-509 (201 wall steps, 944 ok) to give
# wall steps the ok steps' coverage (0.688 / 0.981 within 1 / 2 sigma): 0.517 / 0.896 at 1, 0.632 / 0.945 at 1.5,
# 0.687 / 0.950 at 1.8, 0.706 / 0.955 at 2 (docs/RESULTS.md)
WALL_SIGMA_FACTOR = 1.8
# A tube fit whose cylinder no capsule could be in, or that runs across a view of the lumen ahead, has fitted the
# cylinder beside or across a fold. Either: the camera more than BESIDE_WALL_RADII radii from the axis (a capsule,
# 5.5 mm in radius, in a cylindrical lumen of 0.8-1.6 cm sits at most 0.31-0.66 radii from it, and the ratio does
# not depend on the radius the fit assumes); or, between two frames classified facing the tunnel, the axis more
# than ACROSS_TILT_RAD off the view. In a lumen that is not a cylinder such fits explain the matches with a fraction
# of the step, often ~0, at a 1-sigma of hundredths of a millimetre (docs/RESULTS.md, "Fits beside the wall",
# session 36): the lumen-shape share of the 1-sigma (``with_lumen_uncertainty``) scales with the estimated length
# and vanishes with it. Such a step keeps its motion and gets BESIDE_WALL_SIGMA_RADII lumen radii added in
# quadrature to its fit's own 1-sigma. Chosen on realistic tuning seeds 560-561 at three textures (fast mode, 390
# estimated steps, 344 between frames facing the tunnel; each run's scale taken out): the 33 moving steps fitted
# shorter than 0.35 of the true one all lie beyond 0.8 radii (29 of them between FT frames, 22 of those tilted
# more than 45 deg); the 111 steps either rule flags were inside their 1 / 2 sigma 0.25 / 0.39, with 0.06 radii
# added 0.47 / 0.84 (the others: 0.44 / 0.69), and the FT-FT steps in all 0.401 / 0.622 -> 0.465 / 0.759 (one
# rule alone: 0.433 / 0.721 by the distance, 0.448 / 0.733 by the tilt; 0.04 radii too few, 0.34 / 0.58 on
# the tilted ones, 0.10 too many, 0.69 / 0.99). Their rotation errs more too (mean 3.5 deg against the others'
# 1.0; inside the 68% radius 0.35 against 0.63): its 1-sigma is multiplied by BESIDE_WALL_ROTATION_FACTOR (1.5:
# 0.50, 2: 0.62, 2.5: 0.69, 3: 0.81), to the others' coverage as WALL_SIGMA_FACTOR does for wall steps
BESIDE_WALL_RADII = 0.8
ACROSS_TILT_RAD = math.radians(45.0)
BESIDE_WALL_SIGMA_RADII = 0.06
BESIDE_WALL_ROTATION_FACTOR = 2.0
# ... and where it is the camera's place that flags the fit (no capsule can be there), its motion is fitted again
# with the tube's axis held on the optical axis and the camera on it (the six motion parameters only;
# bodyslam.vision.motion.fit_tube's hold_axis). A capsule in a folded or collapsed lumen is not beside the wall: on
# slow realistic tuning renders 587-594 the capsule of a step fitted beside the wall lay 0.07 radii from the centre
# line at the median (0.11 at the 90th percentile) with its view 2.7 deg off the gut (6.0), as for the other steps;
# the free fit reads such a step at ~0 (median 0.0000 cm where 0.035 cm was true). Held, the 1,056 steps fitted
# beside the wall there read their length with a correlation of 0.57-0.89 a run to the truth (0.25-0.72 free), ~1.25x
# long once the exam's lumen scale is applied (their lumen is narrower than the exam's), and their rotation errs less
# (roll / tilt 0.163 / 1.166 -> 0.070 / 0.432 deg mean; the other steps' 0.044 / 0.185). They keep their widened
# 1-sigma and their flag: the path's speed model still reads them weakly (docs/RESULTS.md, "Fits beside the wall
# held on the axis"). A fit flagged only by its axis across the view is not fitted again: on ideal tubes those are
# real turns of ~30 deg a step (thesis tuning seeds 591 and 593, the ideal `exam` seed 599), which the free fit gets
# right and the held one 4 deg and a quarter of the length wrong. False: the free fit's motion, as before.
BESIDE_WALL_HELD_AXIS = True
# A fit beside the wall (above) whose verified matches a pure rotation explains to within this median residual
# (pixels) is a capsule at rest: without parallax its translation is unobservable and the fit slides to the wall
# (the testbed's slow exams hold many true rests: 12% of the steps, half of them fitted beside the wall). It is
# reported at rest (distance 0, REST_SIGMA_RADII lumen radii of 1-sigma, the pure rotation) and not flagged.
# Measured on 500 estimated steps of bench_batch.py's 10,000-frame `realistic_exam` render (tuning; fast mode's
# matches): median residual of the steps at rest 0.37 px (10th percentile 0.16), of steps of 0.1-0.2 mm 1.18 (0.64);
# under 0.4 px: 51% of the steps at rest, 0.5% of those of 0.1 mm or more; of the 164 fitted beside the wall, 16,
# whose true lengths were at most 0.13 mm (mean 0.03). 0: not tried (the rule before session 54)
REST_PARALLAX_PX = 0.4
REST_SIGMA_RADII = 0.01
# A step no matching could fit between two frames that each have at least this share of the matcher's keypoint
# budget (``max_features``: 3000 in sift/asift mode, 800 in fast mode) is lost to motion (status ``lost``): the
# view changed too much to match. Fewer keypoints: a blurred, turbid or featureless frame, which may be a capsule
# at rest (status stays ``too_few_matches``). Measured with the sift matcher: five real PillCam COLON 2 frames
# (576 px) have 870-2330 keypoints, the same blurred by a 5 px Gaussian 80-180 and by 15 px 9-19; the realistic
# testbed's frames of failed steps 2270 at the 5th percentile (tuning seed 504)
LOST_MIN_KEYPOINTS_FRAC = 0.25
# ... and when its verified matches are no more than two frames with nothing in common give: 50 pairs of frames of
# two different realistic runs (tuning seeds 504, 505) verify at most 9 (95th percentile 8-9) in fast and in sift
# mode. More show that the frames overlap, and the fit failed for want of matches (a weak matcher on real texture:
# two pairs of four real PillCam frames verify 15 and 19 in fast mode, where asift fits one of them as ~0 mm):
# status stays ``too_few_matches``. On the testbed's clips 81% of the lost steps have at most 10
LOST_MAX_MATCHES = 10
# A gap's end-to-end motion is not taken when it is shorter than this share of its steps lost to motion at their
# least length each (bodyslam.steps.lost_step_floor_m): the steps say the capsule moved far, the bridge that it
# hardly moved. Seen on thesis tuning seed 510: ten steps of 1.4-3.1 cm (six ``lost``, four ``rotation``)
# bridged as 0.62 cm in all with a 1-sigma of 0.002 cm (the far tunnel of the first frame is the near wall of the
# last: 313 verified matches, a wrong minimum of the tube fit), the path 25% short at 13 sigma. Half: a lost step
# may be shorter than the floor (18% of the steps of 0.3-0.4 cm are lost), or go back part of the way
BRIDGE_MIN_LOST_SHARE = 0.5


@dataclass(frozen=True)
class MotionSettings:
    match_mode: str = "sift"
    estimator: str = "tube"
    unroll_mode: str = "exact"  # for the thesis estimator: "exact" angles or the linear Eq. 3.11 ("thesis")
    min_matches: int = 20  # a 10-parameter fit on fewer verified matches fails on big jumps (measured)
    mask: str | None = None  # valid field of view: None or "auto" = detected from the frames (field stop, burned-in
    #                          text; the image circle where they agree), "circle" = the camera's image circle, or a
    #                          PNG path (non-zero = valid)
    classify: bool = True  # FT/FL per frame (kernel SVM); a step touching an FL frame is "wall" (below)
    wall_steps: str = "estimate"  # a step touching an FL frame: "estimate" it by the tube fit, status wall, its
    #                               1-sigma times WALL_SIGMA_FACTOR; "drop" it (status no_lumen: the dissertation,
    #                               and always with the thesis estimator, whose unrolling needs the lumen in view)
    model: str | None = None  # classifier model file (default: the shipped one)
    classify_px: int | None = None  # SRM working size for classification; None: classify_work_px (the model's)
    bridge_gaps: int = 15  # runs of up to this many steps without an estimate are bridged by matching their
    #                        end frames directly (0: off); see README "gap bridging"
    rotation_steps: bool = True  # a step the tube fit fails on (too few matches, uncertain) gets its rotation by
    #                              guided matching when it can (status rotation; bodyslam.vision.guided)
    rescue: bool = True  # fast mode: where tracking and the smaller detections fail, SIFT on the full frame
    #                      (bodyslam.vision.matching, "rescue"); off: such a step fails as before session 24
    lumen_scale: bool = True  # tube estimator: the exam's steps rescaled by the lumen's scale seen in a sample of
    #                           them (bodyslam.vision.lumen_scale); off: the radius prior's scale, as to session 37
    #                           (and no scale chain either)
    scale_chain: bool = True  # tube estimator, radius a prior, lumen scale on: each step's scale tied to its
    #                           neighbours' by the depths of the points they share (bodyslam.vision.scale_chain)

    def __post_init__(self) -> None:
        for name, allowed in (("match_mode", MATCH_MODES), ("estimator", ESTIMATORS), ("unroll_mode", UNROLL_MODES)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if self.min_matches < 5:
            raise ConfigError(f"min_matches must be at least 5, got {self.min_matches}")
        if self.bridge_gaps < 0:
            raise ConfigError(f"bridge_gaps must be >= 0, got {self.bridge_gaps}")
        if self.wall_steps not in WALL_STEPS:
            raise ConfigError(f"wall_steps must be one of {', '.join(WALL_STEPS)}, got {self.wall_steps!r}")


def classify_work_px(settings: MotionSettings, model=None) -> int:
    """SRM working size of the classifier: the settings' if they say, else the size ``model`` (a
    :class:`~bodyslam.vision.classify.TunnelClassifier`) was trained at (its features are measured at that size),
    else 96 px (64 px in fast mode) for a model that does not record it. Models trained by
    ``benchmarks/bench_classifier.py`` record the size chosen on held-out tuning seeds; the size matters: a model
    used at another size than its training's mis-calls realistic frames."""
    if settings.classify_px:
        return int(settings.classify_px)
    if model is not None and model.work_px:
        return model.work_px
    return 64 if settings.match_mode == "fast" else 96


@dataclass
class ChunkResult:
    """What :meth:`VisualOdometry.run` returns for positions ``first .. last``.

    ``frames``: ``[index, label, t_s, class, status]`` per frame the chunk owns (class ``FT``/``FL``, ``""``
    when not classified; status ``ok``, ``dark``, ``saturated``, ``unreadable``, ``bad_size``); ``steps``:
    ``(position, index, t_s, StepMotion)`` of the steps into ``first+1 .. last``; ``problems``: ``[file,
    frame, severity, reason]``; ``eof``: the position where a video ended early, else None."""

    frames: list[list]
    steps: list[tuple[int, int, float, StepMotion]]
    problems: list[list]
    eof: int | None = None
    # the points of the chunk's first step's first frame and of its last step's last frame (None where that step
    # has no fit), so whoever joins the chunks links the seams (bodyslam.vision.scale_chain)
    seam_in: object = None
    seam_out: object = None
    # with ``run(..., bridge=True)``: each gap closed inside the chunk (:func:`find_gaps`' rule), ``(a, b)`` in
    # positions, and its end-to-end motion (None where it did not match), from the features the run had made
    gap_totals: dict = field(default_factory=dict)


class VisualOdometry:
    """The frame-to-step engine (module docstring). ``T_body_cam``: ``(q_xyzw, t_m)`` of a camera that is not
    the capsule body's (a dual capsule's rear camera): its steps are reported as the body's motion."""

    def __init__(self, camera: CameraModel, settings: MotionSettings, radius_m: float,
                 mask: np.ndarray | None = None, T_body_cam: tuple | None = None):
        from bodyslam.vision.matching import Matcher
        from bodyslam.vision.unroll import Unroller

        if not (isinstance(radius_m, (int, float)) and math.isfinite(radius_m) and radius_m > 0):
            raise ConfigError(f"lumen radius must be a positive number of metres, got {radius_m!r}")
        self.camera, self.settings, self.radius_m = camera, settings, float(radius_m)
        self.matcher = Matcher(camera, settings.match_mode, mask=mask, rescue=settings.rescue)
        self.unroller = Unroller(camera, mode=settings.unroll_mode) if settings.estimator == "thesis" else None
        self.fov = camera.fov_mask() if mask is None else mask
        self.classifier = None
        if settings.classify:
            from bodyslam.vision.classify import TunnelClassifier

            self.classifier = (TunnelClassifier.load(settings.model) if settings.model
                               else TunnelClassifier.default())
        self.work_px = classify_work_px(settings, self.classifier)
        self.T_body_cam = None
        self.signatures = None  # the last estimate_pair's step points (bodyslam.vision.scale_chain.Signature x 2)
        if T_body_cam is not None:
            self.T_body_cam = (Rotation.from_quat(T_body_cam[0]), np.asarray(T_body_cam[1], float).reshape(3))

    # -- one pair ---------------------------------------------------------------------------------------------
    def _fit(self, m, estimator: str | None = None) -> tuple[StepMotion, np.ndarray | None]:
        """The step from matches by ``estimator`` (default: the settings'), and the tube fit's 10-vector where
        there was one."""
        from bodyslam.vision.motion import estimate_thesis, fit_tube

        if (estimator or self.settings.estimator) == "tube":
            return fit_tube(m, self.camera, self.radius_m, min_matches=self.settings.min_matches)
        return estimate_thesis(m, self.unroller, self.radius_m, min_matches=self.settings.min_matches), None

    def estimate_pair(self, f1, f2, estimator: str | None = None, rotation: bool = True,
                      ahead: bool = False, ring: bool = False) -> StepMotion:
        """Match two frames' features and estimate the step from the first matches of the matcher's cascade
        (:meth:`~bodyslam.vision.matching.Matcher.cascade`) the estimate succeeds on: in fast mode tracking, then
        coarse descriptors, then the full-frame rescue, then (:meth:`~bodyslam.vision.matching.Matcher.last_resort`)
        descriptors at the 0.7 scale, kept only where their fit succeeds, so the cheap tries never cost coverage. A
        step the tube fit still fails on gets its rotation by guided matching where it can (status ``rotation``,
        :mod:`bodyslam.vision.guided`; ``rotation=False`` or ``MotionSettings.rotation_steps`` off: not tried), and
        one that stays without an estimate is ``lost`` to motion when both frames are rich in features and the pair
        verified no more matches than unrelated frames give (:data:`LOST_MIN_KEYPOINTS_FRAC`,
        :data:`LOST_MAX_MATCHES`; not with ``rotation=False``: the gap bridge wants a pose or nothing).
        ``estimator``: overrides the settings' (the gap bridge wants the tube fit's full pose). A tube fit that puts
        the camera beside the wall of its own cylinder (:func:`~bodyslam.vision.motion.camera_off_axis_radii` over
        :data:`BESIDE_WALL_RADII`) or, with ``ahead`` (both frames were classified facing the tunnel), its axis more
        than :data:`ACROSS_TILT_RAD` off the view gets :data:`BESIDE_WALL_SIGMA_RADII` lumen radii in its 1-sigma
        distance and its rotation's 1-sigma times :data:`BESIDE_WALL_ROTATION_FACTOR`, and says so (``beside_wall``);
        where the camera's place flags it, its motion is first fitted again with the axis held on the optical axis
        (:data:`BESIDE_WALL_HELD_AXIS`). ``ring``: a fitted step also gets its ``ring_ratio``
        (:func:`bodyslam.vision.lumen_scale.ring_distance_ratio`, the exam's lumen scale is measured on such steps).
        The step is in the body frame (:meth:`to_body`)."""
        from bodyslam.vision.motion import axis_tilt_rad, camera_off_axis_radii

        estimator = estimator or self.settings.estimator
        for m in self.matcher.cascade(f1, f2):
            s, x = self._fit(m, estimator)
            if s.ok:
                break
        else:
            # fast mode's 0.7-scale try after its rescue, only where the rescue verified enough matches and its fit
            # failed (on fewer matches its fewer keypoints never fitted one: 0 of 243 such pairs, realistic seeds
            # 912-915 and thesis 912-913; 6 of 62 where the fit failed; session 72); where it fails, the rescue's
            # result stands
            m2 = self.matcher.last_resort(f1, f2) if s.status == StepStatus.UNCERTAIN else None
            if m2 is not None:
                s2, x2 = self._fit(m2, estimator)
                if s2.ok:
                    m, s, x = m2, s2, x2
        if ring and s.ok and x is not None:
            from bodyslam.vision.lumen_scale import ring_distance_ratio

            s = replace(s, ring_ratio=ring_distance_ratio(m.pts1_px, m.pts2_px, self.camera, self.radius_m, x))
        off_axis = s.ok and x is not None and camera_off_axis_radii(x, self.radius_m) > BESIDE_WALL_RADII
        if off_axis and estimator == "tube" and REST_PARALLAX_PX > 0:
            rest = self._rest_step(m, s)
            if rest is not None:  # no parallax: the fit slid to the wall because the capsule did not move
                s, x, off_axis = rest, None, False
        if off_axis or (s.ok and x is not None and ahead and axis_tilt_rad(x) > ACROSS_TILT_RAD):
            if off_axis and BESIDE_WALL_HELD_AXIS and estimator == "tube":
                s, x = self._held_axis_refit(m, s, x)
            s = replace(s, sigma_distance_m=math.hypot(s.sigma_distance_m, BESIDE_WALL_SIGMA_RADII * self.radius_m),
                        sigma_rotation_rad=s.sigma_rotation_rad * BESIDE_WALL_ROTATION_FACTOR, beside_wall=True)
        if (rotation and self.settings.rotation_steps and estimator == "tube"
                and s.status in (StepStatus.TOO_FEW_MATCHES, StepStatus.UNCERTAIN)):
            from bodyslam.vision.guided import estimate_rotation

            s = estimate_rotation(self.matcher, f1, f2, self.camera, self.radius_m, start=x) or s
        if (rotation and estimator == "tube" and s.status == StepStatus.TOO_FEW_MATCHES
                and s.n_matches <= LOST_MAX_MATCHES and self._textured(f1) and self._textured(f2)):
            s = StepMotion(n_matches=s.n_matches, status=StepStatus.LOST)
        self.signatures = None  # the step's points in both frames, for its scale link (bodyslam.vision.scale_chain)
        if s.ok and x is not None:
            from bodyslam.vision.scale_chain import step_signatures

            self.signatures = step_signatures(m.pts1_px, m.pts2_px, x, self.camera)
        return self.to_body(s)

    def _rest_step(self, m, s: StepMotion) -> StepMotion | None:
        """The step at rest (no translation, :data:`REST_SIGMA_RADII` lumen radii of 1-sigma distance, the pure
        rotation that best maps the verified matches' rays) where that rotation alone explains them to within
        :data:`REST_PARALLAX_PX` (median); None otherwise."""
        from bodyslam.vision.matching import rotation_ransac

        r1, v1 = self.camera.unproject(m.pts1_px)
        r2, v2 = self.camera.unproject(m.pts2_px)
        R, _ = rotation_ransac(r1, r2, self.matcher.ransac_rad, v1 & v2)
        if R is None:
            return None
        ok = v1 & v2
        resid = np.arccos(np.clip(np.einsum("ij,nj,ni->n", R, r1[ok], r2[ok]), -1.0, 1.0))
        if not float(np.median(resid)) * float(self.camera.fx) < REST_PARALLAX_PX:
            return None
        rest = motion_from_transform(Rotation.from_matrix(R.T), np.zeros(3), s.n_matches,
                                     REST_SIGMA_RADII * self.radius_m, s.sigma_rotation_rad, s.status)
        return replace(rest, ring_ratio=s.ring_ratio)

    def _held_axis_refit(self, m, s: StepMotion, x: np.ndarray) -> tuple[StepMotion, np.ndarray]:
        """A fit beside the wall fitted again with the tube's axis held on the optical axis and the camera on it
        (:data:`BESIDE_WALL_HELD_AXIS`), from its own motion and from a forward step of
        :data:`~bodyslam.vision.motion.ESSENTIAL_START_STEP` radii; the free fit where the held one fails. The
        step keeps its ring ratio (the exam's lumen scale sample, measured from the free fit as on every step)."""
        from bodyslam.vision.motion import ESSENTIAL_START_STEP, fit_tube

        forward = np.zeros(10)
        forward[0:3] = x[0:3]
        forward[5] = ESSENTIAL_START_STEP * self.radius_m
        s2, x2 = fit_tube(m, self.camera, self.radius_m, min_matches=self.settings.min_matches, hold_axis=True,
                          starts=[x, forward])
        return (replace(s2, ring_ratio=s.ring_ratio), x2) if s2.ok else (s, x)

    def _textured(self, f) -> bool:
        """Whether a frame has the keypoints to match (:data:`LOST_MIN_KEYPOINTS_FRAC` of the matcher's budget;
        detected once per frame, at the matcher's ``detect_scale``: every mode has them once its cascade failed, fast
        mode with its rescue from its last resort, detected only for the pairs the rest failed on)."""
        return len(self.matcher.keypoints(f)[0]) >= LOST_MIN_KEYPOINTS_FRAC * self.matcher.max_features

    def to_body(self, s: StepMotion) -> StepMotion:
        """A step measured by this camera, as the motion of the capsule body (front camera) frame."""
        if self.T_body_cam is None or not s.has_rotation:
            return s
        R_bc, t_bc = self.T_body_cam
        R = R_bc * Rotation.from_matrix(s.R_c1_c2) * R_bc.inv()
        if s.t_c1_c2_m is None:  # a rotation step: the body turns by the same rotation, in its own axes
            return rotation_step(R, s.n_matches, s.sigma_rotation_rad)
        t = R_bc.apply(s.t_c1_c2_m) + t_bc - R.apply(t_bc)
        return replace(motion_from_transform(R, t, s.n_matches, s.sigma_distance_m, s.sigma_rotation_rad, s.status),
                       beside_wall=s.beside_wall, ring_ratio=s.ring_ratio, scale_link=s.scale_link,
                       scale_link_sd=s.scale_link_sd, chain_factor=s.chain_factor)

    def estimate_wall(self, f1, f2, ring: bool = False) -> StepMotion:
        """A step touching a frame that faces the wall. The dissertation drops it (its unrolling needs the lumen
        in view, Sec. 3.2.1: status ``no_lumen``, as with ``wall_steps="drop"`` or the thesis estimator); the tube
        fit does not need the lumen in view, only the wall, so by default it is estimated (status ``wall``) with
        its 1-sigma times :data:`WALL_SIGMA_FACTOR`. A failed fit keeps its own reason."""
        if self.settings.wall_steps == "drop" or self.settings.estimator != "tube":
            return StepMotion.failed(StepStatus.NO_LUMEN)
        s = self.estimate_pair(f1, f2, ring=ring)
        if not s.ok:
            return s
        return replace(s, status=StepStatus.WALL, sigma_distance_m=s.sigma_distance_m * WALL_SIGMA_FACTOR,
                       sigma_rotation_rad=s.sigma_rotation_rad * WALL_SIGMA_FACTOR)

    def classify(self, img: np.ndarray) -> tuple[str, str]:
        """``(class, status)`` of a frame: FT/FL by the kernel SVM (dark or saturated frames: FL), ``""`` and
        ``ok`` when classification is off."""
        if self.classifier is None:
            return "", "ok"
        from bodyslam.vision.classify import frame_features, frame_status

        status = frame_status(img, self.fov)
        if status != "ok":
            return "FL", status
        f = frame_features(img, self.fov, work_px=self.work_px, photometric=self.classifier.photometric)
        return str(self.classifier.predict(f[None])[0]), status

    # -- a range of frames ------------------------------------------------------------------------------------
    def run(self, frames: Iterable[Frame], first: int, ring_every: int = 0, bridge: bool = False) -> ChunkResult:
        """Records and steps of the frames at positions ``first ..`` (module docstring). ``ring_every``: the
        fitted steps into positions divisible by it get their ``ring_ratio`` (the exam's lumen scale sample,
        :func:`bodyslam.vision.lumen_scale.ring_every`; 0: none). ``bridge``: also match the ends of every gap
        that closes inside the chunk as it closes (``gap_totals``; :func:`bridge_inside`), from the features the
        steps beside it made -- the same motion :meth:`bridge` finds from the frames (features are a function of
        the frame), without reading and detecting them again."""
        from bodyslam.vision.scale_chain import linked

        cam = self.camera
        out = ChunkResult([], [], [])
        prev = None  # (features or None, class, frame status)
        prev_points = None  # the previous step's points in its last frame (this step's first), None: no fit
        max_gap = self.settings.bridge_gaps if bridge and self.settings.estimator == "tube" else 0
        prev_measured = False  # the step into the previous frame was measured (inside this chunk)
        gap = None  # an open gap: [its first frame's position, that frame's features, steps in it, a bad frame in it]
        for fr in frames:
            if fr.end_of_video:  # a container's frame count is an estimate: every decodable frame was read
                out.eof = fr.pos
                break
            own = fr.pos > first or first == 0  # the seam frame belongs to the previous chunk
            img, notes = fr.image, list(fr.notes)
            status = "unreadable" if img is None else "ok"
            if img is not None and img.shape[:2] != (cam.height, cam.width):
                notes.append(("error", f"size {img.shape[1]}x{img.shape[0]} is not the camera's "
                                       f"{cam.width}x{cam.height}"))
                img, status = None, "bad_size"
            feats, cls = None, ""
            if img is not None:
                feats = self.matcher.features(img)
                cls, status = self.classify(img)
            if own:
                out.problems.extend([fr.path, fr.index, sev, reason] for sev, reason in notes)
                out.frames.append([fr.index, fr.label, fr.t_s, cls, status])
            if fr.pos > first:
                ring = ring_every > 0 and fr.pos % ring_every == 0
                self.signatures = None
                if prev is None or prev[0] is None or feats is None:
                    s = StepMotion.failed(StepStatus.BAD_FRAME)
                elif self.classifier is not None and (prev[2] != "ok" or status != "ok"):
                    s = StepMotion.failed(StepStatus.NO_LUMEN)  # a dark or saturated frame: nothing to fit
                elif self.classifier is not None and (prev[1] != "FT" or cls != "FT"):
                    s = self.estimate_wall(prev[0], feats, ring=ring)
                else:  # both frames face the tunnel where they were classified
                    s = self.estimate_pair(prev[0], feats, ahead=self.classifier is not None, ring=ring)
                points = self.signatures if s.ok else None
                if fr.pos == first + 1:
                    out.seam_in = points[0] if points else None
                elif points is not None and prev_points is not None:
                    s = linked(s, prev_points, points[0])
                prev_points = points[1] if points else None
                out.steps.append((fr.pos, fr.index, fr.t_s, s))
                if max_gap:  # after the step's own points are read: the bridge's estimate_pair sets them again
                    gap, prev_measured = self._follow_gap(gap, prev_measured, s, fr.pos, prev[0] if prev else None,
                                                          max_gap, out.gap_totals)
            prev = (feats, cls, status)
        out.seam_out = prev_points
        return out

    def _follow_gap(self, gap, prev_measured: bool, s: StepMotion, pos: int, prev_feats, max_gap: int,
                    totals: dict):
        """One step of :meth:`run`'s gap tracking (the rule of :func:`find_gaps`): a step without an estimate after
        a measured one opens a gap at its first frame (``pos - 1``, whose features ``prev_feats`` it keeps); a
        measured step closes the open gap at its own first frame, whose ends are matched then (``totals``) when the
        gap holds at most ``max_gap`` steps and no unreadable frame. Returns the open gap and whether ``s`` was
        measured."""
        measured = s.status in MEASURED
        if measured:
            if gap is not None and gap[2] <= max_gap and not gap[3]:
                b = self.estimate_pair(gap[1], prev_feats, "tube", rotation=False)  # as bridge() does
                totals[(gap[0], pos - 1)] = b if b.ok else None
            return None, True
        if gap is None:
            return ([pos - 1, prev_feats, 1, s.status == StepStatus.BAD_FRAME] if prev_measured else None), False
        gap[2] += 1
        gap[3] |= s.status == StepStatus.BAD_FRAME
        return (gap if gap[2] <= max_gap else None), False

    def bridge(self, img_a: np.ndarray | None, img_b: np.ndarray | None) -> StepMotion | None:
        """The motion from frame ``a`` straight to frame ``b`` (a gap's ends, tube estimator), or None."""
        if img_a is None or img_b is None:
            return None
        fa, fb = self.matcher.features(img_a), self.matcher.features(img_b)
        s = self.estimate_pair(fa, fb, "tube", rotation=False)
        return s if s.ok else None


# -- workers ----------------------------------------------------------------------------------------------------
_ENGINES: dict = {}


def engine_for(camera_d: dict, settings: MotionSettings, radius_m: float, mask: np.ndarray | None,
               T_body_cam: tuple | None = None) -> VisualOdometry:
    """A worker's engine, built once per process and (camera, settings, radius, mask)."""
    key = (json.dumps(camera_d, sort_keys=True), settings, radius_m,
           None if mask is None else hashlib.sha1(np.ascontiguousarray(mask)).hexdigest(), repr(T_body_cam))
    if key not in _ENGINES:
        _ENGINES.clear()
        _ENGINES[key] = VisualOdometry(camera_from_dict(camera_d), settings, radius_m, mask, T_body_cam)
    return _ENGINES[key]


def set_worker_threads() -> None:
    """One OpenCV thread per worker process (the pool has one process per core)."""
    import cv2

    cv2.setNumThreads(1)


def chunk_task(task: dict) -> ChunkResult:
    """A worker's chunk: ``task`` holds the source subset, camera, settings, radius, mask, first and last."""
    from bodyslam.parallel import heap_top_kept

    set_worker_threads()
    vo = engine_for(task["camera"], task["settings"], task["radius_m"], task["mask"], task.get("T_body_cam"))
    src: FrameSource = task["source"]
    with heap_top_kept():  # SIFT's scale space reused from call to call, not faulted in again (bodyslam.parallel)
        return vo.run(src.read(task["first"], task["last"]), task["first"], task.get("ring_every", 0),
                      bridge=task.get("bridge_inside", False))


def bridge_task(task: dict) -> StepMotion | None:
    """A worker's gap: the motion from position ``a`` to ``b`` of the source."""
    set_worker_threads()
    vo = engine_for(task["camera"], task["settings"], task["radius_m"], task["mask"], task.get("T_body_cam"))
    return vo.bridge(task["source_a"].read_one(task["a"]).image, task["source_b"].read_one(task["b"]).image)


# -- gaps -------------------------------------------------------------------------------------------------------
def find_gaps(statuses: list, max_len: int) -> list[tuple[int, int]]:
    """Runs of steps without an estimate, as position pairs ``(a, b)``: steps ``a+1..b`` (0-based list items
    ``a..b-1``) have none, the steps on both sides have one (so frames ``a`` and ``b`` are readable and
    were matched); runs of at most ``max_len``, none across an unreadable frame. ``statuses``: per step, a
    :class:`StepStatus` or a StepMotion; estimated = measured from its own matches (``ok``, ``wall``)."""
    st = [getattr(s, "status", s) for s in statuses]
    out, k, n = [], 0, len(st)
    while k < n:
        if st[k] in MEASURED:
            k += 1
            continue
        j = k
        while j < n and st[j] not in MEASURED:
            j += 1
        if k > 0 and j < n and j - k <= max_len and all(s != StepStatus.BAD_FRAME for s in st[k:j]):
            out.append((k, j))
        k = j
    return out


def split_motion(total: StepMotion, n: int) -> list[StepMotion]:
    """``n`` equal steps whose composition is ``total`` (constant twist: rotation ``R^(1/n)``, translation on
    the screw), each with status ``bridged`` and a 1-sigma of ``total``'s over sqrt(n) (independent steps)."""
    R = Rotation.from_matrix(total.R_c1_c2)
    dR = Rotation.from_rotvec(R.as_rotvec() / n)
    # find t_s with sum_{i<n} dR^i t_s = t_total
    A = np.zeros((3, 3))
    Ri = np.eye(3)
    for _ in range(n):
        A += Ri
        Ri = Ri @ dR.as_matrix()
    t_s = np.linalg.solve(A, np.asarray(total.t_c1_c2_m, float))
    share = motion_from_transform(dR, t_s, total.n_matches, total.sigma_distance_m / math.sqrt(n),
                                  total.sigma_rotation_rad / math.sqrt(n), StepStatus.BRIDGED)
    return [share] * n


def pair_motions(pairs: list[tuple[int, int]], task_base: dict, jobs: int | None = None, run_tasks=None):
    """The motion from position ``a`` straight to ``b`` for each pair (:func:`bridge_task`: tube estimator; None
    where it fails), in order. ``run_tasks(func, tasks)``: how to run them (default: local worker processes)."""
    if run_tasks is None:
        from bodyslam.parallel import imap_tasks

        def run_tasks(func, tasks):
            return imap_tasks(func, tasks, jobs)

    src: FrameSource = task_base["source"]
    return run_tasks(bridge_task, [dict(task_base, source=None, a=a, b=b, source_a=src.subset(a, a),
                                        source_b=src.subset(b, b)) for a, b in pairs])


def bridge_gaps(steps: list, settings: MotionSettings, task_base: dict,
                jobs: int | None = None, run_tasks=None,
                done: Iterable[tuple[int, int]] = (), totals_seen: dict | None = None) -> dict[int, StepMotion]:
    """Bridge the gaps of ``steps`` (StepMotions or their statuses; list item ``i`` = the step into position
    ``i + 1``): returns ``{list item: bridged share}``. ``task_base``: the engine's task fields (source, camera,
    settings, radius, mask); ``run_tasks(func, tasks)``: how to run them (default: local worker processes);
    ``done``: gaps ``(a, b)`` already bridged elsewhere (a batch chunk's own, :func:`bridge_inside`), left out;
    ``totals_seen``: gaps' end-to-end motions already matched as a run's chunks went (``ChunkResult.gap_totals``),
    not matched again."""
    if not settings.bridge_gaps or settings.estimator != "tube":
        return {}
    skip = set(map(tuple, done))
    gaps = [g for g in find_gaps(steps, settings.bridge_gaps) if g not in skip]
    if not gaps:
        return {}
    seen = totals_seen or {}
    todo = [g for g in gaps if g not in seen]
    matched = dict(zip(todo, pair_motions(todo, task_base, jobs, run_tasks))) if todo else {}
    return bridged_shares(steps, gaps, [seen[g] if g in seen else matched[g] for g in gaps], task_base["radius_m"])


def bridged_shares(steps: list, gaps: list[tuple[int, int]], totals: Iterable[StepMotion | None],
                   radius_m: float) -> dict[int, StepMotion]:
    """``{list item: share}`` of the gaps whose end-to-end motion ``totals`` (in the gaps' order; None: not
    matched) is long enough for the steps it holds that were lost to motion (:data:`BRIDGE_MIN_LOST_SHARE` of the
    least length of each, :func:`bodyslam.steps.lost_step_floor_m`), split into equal shares."""
    out = {}
    floor = lost_step_floor_m(radius_m)
    for (a, b), total in zip(gaps, totals):
        if total is None:
            continue
        n_lost = sum(getattr(s, "status", s) in LOST_TO_MOTION for s in steps[a:b])
        length_m = float(np.linalg.norm(total.t_c1_c2_m))
        if length_m < BRIDGE_MIN_LOST_SHARE * n_lost * floor:
            log.info("gap of steps %d-%d not bridged: %.2f cm end to end, where %d of its steps were lost to motion "
                     "(each at least %.2f cm)", a + 1, b, 100 * length_m, n_lost, 100 * floor)
            continue
        for i, s in zip(range(a, b), split_motion(total, b - a)):
            out[i] = s
    return out


def bridge_inside(statuses: list, first: int, settings: MotionSettings, radius_m: float,
                  totals: dict) -> tuple[list[tuple[int, int]], dict[int, StepMotion]]:
    """The gaps that lie wholly inside a chunk of steps into positions ``first + 1 ..`` (``statuses``: theirs, in
    order), bridged by the chunk's own worker: ``(gaps (a, b), {list item: share})`` in the exam's positions and
    items. A gap with an estimated step on both sides inside the chunk is the same gap in the whole exam
    (:func:`find_gaps`), bridged from the same two frames by the same rule as :func:`bridge_gaps`, so the result
    is the same as bridging it after all chunks; gaps at the chunk's ends are left for then. ``totals``: the gaps'
    end-to-end motions, matched by the chunk's run as each gap closed (``ChunkResult.gap_totals``, the same rule)."""
    if not settings.bridge_gaps or settings.estimator != "tube":
        return [], {}
    gaps = [(first + a, first + b) for a, b in find_gaps(statuses, settings.bridge_gaps)]
    shares = bridged_shares(statuses, [(a - first, b - first) for a, b in gaps], [totals[g] for g in gaps], radius_m)
    return gaps, {first + i: s for i, s in shares.items()}


# -- does the per-step 1-sigma hold? ---------------------------------------------------------------------------
# the k-step check's distance ratio leaves out pairs whose single steps add up to less than this: a capsule at rest
# (a repeated frame's step is fitted at ~1e-15 m, whose ratio is rounding, not scale); a micrometre is a fifth of
# the 1-sigma the fit states for a step at rest (~5 um on demo and real frames)
CONSISTENCY_MIN_LENGTH_M = 1e-6


def consistency_pairs(statuses: list, k: int = 3, max_pairs: int = 30) -> list[tuple[int, int]]:
    """Position pairs ``(a, a + k)`` whose ``k`` single steps were all estimated from their own matches, spread
    evenly over the exam and not overlapping (at most ``max_pairs``)."""
    st = [getattr(s, "status", s) for s in statuses]
    cand, a = [], 0
    while a + k <= len(st):
        if all(x in MEASURED for x in st[a:a + k]):
            cand.append(a)
            a += k
        else:
            a += 1
    if len(cand) > max_pairs:
        cand = [cand[i] for i in np.linspace(0, len(cand) - 1, max_pairs).round().astype(int)]
    return [(a, a + k) for a in cand]


def consistency_diagnostic(singles: list[list[StepMotion]], totals: list[StepMotion | None], k: int = 3,
                           shape_sd_rel: float = 0.0) -> dict:
    """The k-step check of the per-step uncertainty: for each pair, the distance of the motion estimated
    straight from frame ``a`` to ``a + k`` against the distance of its ``k`` single steps composed, and their
    difference over the combined 1-sigma (``z``; the radius's share is left out: it is common to both). If the
    1-sigma holds, ~68% of ``|z|`` are <= 1 and ~95% <= 2; the median ratio says whether single steps and longer
    baselines agree in scale. ``within_*``: the fit's own 1-sigma; with ``shape_sd_rel`` (the lumen's departure
    from a cylinder, a share of each estimate's distance), ``stated_within_*`` also counts that share, as each
    step's stated 1-sigma does (less the radius's), taken as independent between the pair and its single steps:
    they look at much of the same wall, so that check errs on the generous side, and the fit's own is the strict
    one (docs/RESULTS.md, session 75)."""
    z, z_stated, ratio = [], [], []
    for ks, tot in zip(singles, totals):
        if tot is None or not tot.has_estimate or not all(s.has_estimate for s in ks):
            continue
        R, t, var, var_shape = np.eye(3), np.zeros(3), 0.0, 0.0
        for s in ks:
            t = t + R @ np.asarray(s.t_c1_c2_m, float)
            R = R @ np.asarray(s.R_c1_c2, float)
            var += s.sigma_t_m**2
            var_shape += (shape_sd_rel * float(np.linalg.norm(s.t_c1_c2_m))) ** 2
        d_single, d_pair = float(np.linalg.norm(t)), float(np.linalg.norm(tot.t_c1_c2_m))
        sig = math.sqrt(var + tot.sigma_t_m**2)
        z.append((d_pair - d_single) / sig if sig > 0 else math.inf)
        sig_stated = math.sqrt(sig**2 + var_shape + (shape_sd_rel * d_pair) ** 2)
        z_stated.append((d_pair - d_single) / sig_stated if sig_stated > 0 else math.inf)
        if d_single > CONSISTENCY_MIN_LENGTH_M:
            ratio.append(d_pair / d_single)
    z_abs, z_st = np.abs(np.array(z)), np.abs(np.array(z_stated))
    out = {"k": k, "pairs_tried": len(totals), "pairs_estimated": len(z),
           "median_distance_ratio_pair_over_singles": float(np.median(ratio)) if ratio else None,
           "within_1sigma": float(np.mean(z_abs <= 1)) if z else None,
           "within_2sigma": float(np.mean(z_abs <= 2)) if z else None,
           "honest_if": "within_1sigma ~0.68 and within_2sigma ~0.95; a ratio far from 1 means the single steps "
                        "and the k-frame baseline disagree in scale"}
    if shape_sd_rel > 0:
        out.update({"lumen_shape_sd_rel": float(shape_sd_rel),
                    "stated_within_1sigma": float(np.mean(z_st <= 1)) if z else None,
                    "stated_within_2sigma": float(np.mean(z_st <= 2)) if z else None})
    return out


def step_consistency(steps: list, settings: MotionSettings, task_base: dict, k: int = 3,
                     max_pairs: int = 30, jobs: int | None = None, run_tasks=None,
                     pairs: list[tuple[int, int]] | None = None, shape_sd_rel: float = 0.0) -> dict | None:
    """:func:`consistency_diagnostic` of ``steps`` (the fit's own 1-sigma, before
    :func:`with_lumen_uncertainty`; and with ``shape_sd_rel``, the lumen shape's share), the k-frame motions
    estimated with the gap bridge's rule; None for an estimator without a full pose (``thesis``). ``pairs``:
    already chosen (:func:`consistency_pairs`; then only their steps need to be in ``steps``)."""
    if settings.estimator != "tube":
        return None
    pairs = consistency_pairs(steps, k, max_pairs) if pairs is None else pairs
    totals = list(pair_motions(pairs, task_base, jobs, run_tasks)) if pairs else []
    return consistency_diagnostic([steps[a:b] for a, b in pairs], totals, k, shape_sd_rel)


# -- masks ------------------------------------------------------------------------------------------------------
def fov_from_frames(frames: list[np.ndarray], camera: CameraModel, mask: str | None) -> np.ndarray | None:
    """The valid field of view by the ``--mask`` rule (:attr:`MotionSettings.mask`) for a few frames of the
    camera's size: None means the camera's image circle. ``None``/``"auto"``: detected from ``frames``
    (:func:`bodyslam.vision.matching.field_of_view`; none given: the circle); ``"circle"``; or read from a PNG."""
    if mask == "circle":
        return None
    if mask in (None, "auto"):
        if not frames:
            return None
        from bodyslam.vision.matching import field_of_view

        m, how = field_of_view(frames, camera.fov_mask())
        log.info("field of view: %s", how)
        return m
    img = read_image(mask, unchanged=True)
    if img.ndim == 3:
        img = img.max(axis=2)
    if img.shape != (camera.height, camera.width):
        raise InputError(f"{mask}: mask is {img.shape[1]}x{img.shape[0]}, frames are {camera.width}x{camera.height}")
    return img > 0


def resolve_mask(source: FrameSource, camera: CameraModel, mask: str | None, n_sample: int = 30) -> np.ndarray | None:
    """:func:`fov_from_frames` for a whole source: the detection (``None``/``"auto"``) looks at ``n_sample``
    frames spread over the exam. Frames none of which is the camera's size are one error up front."""
    if mask not in (None, "auto"):
        return fov_from_frames([], camera, mask)
    n = len(source)
    frames, other_sizes = [], set()
    for k in np.unique(np.linspace(0, n - 1, min(n_sample, n)).astype(int)):
        fr = source.read_one(int(k))
        if fr.end_of_video:  # a container's frame count is an estimate: the later samples lie past the end too (the
            log.info("%s: %s (field of view detected from the frames before it)", fr.path,  # run reports the end)
                     fr.notes[-1][1] if fr.notes else "the video ends here")
            break
        if fr.image is not None and fr.image.shape[:2] == (camera.height, camera.width):
            frames.append(fr.image)
        elif fr.image is not None:
            other_sizes.add(f"{fr.image.shape[1]}x{fr.image.shape[0]}")
        elif fr.notes:
            log.warning("%s: %s (skipped for field-of-view detection)", fr.path, fr.notes[-1][1])
    if not frames and other_sizes:  # one line up front, not one error per frame
        raise InputError(f"{source.source}: frames are {', '.join(sorted(other_sizes))}, the camera "
                         f"(calibration) is {camera.width}x{camera.height}")
    if not frames and mask == "auto":
        raise InputError(f"{source.source}: no readable frame to detect the field of view from")
    return fov_from_frames(frames, camera, mask)


def write_mask(path: str | os.PathLike, mask: np.ndarray | None, camera: CameraModel) -> None:
    """The field of view a run used, as a PNG (255 = valid): what ``--mask PNG`` reads back."""
    from bodyslam.io import write_image

    m = camera.fov_mask() if mask is None else mask
    write_image(path, (np.asarray(m, bool) * 255).astype(np.uint8))


# -- a sequence directory ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Sequence:
    """What the pipeline may read of a sequence directory: frames, time stamps, calibration, lumen radius."""

    path: Path
    camera: CameraModel
    camera_d: dict
    n_frames: int
    frame_rate_hz: float
    radius_m: float
    source: FrameSource
    camera_name: str = "front"
    T_body_cam: tuple | None = None  # (q_xyzw, t_m) of a non-front camera in the body (front camera) frame
    radius_sd_m: float = 0.0  # 1-sigma of radius_m (meta.json; 0 when the radius was given on the command line)
    shape_sd_rel: float = 0.0  # the lumen's departure from a cylinder, relative to a step (meta.json)

    @property
    def radius_sd_rel(self) -> float:
        """The lumen radius's 1-sigma relative to it (the visual scale's)."""
        return self.radius_sd_m / self.radius_m

    @classmethod
    def open(cls, seq_dir: str | os.PathLike, radius_m: float | None = None, camera: str = "front",
             radius_sd_m: float | None = None) -> "Sequence":
        """A sequence directory's frames and meta.json. ``radius_m``: the lumen radius given instead of meta.json's,
        known exactly unless ``radius_sd_m`` gives its 1-sigma (``--radius-from``: the radius an exam measured)."""
        seq = Path(seq_dir)
        meta = read_meta(seq)
        if camera not in CAMERAS:
            raise ConfigError(f"camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
        r = radius_m if radius_m is not None else meta.tube_radius_m
        if r is None:
            raise InputError(f"{seq}/meta.json: no tube_radius_m; give the lumen radius (--radius-m)")
        if not (math.isfinite(r) and r > 0):
            raise InputError(f"lumen radius must be a positive number of metres, got {r!r}")
        sd = meta.tube_radius_sd_m if radius_m is None else float(radius_sd_m or 0.0)
        if not (math.isfinite(sd) and 0 <= sd < r):
            raise InputError(f"the lumen radius's 1-sigma must be below the radius, got {sd!r} m for {r!r} m")
        extr = None
        if camera == "front":
            cam_d, frames_dir = meta.camera, seq / meta.frames_dir
        else:
            if meta.rear_camera is None:
                raise InputError(f"{seq}/meta.json: no rear_camera (a single-camera capsule)")
            rc = meta.rear_camera
            cam_d, frames_dir = rc.camera, seq / rc.frames_dir
            extr = (rc.q_front_rear_xyzw, rc.t_front_rear_m)
        if not frames_dir.is_dir():
            raise InputError(f"{frames_dir}: frames directory not found")
        src = FrameSource.sequence(frames_dir, meta.n_frames, meta.frame_rate_hz)
        return cls(seq, camera_from_dict(cam_d), cam_d, meta.n_frames, meta.frame_rate_hz, float(r), src, camera,
                   extr, sd, meta.lumen_shape_sd_rel)

    def frame(self, k: int) -> np.ndarray:
        """Frame ``k`` as RGB; raises :class:`InputError` when unreadable or of the wrong size."""
        fr = self.source.read_one(k)
        if fr.image is None:
            raise InputError(f"{fr.path}: {fr.notes[-1][1] if fr.notes else 'unreadable'}")
        if fr.image.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(f"{fr.path}: size {fr.image.shape[1]}x{fr.image.shape[0]} is not the camera's "
                             f"{self.camera.width}x{self.camera.height}")
        return fr.image

    def task_base(self, settings: MotionSettings, mask: np.ndarray | None) -> dict:
        return {"source": self.source, "camera": self.camera_d, "settings": settings, "radius_m": self.radius_m,
                "mask": mask, "T_body_cam": self.T_body_cam}


def chunk_bounds(n: int, size: int) -> list[tuple[int, int]]:
    """Position ranges ``(a, b)`` of chunks of ``size`` steps that overlap by one frame."""
    if n <= 1:
        return [(0, max(n - 1, 0))]
    b = list(range(0, n - 1, size)) + [n - 1]
    return [(b[i], b[i + 1]) for i in range(len(b) - 1)]


def sequence_motion(seq_dir: str | os.PathLike, settings: MotionSettings = MotionSettings(),
                    jobs: int | None = None, radius_m: float | None = None, chunk_frames: int = 50,
                    progress: Callable[[int, int], None] | None = None, camera: str = "front",
                    problems: list | None = None, fov_used: list | None = None,
                    lumen_scale_used: list | None = None, radius_sd_m: float | None = None) -> list[StepMotion]:
    """Per-step motion of every consecutive pair of a sequence (``n_frames - 1`` steps, in order), gaps
    bridged, rescaled by the lumen's scale seen in a sample of them where the radius is a prior
    (:func:`lumen_scale_measured`, :mod:`bodyslam.vision.lumen_scale`), each step's 1-sigma with the radius's
    uncertainty in it (:func:`with_lumen_uncertainty`: the measured factor's where it applies,
    :func:`~bodyslam.vision.lumen_scale.radius_sd_rel_after`). ``camera="rear"``: a dual-camera capsule's rear
    frames, reported as the body's motion. ``problems``: a list that receives ``[file, frame, severity, reason]``
    for every bad frame;
    ``fov_used``: one that receives the field-of-view mask the run used (None: the image circle; :func:`write_mask`
    writes it); ``lumen_scale_used``: one that receives the scale's summary
    (:func:`~bodyslam.vision.lumen_scale.lumen_scale_summary`), or None where it was not measured; ``radius_sd_m``:
    the 1-sigma of a ``radius_m`` given (:meth:`Sequence.open`)."""
    from bodyslam.parallel import imap_tasks
    from bodyslam.vision.lumen_scale import (exam_scale, exam_scale_sd_rel, local_sd_rel_after, lumen_scale_summary,
                                             radius_sd_rel_after, rescaled, ring_tried)
    from bodyslam.vision.lumen_scale import ring_every as sample_every

    seq = Sequence.open(seq_dir, radius_m, camera, radius_sd_m=radius_sd_m)
    n = seq.n_frames
    if n < 2:
        raise InputError(f"{seq_dir}: need at least 2 frames, meta.json says {n}")
    mask = resolve_mask(seq.source, seq.camera, settings.mask)
    if fov_used is not None:
        fov_used.append(mask)
    base = seq.task_base(settings, mask)
    measure = lumen_scale_measured(settings, seq.radius_sd_rel)
    every = sample_every(n) if measure else 0
    tasks = [dict(base, source=seq.source.subset(a, b), first=a, last=b, ring_every=every, bridge_inside=True)
             for a, b in chunk_bounds(n, chunk_frames)]
    from bodyslam.vision.scale_chain import chained, linked

    steps: list[StepMotion] = []
    seam = None  # the previous chunk's last step's points in its last frame
    seen: dict = {}  # the gaps matched inside their chunk as they closed (VisualOdometry.run's gap_totals)
    for res in imap_tasks(chunk_task, tasks, jobs):
        seen.update(res.gap_totals)
        for j, (_, _, _, s) in enumerate(res.steps):
            if j == 0 and seam is not None and res.seam_in is not None:  # the seam's link, as one chunk gives it
                s = linked(s, seam, res.seam_in)
            steps.append(s)
        seam = res.seam_out
        for p in res.problems:
            log.warning("%s: %s", p[0], p[3])
            if problems is not None:
                problems.append(p)
        if progress:
            progress(len(steps), n - 1)
    for i, s in bridge_gaps(steps, settings, base, jobs, totals_seen=seen).items():
        steps[i] = s
    if measure:
        chain = None
        if settings.scale_chain:
            steps, chain = chained(steps, seq.radius_m)
            log.info("scale chain: %d steps tied to their neighbours by %d links", chain["steps_chained"],
                     chain["links"])
        tried = ring_tried((s.status for s in steps), every)
        ratios = [s.ring_ratio for s in steps]
        factor, samples = exam_scale(ratios, tried)
        log.info("lumen scale: %.3f from %d ring ratios of %d steps fitted (one step in %d)", factor, samples, tried,
                 every)
        steps = [rescaled(s, factor) for s in steps]
        sc = lumen_scale_summary(factor, samples, every, seq.radius_m, chain, tried,
                                 exam_scale_sd_rel(ratios) if factor != 1.0 else None)
        # the measured factor's 1-sigma where it applies, and what it cannot follow from step to step
        rel, local = radius_sd_rel_after(sc, seq.radius_sd_rel), local_sd_rel_after(sc)
        if lumen_scale_used is not None:
            lumen_scale_used.append(sc)
    else:
        rel, local = seq.radius_sd_rel, 0.0
        if lumen_scale_used is not None:
            lumen_scale_used.append(None)
    return with_lumen_uncertainty(steps, rel, seq.shape_sd_rel, local)


def lumen_scale_measured(settings: MotionSettings, radius_sd_rel: float) -> bool:
    """Whether an exam's steps are rescaled by the lumen scale seen in them (:mod:`bodyslam.vision.lumen_scale`)
    and tied to their neighbours' (:mod:`bodyslam.vision.scale_chain`): with the tube estimator, where the settings
    ask for it and the radius is a prior at least :data:`LUMEN_SCALE_MIN_PRIOR_SD_REL` wide; a radius known exactly
    (the ideal testbed's, or one given on the command line) or to within that is the scale."""
    return settings.lumen_scale and settings.estimator == "tube" and radius_sd_rel >= LUMEN_SCALE_MIN_PRIOR_SD_REL


# The lumen scale is measured only where the radius's prior is at least this wide (its relative 1-sigma): the ring
# measure errs by about 5% itself (its ratios read 0.94-0.95 on lumens without contraction rings; lumen_scale's
# docstring, session 42), so a radius known to within that keeps its scale. A testbed tube's own mean, stated with
# the radius's spread along the tube (exam 4.2%, demo 6.5%; testbed.simulate.told_radius), is such a radius: on the
# demo sample (told its centre line's mean, 1.38 cm) the ring measure took the steps x0.974 where the wall its frames
# see is ~1.39 cm from the centre line (distance error 0.022 -> 0.028 cm; docs/RESULTS.md, session 55). Real exams'
# assumed prior (20%) and the realistic testbed's are measured.
LUMEN_SCALE_MIN_PRIOR_SD_REL = 0.10


def with_lumen_uncertainty(steps: list[StepMotion], radius_sd_rel: float,
                           shape_sd_rel: float = 0.0, local_sd_rel: float = 0.0) -> list[StepMotion]:
    """The steps with what the tube estimator assumes of the lumen in their 1-sigma distance, both added in
    quadrature to the fit's own 1-sigma:

    - the radius: the translation scales with the radius the fit assumes, so a relative 1-sigma ``radius_sd_rel``
      of the radius adds ``radius_sd_rel * |d|``. The error is the same for neighbouring steps (the radius changes
      over centimetres): the fusion carries it as one scale state and takes this part back out of each step
      (:func:`bodyslam.fusion.ekf.step_noise`, :func:`bodyslam.vision.tracking.path_from_lengths`);
    - the shape: a lumen that is not the cylinder the fit assumes (folds, a star-shaped cross-section, a radius
      that changes within the view) errs by a fraction of the step that changes from step to step, which the fit's
      residuals do not show (its 1-sigma was ~5x optimistic on the realistic testbed); ``shape_sd_rel * |d|``
      stays in the step's 1-sigma (meta.json ``lumen_shape_sd_rel``). A step facing the wall (status ``wall``)
      has it times :data:`WALL_SIGMA_FACTOR`, as its fit's share already is: its non-radius part is inflated;
    - where a measured lumen scale replaced the radius prior (``radius_sd_rel`` is then the factor's 1-sigma), the
      radius about the exam's mean over a step's few millimetres, which one factor cannot follow: ``local_sd_rel *
      |d|`` (:data:`bodyslam.vision.lumen_scale.SCALE_LOCAL_SD_REL`), white as the shape's share is.

    Steps without an estimate are unchanged."""
    if not (radius_sd_rel > 0 or shape_sd_rel > 0 or local_sd_rel > 0):
        return steps
    radius_sd_rel, shape_sd_rel, local_sd_rel = max(radius_sd_rel, 0.0), max(shape_sd_rel, 0.0), max(local_sd_rel, 0.0)
    out = []
    for s in steps:
        if s.has_estimate and math.isfinite(s.distance_m):
            fit = s.sigma_distance_m if math.isfinite(s.sigma_distance_m) else 0.0
            shape = shape_sd_rel * (WALL_SIGMA_FACTOR if s.status == StepStatus.WALL else 1.0)
            d = abs(s.distance_m)
            s = replace(s, sigma_distance_m=math.hypot(fit, radius_sd_rel * d, shape * d, local_sd_rel * d))
        out.append(s)
    return out

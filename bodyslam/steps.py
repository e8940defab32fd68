"""The one type of a visual step, and what became of it (statuses).

A *step* ``k`` is the capsule's motion from frame ``k-1`` to frame ``k``: the relative pose ``T_c1_c2`` (rotation
``R_c1_c2``, translation ``t_c1_c2_m`` in frame ``k-1``'s camera axes) with its 1-sigma uncertainties, reported
also as the dissertation's quantities (distance, roll, pitch, yaw, tilt; :mod:`bodyslam.geometry`). The same
object is what the estimators return, what ``motion.csv`` stores (:func:`bodyslam.io.write_motion_csv` /
:func:`bodyslam.io.read_motion_steps`), what dead reckoning and the fusion consume, and what batch chunks carry.

Statuses (:class:`StepStatus`, a ``StrEnum``: compares equal to its text, which is what ``motion.csv`` holds):

- ``ok``: estimated from the pair's matches;
- ``wall``: estimated from the pair's matches by the tube fit although a frame of the pair faces the wall (FL),
  with its 1-sigma inflated (:data:`bodyslam.vision.odometry.WALL_SIGMA_FACTOR`); the dissertation drops such steps
  (``--drop-wall-steps``);
- ``bridged``: a share of a gap's end-to-end motion (:func:`bodyslam.vision.odometry.split_motion`);
- ``rotation``: only the rotation was measured (a fast step whose ordinary matches were too few: guided matching,
  :mod:`bodyslam.vision.guided`); roll, pitch, yaw, tilt and ``R_c1_c2`` are set, the distance and translation
  are NaN;
- ``rotation_slow``: as ``rotation``, but guided matching's short-step hypotheses (the capsule nearly in place)
  verified at least :data:`bodyslam.vision.guided.SLOW_MATCH_RATIO` times the matches of its forward ones: the
  pair overlaps as a slow step does, so the step is not counted lost to motion (a capsule turning in pooled
  turbid fluid, session 48; the ``lost`` steps of a turn into a featureless wall stay ``lost``);
- ``lost``: no estimate, and lost to motion: ordinary and guided matching both failed between two frames rich in
  features (:data:`bodyslam.vision.odometry.LOST_MIN_KEYPOINTS_FRAC`), with no more verified matches than
  unrelated frames give (:data:`~bodyslam.vision.odometry.LOST_MAX_MATCHES`), so the view changed too much to
  match -- the capsule moved far (a blurred, turbid or featureless frame keeps ``too_few_matches``: it may be a
  capsule at rest; so do frames that overlap but verify too few matches to fit);
- ``too_few_matches``, ``uncertain``, ``solver_failed``: the estimator gave no usable estimate;
- ``no_lumen``: a frame of the pair is too dark or saturated to fit, or faces the wall and the step was not
  estimated (the thesis estimator's unrolling needs the lumen in view; ``--drop-wall-steps``);
- ``bad_frame``: a frame of the pair could not be read;
- ``missing``: no row for the step in a ``motion.csv`` that was read back.

Steps that are neither ``ok``, ``wall`` nor ``bridged`` carry NaN distances, never an invented number; only
``rotation`` and ``rotation_slow`` steps among them carry a rotation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

__all__ = ["StepStatus", "MEASURED", "WITH_ESTIMATE", "WITH_ROTATION", "StepMotion", "motion_from_transform",
           "rotation_step", "lost_to_motion", "StepLengths", "SIGMA_T_DEFAULT_M", "SIGMA_R_DEFAULT_RAD",
           "LOST_STEP_QUANTILE", "LOST_STEP_FLOOR_R", "lost_step_floor_m", "LOST_TO_MOTION", "LOSS_SLOPE",
           "STEP_MAX_R", "SPEED_JUMP_PROB", "MISSING_STEP_REL_SD", "HAMPERED_ENTER_PROB", "HAMPERED_STAY_PROB",
           "BESIDE_WALL_LOG_SD", "LOSS_SCALE_GRID", "LOSS_SCALE_PRIOR_LOG_SD"]

NAN = float("nan")
# 1-sigma assumed for an estimated step whose file gave none (a motion.csv from another tool)
SIGMA_T_DEFAULT_M = 1e-3
SIGMA_R_DEFAULT_RAD = math.radians(1.0)
# a step lost to motion is at least this percentile of the estimated step lengths long, and every step without an
# estimate gets at least that 1-sigma (the path travelled, bodyslam.vision.tracking.path_from_lengths, and the
# fusion's process rule, bodyslam.fusion.ekf.step_noise). Chosen on realistic tuning seeds 503-509 among the 75th,
# 90th and 95th percentile (docs/RESULTS.md, "How far along the gut")
LOST_STEP_QUANTILE = 90.0
# ... and at least this many lumen radii (the radius the steps assume): the length at which matching loses about
# half of the steps (realistic tuning seeds 503-509, 1.25 cm prior: 18% of the steps of 0.3-0.4 cm lost, 33% of
# 0.4-0.5, 61% of 0.5-0.6, 97% of 1.0-1.5). The percentile alone collapses where an exam's estimated steps are
# few and short: an 18-frame clip of a fast phase then a rest gave a path of 0.0 +- 0.01 cm for 12.9 cm travelled
# (docs/RESULTS.md, "Short clips")
LOST_STEP_FLOOR_R = 0.4
# the path travelled's model of the steps matching loses (bodyslam.vision.tracking.missing_step_lengths;
# docs/RESULTS.md, "The steps matching loses, from the speed around them"):
# - the chance that ordinary matching loses a step of length d is a logistic in ln(d / radius), half at
#   LOST_STEP_FLOOR_R and this slope (realistic tuning seeds 503-522, 3850 steps: fitted 0.45 radii and 3.66;
#   3% lost at 0.1-0.2 radii, 26% at 0.3-0.4, 84% at 0.6-0.8, 99% at 0.8-1.0)
LOSS_SLOPE = 3.5
# - a step is at most this many lumen radii long (1.25 cm, 2.5 cm/s at 2 frames/s; papers 002/003 model the capsule
#   at 0.05 +- 0.07 cm/s): the prior's upper end, chosen on tuning seeds among 0.8, 1.0, 1.2, 1.5 and 4 radii
STEP_MAX_R = 1.0
# - the capsule's speed changes little from one step to the next, and with this chance per step jumps to any value
#   (a phase of rest or of fast motion starting; stated choice: the path moved by < 1% between 0.02 and 0.2)
SPEED_JUMP_PROB = 0.05
# - a missing step's 1-sigma is at least this share of its length: on realistic tuning seeds 503-522 the model's
#   lengths of 1019 lost steps were right on average (+4%), 68% of them within 38% (its own 1-sigma held 47%)
MISSING_STEP_REL_SD = 0.4
# - the world can hamper matching for a while (a close, blurred, featureless wall; turbid fluid): a hidden state
#   that starts with this chance per step and lasts with the next, in which a step is lost or fitted beside the wall
#   whatever its length, so such a step says nothing of the speed there. A step with a rotation (guided matching
#   saw the wall under motion hypotheses) or an ordinary fit is never in it. Without it, runs of three steps lost
#   at a real exam's pace were filled as fast phases (true 0.04-0.13 cm, filled 0.84-0.88 cm). Chosen with
#   BESIDE_WALL_LOG_SD on realistic tuning renders through `bodyslam batch`'s defaults (slow 587-594, the
#   dissertation's pace 595-598) among entry 0.002-0.02, stay 0.4-0.8 and ln-sd 1-3: the best twelve of the 36 lay
#   within 0.8 points of mean absolute path error (docs/RESULTS.md, "Beside the wall and hampered by the world";
#   on reporting seeds it gains at a real exam's pace and loses 1-2 points at the dissertation's)
HAMPERED_ENTER_PROB = 0.005
HAMPERED_STAY_PROB = 0.6
# - a step fitted beside its own tube's wall (StepMotion.beside_wall) reads its length poorly (realistic tuning
#   renders: 0.07-0.63 of the truth at the median at a real exam's pace, 0.72-1.6 at the dissertation's): the path
#   takes its length from the speed model, the fit's length observing it with this 1-sigma in ln(length)
#   (chosen among 1, 2 and 3 with the hampered state above)
BESIDE_WALL_LOG_SD = 1.0
# - the loss curve's scale is the exam's own (session 50): its half-loss length is taken among these multiples of
#   LOST_STEP_FLOOR_R as the one under which the exam's steps (lost and not) are likeliest, with a prior of this
#   1-sigma in ln(scale) about 1. An exam in turbid fluid loses shorter steps than the matcher's measured curve says
#   (slow tuning renders 587-590: 10% of the steps of 0.1-0.2 radii lost, against 2-5% at the dissertation's pace).
#   Chosen on the nineteen realistic tuning renders (587-598, 580-586) among four grids and prior widths 0.3-2:
#   mean absolute path error 11.0 -> 9.2% (slow 587-590 11.2 -> 7.6, 591-594 12.1 -> 12.3; the dissertation's pace
#   595-598 10.9 -> 10.3, 580-586 10.2 -> 7.6). Reporting seeds: 764-783 17.8 -> 15.8%, 784-803 13.1 -> 12.6%,
#   `testbed evaluate realistic --seeds 700-719` 10.4 -> 11.3% (docs/RESULTS.md, "The loss curve's scale ...").
#   Session 63 added 2.0 (half lost at 0.8 radii): on the ideal tube's texture the matcher reaches further, so under
#   the measured curve the long steps it did estimate read as unlikely and the fast phases around its lost steps
#   slow; the thesis paths came out short (README table: -2.2%, 50% of frames inside 1-sigma). Thesis tuning 550-559:
#   path end 1.8 -> 1.6% mean absolute, mean z^2 2.08 -> 1.82; every realistic tuning run (540-549, 587-598)
#   unchanged, 2.0 never chosen there; 2.83 beside it changed nothing more (docs/RESULTS.md, "The loss curve's scale
#   reaches further on the ideal tube")
LOSS_SCALE_GRID = (0.5, 0.71, 1.0, 1.41, 2.0)
LOSS_SCALE_PRIOR_LOG_SD = 1.0


def lost_step_floor_m(radius_m: float | None) -> float:
    """The least length (m) of a step lost to motion at the lumen radius ``radius_m`` (None: no floor)."""
    return 0.0 if radius_m is None or not radius_m > 0 else LOST_STEP_FLOOR_R * float(radius_m)


class StepStatus(StrEnum):
    OK = "ok"
    WALL = "wall"
    BRIDGED = "bridged"
    ROTATION = "rotation"
    ROTATION_SLOW = "rotation_slow"
    LOST = "lost"
    TOO_FEW_MATCHES = "too_few_matches"
    UNCERTAIN = "uncertain"
    SOLVER_FAILED = "solver_failed"
    NO_LUMEN = "no_lumen"
    BAD_FRAME = "bad_frame"
    MISSING = "missing"


# statuses of a step estimated from its own pair's matches, of every step that carries a pose, and of every step
# that carries at least a rotation
MEASURED = (StepStatus.OK, StepStatus.WALL)
WITH_ESTIMATE = (*MEASURED, StepStatus.BRIDGED)
WITH_ROTATION = (*WITH_ESTIMATE, StepStatus.ROTATION, StepStatus.ROTATION_SLOW)
# statuses of a step lost to motion (lost_to_motion)
LOST_TO_MOTION = (StepStatus.ROTATION, StepStatus.LOST)


@dataclass(frozen=True, slots=True)
class StepMotion:
    """One step (module docstring). ``R_c1_c2`` is a 3x3 matrix when the estimator gives a full pose. Slotted: a
    whole exam's steps are held by the fusion (without a ``__dict__`` a step takes ~0.65 kB instead of ~0.79)."""

    distance_m: float = NAN
    roll_rad: float = NAN
    pitch_rad: float = NAN
    yaw_rad: float = NAN
    tilt_rad: float = NAN
    n_matches: int = 0
    status: StepStatus = StepStatus.OK
    R_c1_c2: np.ndarray | None = field(default=None, repr=False)
    t_c1_c2_m: np.ndarray | None = field(default=None, repr=False)
    sigma_distance_m: float = NAN  # 1-sigma of distance_m (tube estimator: from the fit)
    sigma_rotation_rad: float = NAN  # 1-sigma of the rotation (largest axis)
    # the tube fit put the camera beside the wall of its own cylinder or ran its axis across the view: the motion is
    # kept, its 1-sigma widened (bodyslam.vision.odometry.BESIDE_WALL_RADII); motion.csv's ``beside_wall`` column
    beside_wall: bool = False
    # the step's length under a tube with one contraction ring over its length under the cylinder, on the steps the
    # exam's lumen scale is measured on (bodyslam.vision.lumen_scale; NaN elsewhere); motion.csv's ``ring_ratio``
    ring_ratio: float = NAN
    # log(this step's scale / the previous step's) from the depths of the points both matched in their shared frame,
    # and its 1-sigma (bodyslam.vision.scale_chain; NaN where none); motion.csv's ``scale_link``, ``scale_link_sd``
    scale_link: float = NAN
    scale_link_sd: float = NAN
    # the factor the step's length was multiplied by to tie its scale to its neighbours' (bodyslam.vision.scale_chain;
    # NaN where the chain did not take it); motion.csv's ``chain_factor``
    chain_factor: float = NAN
    # a full pose the filters can use (has_estimate), worked out once: a step is not changed once made, and the
    # filters ask ~13 times a step
    _has_estimate: bool = field(init=False, repr=False, compare=False, default=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", StepStatus(self.status))  # also refuses an unknown status
        object.__setattr__(self, "_has_estimate", bool(
            self.status in WITH_ESTIMATE and self.R_c1_c2 is not None and self.t_c1_c2_m is not None
            and np.isfinite(self.t_c1_c2_m).all() and np.isfinite(self.R_c1_c2).all()))

    @property
    def ok(self) -> bool:
        """Estimated from this pair's own matches (``ok`` or ``wall``)."""
        return self.status in MEASURED

    @property
    def bridged(self) -> bool:
        return self.status == StepStatus.BRIDGED

    @property
    def has_estimate(self) -> bool:
        """A full pose the filters can use: ``ok``, ``wall`` or ``bridged``, with finite ``R_c1_c2`` and
        ``t_c1_c2_m``."""
        return self._has_estimate

    @property
    def has_rotation(self) -> bool:
        """A rotation the filters can use: every step with an estimate, and ``rotation`` / ``rotation_slow`` steps."""
        return (self.status in WITH_ROTATION and self.R_c1_c2 is not None
                and bool(np.isfinite(self.R_c1_c2).all()))

    @property
    def sigma_t_m(self) -> float:
        """1-sigma of the translation (m); :data:`SIGMA_T_DEFAULT_M` where none was given."""
        return self.sigma_distance_m if np.isfinite(self.sigma_distance_m) else SIGMA_T_DEFAULT_M

    @property
    def sigma_r_rad(self) -> float:
        """1-sigma of the rotation (rad); :data:`SIGMA_R_DEFAULT_RAD` where none was given."""
        return self.sigma_rotation_rad if np.isfinite(self.sigma_rotation_rad) else SIGMA_R_DEFAULT_RAD

    def with_status(self, status: StepStatus | str) -> "StepMotion":
        return replace(self, status=StepStatus(status))

    @classmethod
    def failed(cls, status: StepStatus | str, n_matches: int = 0) -> "StepMotion":
        """A step without an estimate, with its reason."""
        return cls(n_matches=n_matches, status=StepStatus(status))


def motion_from_transform(R_c1_c2, t_c1_c2_m: np.ndarray, n_matches: int = 0, sigma_distance_m: float = NAN,
                          sigma_rotation_rad: float = NAN, status: StepStatus | str = StepStatus.OK) -> StepMotion:
    """A step from a relative pose (``R_c1_c2``: scipy Rotation), with the conventions of
    :mod:`bodyslam.geometry` for the dissertation's quantities (distance signed by the optical-axis direction,
    roll about it, swing as pitch and yaw). The step keeps copies of its own (~0.2 kB; scipy's ``as_matrix`` of one
    rotation is a view that holds ~1.4 kB, 65 MB over a 55,000-frame exam's steps)."""
    from bodyslam.geometry import swing_twist_z

    t = np.array(t_c1_c2_m, float)
    roll, swing = swing_twist_z(R_c1_c2)
    dist = float(np.linalg.norm(t)) * (1.0 if t[2] >= 0 else -1.0)
    return StepMotion(dist, float(roll[0]), float(swing[0, 0]), float(swing[0, 1]), float(np.linalg.norm(swing[0])),
                      n_matches, StepStatus(status), np.array(R_c1_c2.as_matrix(), float), t, sigma_distance_m,
                      sigma_rotation_rad)


def rotation_step(R_c1_c2, n_matches: int, sigma_rotation_rad: float, slow: bool = False) -> StepMotion:
    """A step with only its rotation measured (status ``rotation``, or ``rotation_slow`` where ``slow``: the pair
    overlaps as a slow step does; ``R_c1_c2``: scipy Rotation): roll, pitch, yaw and tilt as
    :func:`motion_from_transform` gives them, distance and translation NaN / None."""
    s = motion_from_transform(R_c1_c2, np.zeros(3), n_matches, NAN, sigma_rotation_rad,
                              StepStatus.ROTATION_SLOW if slow else StepStatus.ROTATION)
    return replace(s, distance_m=NAN, t_c1_c2_m=None)


def lost_to_motion(s: StepMotion) -> bool:
    """A step whose pair ordinary matching lost although guided matching, under forward-motion hypotheses, found
    the wall in both frames (status ``rotation``, :mod:`bodyslam.vision.guided`), or although both frames are rich
    in features (status ``lost``): a step longer than the matcher measures (on the realistic testbed's tuning seeds:
    median 0.68-0.71 cm against 0.20 for the measured ones). A step without an estimate between a dark, blurred or
    featureless frame and the next may be a capsule at rest: not counted; nor is a ``rotation_slow`` step, whose
    pair short-step hypotheses matched best."""
    return s.status in LOST_TO_MOTION


class StepLengths:
    """The lengths of the steps seen so far, as counts in log-spaced bins (constant memory, causal): a percentile
    to within one bin (2.3%: 400 bins over 10 um - 10 cm; lengths outside are counted in the end bins)."""

    LO_M, HI_M, BINS = 1e-5, 0.1, 400

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, np.int64)
        self.n = 0
        self._cached: tuple[int, float, float] | None = None  # (n, q, value)

    def add(self, length_m: float) -> None:
        if not (length_m > 0 and math.isfinite(length_m)):
            return
        b = int(math.log(length_m / self.LO_M) / math.log(self.HI_M / self.LO_M) * self.BINS)
        self.counts[min(max(b, 0), self.BINS - 1)] += 1
        self.n += 1

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (m; the geometric centre of its bin), 0 before any length."""
        if self.n == 0:
            return 0.0
        if self._cached is not None and self._cached[:2] == (self.n, q):
            return self._cached[2]
        b = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n))
        v = self.LO_M * (self.HI_M / self.LO_M) ** ((min(b, self.BINS - 1) + 0.5) / self.BINS)
        self._cached = (self.n, q, v)
        return v

    def lost_length_m(self, floor_m: float = 0.0) -> float:
        """The least length (m) of a step lost to motion: the lengths so far at :data:`LOST_STEP_QUANTILE`, and at
        least ``floor_m`` (:func:`lost_step_floor_m`; 0 before any length and without a floor)."""
        return max(self.percentile(LOST_STEP_QUANTILE), floor_m)

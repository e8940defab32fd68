"""The rotation of a fast step, by matching under motion hypotheses (status ``rotation``, or ``rotation_slow``).

A capsule that jumps ~1 cm in a frame interval (the realistic testbed's fast phases: most of a lumen radius)
leaves frame 1's near wall out of frame 2: Lowe's ratio test over the whole
image keeps ~12 verified matches, too few for the 10-parameter tube fit (status ``too_few_matches``), or a fit
whose distance is uncertain (``uncertain``). Such steps held a fifth of the realistic steps and 43% of the
distance travelled, and each lost its ~8 degrees of roll, which RF cannot see.

Guided matching: for motion hypotheses (forward steps of 4-16 mm, rolls of -16..16 degrees, the tube's axis on
the optical axis; plus the fit of the ordinary matches when there was one), predict where each frame-1 keypoint
lands in frame 2 (:func:`bodyslam.vision.motion.tube_predict`), keep its best descriptor neighbour within a
window around the prediction when it passes a ratio test against the next one there, and verify by a RANSAC
essential matrix. The hypothesis with the most verified matches is fitted by the tube estimator, and matching is
repeated once around that fit with a narrower window.

What it measures (tuning seeds 503-508 of ``realistic``, ``sift`` mode: 220 steps the tube fit failed on,
``docs/RESULTS.md``): the rotation, not the distance. Under forward motion the epipolar lines run radially, so a
forward hypothesis finds matches along them whatever the true distance: the distance comes out biased toward the
hypotheses (mean error 0.48 cm of 0.83) and is not reported. The roll and tilt hold: with at least
:data:`MIN_GUIDED_MATCHES` matches after the second pass (80 in ``sift`` mode: 140 of the 220 steps) the roll
errs 2.4 deg at the 68th percentile (3.8 RMS) and the tilt 2.5, where those steps' true roll is ~11 deg RMS.
The step is written with its rotation, ``distance_m`` NaN, and a 1-sigma that falls with the matches that
verified (:func:`rotation_sigma_rad`).

A rotation step is not always a fast one. A capsule that turns nearly in place in turbid fluid, or against a
featureless stretch of wall, loses its ordinary matches too (session 47: a realistic exam whose 82 steps lost to
matching, 54 of them rotation steps, were filled as a fast phase, its path four times the truth). So the same search
is run under short steps (:data:`SHORT_STEPS_R`): where they verify at least :data:`SLOW_MATCH_RATIO` times the
forward hypotheses' matches, read from frame 1 to 2 and from frame 2 to 1 (a backward step is a forward one read
backward: :data:`MOVING_STEPS_R`), the pair overlaps as a slow step's does and the step is ``rotation_slow``, which
the path's missing-step model and the filters do not count as lost to motion (:func:`bodyslam.steps.lost_to_motion`).
Its rotation is the forward search's, as for any rotation step.

The filters apply the rotation of either kind and treat the translation as unknown: the last estimated step again,
for a ``rotation`` step stretched to the estimated steps so far at their 90th percentile (a step matching loses
is a long one), with that length as 1-sigma (:func:`bodyslam.fusion.ekf.step_noise`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel
from bodyslam.steps import StepMotion, rotation_step
from bodyslam.vision.matching import Matcher, Matches, squared_distances
from bodyslam.vision import motion  # its _tube_c: the compiled loops (None where not built)
from bodyslam.vision.motion import fit_tube, tube_predict

__all__ = ["estimate_rotation", "hypotheses", "short_hypotheses", "guided_matches", "descriptor_distances",
           "MIN_GUIDED_MATCHES", "SHORT_STEPS_R", "SLOW_MATCH_RATIO",
           "rotation_sigma_rad"]

# fewer verified guided matches than this after the second pass: no estimate, per matcher mode (the count a wrong
# hypothesis reaches along the radial epipolar lines grows with the keypoints). Chosen on the tuning seeds
# (420x420 frames). ``sift`` (3000 keypoints; 220 failed steps): the roll error's RMS is 11.9 deg for counts of
# 65-80 (74 steps; the true roll is ~11 deg RMS), 5.7 for 80-100 (58), 1.7 for 100-150 (52), 0.4 above (30).
# ``fast`` (800 keypoints at 0.7 scale; 332 failed steps, FT/FL not classified): 14.9 deg for 30-40 (35), 10.9
# for 40-50 (159), 4.7 for 50-65 (86), 0.3 above (51). ``asift`` keeps 3000 keypoints as ``sift`` does and takes
# its threshold (not measured separately). Below these a step carries no information and would break the stated
# 1-sigma. ``fast`` with its rescue (the default: bodyslam.vision.matching) matches the rescue's full-frame
# keypoints, ``sift``'s budget, at ``sift``'s threshold; ``fast``'s own is for ``--no-rescue``
MIN_GUIDED_MATCHES = {"sift": 80, "asift": 80, "fast": 50}
# 1-sigma of a rotation step's rotation (rotation_sigma_rad): SIGMA_AT_MIN_RAD * (n / threshold) ** -SIGMA_POWER,
# at least SIGMA_FLOOR_RAD. Fitted on realistic tuning seeds 503-509 (sift mode, 248 rotation steps): the error
# angle's 68th percentile over 1.878 (the 3-D 68% radius) is 6.0 / 3.7 / 2.2 / 1.8 / 0.84 deg for 80-90 /
# 90-100 / 100-120 / 120-160 / 160+ verified matches; this gives 5.5 / 4.1 / 2.7 / 1.4 / 0.7. Sessions 12-25 stated
# 4 deg for every step (the steps' roll error at its 68th percentile), over-trusting the few-match steps that hold
# most of the gross errors (36% over 10 deg at 80-90 matches) and under-trusting the many-match ones
SIGMA_AT_MIN_RAD, SIGMA_POWER, SIGMA_FLOOR_RAD = math.radians(6.5), 2.7, math.radians(0.5)
# windows around the prediction, as angles at the image centre (x the camera's pixels per radian): ~30 px and
# ~12 px on the testbed's 420 px frames
WINDOW_RAD, REFINE_WINDOW_RAD = 0.19, 0.08
RATIO = 0.9  # Lowe's ratio against the next neighbour inside the window (the window already excludes most)
# The window's pairs compiled (``_tube_fit.guided_pairs``): the same pairs as :func:`_window_pairs_numpy`, whose
# kd-tree and arrays of every candidate pair took ~6 ms a hypothesis on fast mode's 3,000 rescue keypoints (thesis
# motion; session 67). False: numpy's.
GUIDED_COMPILED = True
# A rotation step is ``rotation_slow`` (not lost to motion) where the short-step hypotheses (SHORT_STEPS_R lumen radii,
# the same rolls) verify at least SLOW_MATCH_RATIO times the matches the forward ones verify (each the best of its
# set, on the first pass's window). Chosen on realistic tuning renders (session 48, fast mode, ``bodyslam batch``'s
# defaults): at a real exam's pace (587-590, 45 rotation steps, true 0.09 lumen radii at the median) the short
# hypotheses verify 1.09 times the forward ones' matches at the median and >= 1.1 times on 49% of the steps; at the
# dissertation's pace (595-598, 117 rotation steps, true 0.65 radii) 0.89 times, >= 1.1 on 4%. Ratio 1.0 / 1.1 / 1.2:
# the path's mean absolute error at the runs' ends, recomputed from their motion.csv, slow 43.9% (as shipped
# before) -> 18.3 / 23.9 / 32.3%, fast 16.6% -> 20.9 / 17.1 / 16.7%; through ``bodyslam batch`` at 1.1: slow 45 ->
# 31%, fast 16.6 -> 16.9% (docs/RESULTS.md, "A slow turn told from a fast step")
SHORT_STEPS_R = (0.0, 0.08, 0.16)
SLOW_MATCH_RATIO = 1.1
# The fast steps' hypotheses: forward steps of these lumen radii (4-16 mm at the 12.5 mm prior). A capsule also moves
# backward (the dissertation's Sec. 4.1; the testbed's ``backward`` phase), and read from frame 1 to 2 only, a fast
# step backward overlaps as a rest does: its near wall stays in the short steps' windows, which won and called it
# ``rotation_slow``, so a clip and the same clip reversed were read differently (the real clip of four frames at
# hand: 1.4 cm forwards, 0.7 reversed). So the slow test reads the pair both ways (session 55): a step is slow when
# the short steps win from frame 1 to 2 and from frame 2 to 1, where a backward step is a forward one
# (docs/RESULTS.md, "Guided matching read both ways"). Backward hypotheses in the rotation's search were tried and
# dropped: a backward step has the same epipolar lines as the forward one, and where the forward search found no
# rotation the backward sets verified 80-102 matches on forward steps and fitted rotations 5-28 deg off.
MOVING_STEPS_R = (0.32, 0.64, 0.96, 1.28)


def hypotheses(radius_m: float, steps_r=MOVING_STEPS_R) -> list[np.ndarray]:
    """Tube-model 10-vectors (:func:`bodyslam.vision.motion.fit_tube`) of the motion hypotheses: forward steps of
    ``steps_r`` lumen radii (:data:`MOVING_STEPS_R`, 0.3-1.3: 4-16 mm at the 12.5 mm prior) by rolls of -16, -8, 0,
    8, 16 deg, axis on the optical axis."""
    out = []
    for d in np.asarray(steps_r, float) * radius_m:
        for roll in np.radians([-16.0, -8.0, 0.0, 8.0, 16.0]):
            x = np.zeros(10)
            x[2], x[5] = roll, d
            out.append(x)
    return out


def short_hypotheses(radius_m: float) -> list[np.ndarray]:
    """:func:`hypotheses` of a capsule nearly in place: steps of 0, 0.08 and 0.16 lumen radii (0-2 mm at the prior),
    the same rolls (:data:`SLOW_MATCH_RATIO`)."""
    return hypotheses(radius_m, SHORT_STEPS_R)


def descriptor_distances(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Euclidean distances ``(n1, n2)`` between two sets of descriptors, float32
    (:func:`~bodyslam.vision.matching.squared_distances`, then the root in place: 3000 x 3000 SIFT descriptors take
    ~0.033 s on one thread and ~72 MB)."""
    sq = squared_distances(np.asarray(d1, np.float32), np.asarray(d2, np.float32))
    return np.sqrt(sq, out=sq)


def guided_matches(matcher: Matcher, pts1: np.ndarray, pts2: np.ndarray, tree: cKDTree | None, dist12: np.ndarray,
                   params: np.ndarray, camera: CameraModel, radius_m: float, window_rad: float,
                   min_sep_px: float = 2.0, level: str = "default") -> Matches:
    """Verified matches under the motion ``params``: each frame-1 keypoint (``pts1``) takes the nearest
    descriptor (``dist12``: :func:`descriptor_distances`) among the frame-2 keypoints (``pts2``; ``tree``, their
    kd-tree, is used where numpy finds the pairs, and built there when None) within ``window_rad`` (x the camera's focal length in pixels) of its predicted position, if that passes the
    ratio test against the next one there that is a different point (more than ``min_sep_px`` away)."""
    p1, p2 = guided_candidates(pts1, pts2, tree, dist12, params, camera, radius_m, window_rad, min_sep_px)
    if len(p1) == 0:
        return Matches(np.zeros((0, 2)), np.zeros((0, 2)), 0)
    return matcher.verify(p1, p2, level)


def guided_candidates(pts1: np.ndarray, pts2: np.ndarray, tree: cKDTree | None, dist12: np.ndarray,
                      params: np.ndarray, camera: CameraModel, radius_m: float, window_rad: float,
                      min_sep_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`guided_matches` before verification: the matched points ``(p1, p2)``, one per frame-2 point; empty
    when fewer than 8."""
    uv, vis = tube_predict(params, pts1, camera, radius_m)
    rows = np.nonzero(vis & np.isfinite(uv).all(axis=1))[0]
    empty = np.zeros((0, 2)), np.zeros((0, 2))
    if len(rows) < 8:
        return empty
    if _pairs_compiled():
        out_i, out_j = np.empty(len(rows), np.int64), np.empty(len(rows), np.int64)
        k = motion._tube_c.guided_pairs(np.ascontiguousarray(uv[rows], np.float64), rows.astype(np.int64),
                                        np.ascontiguousarray(pts2, np.float64),
                                        np.ascontiguousarray(dist12, np.float32), window_rad * float(camera.fx),
                                        float(min_sep_px), float(RATIO), out_i, out_j)
        p1, p2 = pts1[out_i[:k]], pts2[out_j[:k]]
    else:
        p1, p2 = _window_pairs_numpy(pts1, pts2, tree, dist12, uv, rows, window_rad * float(camera.fx), min_sep_px)
    if len(p1) < 8:
        return empty
    _, keep = np.unique(np.round(p2, 1), axis=0, return_index=True)  # one match per frame-2 point
    keep = np.sort(keep)
    return p1[keep], p2[keep]


def _pairs_compiled() -> bool:
    """Whether the window's pairs are found by ``_tube_fit.guided_pairs`` (built, and :data:`GUIDED_COMPILED`)."""
    return GUIDED_COMPILED and motion._tube_c is not None and hasattr(motion._tube_c, "guided_pairs")


def _window_pairs_numpy(pts1: np.ndarray, pts2: np.ndarray, tree: cKDTree | None, dist12: np.ndarray,
                        uv: np.ndarray, rows: np.ndarray, window_px: float,
                        min_sep_px: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`guided_candidates`' pairs in numpy (``_tube_fit.guided_pairs`` where it is built): per predicted
    keypoint the best descriptor in its window if it passes the ratio test, ``(p1, p2)`` in keypoint order.
    ``tree``: ``pts2``'s kd-tree (None: built here)."""
    empty = np.zeros((0, 2)), np.zeros((0, 2))
    tree = cKDTree(pts2) if tree is None else tree
    # Candidate pairs (frame-1 keypoint i, frame-2 keypoint j) within the window, as arrays, grouped by i (a stable
    # sort: j ascending inside a group); per group the nearest descriptor (ties: the lower j) and the nearest
    # among the other points. Written with reductions over the groups: a list per keypoint from query_ball_point
    # and a three-key sort took ~4x as long on ASIFT's 3000 keypoints (~160k pairs per hypothesis).
    pairs = cKDTree(uv[rows]).sparse_distance_matrix(tree, window_px, output_type="ndarray")
    if len(pairs) == 0:
        return empty
    i = rows[pairs["i"]]
    # a stable sort on 16-bit keys is numpy's radix sort: ~10x faster than on int64, the same order
    o = np.argsort(i.astype(np.int16) if len(pts1) <= np.iinfo(np.int16).max else i, kind="stable")
    i, j = i[o], pairs["j"][o]
    # gathers on flat and 1-D arrays: the same values as dist12[i, j] and pts2[j], faster (a candidate
    # list took 14.7 ms per hypothesis on 3000 keypoints a frame, 11.2 so, alternated on realistic tuning seed 561;
    # its motion.csv byte-identical)
    dist = np.take(dist12.reshape(-1), i * dist12.shape[1] + j)
    starts = np.r_[0, np.nonzero(np.diff(i))[0] + 1]
    size = np.diff(np.r_[starts, len(i)])
    best_d = np.minimum.reduceat(dist, starts)
    best_j = np.minimum.reduceat(np.where(dist == np.repeat(best_d, size), j, len(pts2)), starts)
    # the next candidate of the same keypoint that is a different point (more than min_sep_px away): its distance
    x2, y2 = np.ascontiguousarray(pts2[:, 0]), np.ascontiguousarray(pts2[:, 1])
    bj = np.repeat(best_j, size)
    dx, dy = x2[j] - x2[bj], y2[j] - y2[bj]
    other = np.sqrt(dx * dx + dy * dy) > min_sep_px
    second = np.minimum.reduceat(np.where(other, dist, np.inf), starts)
    good = best_d < RATIO * second
    return pts1[i[starts][good]], pts2[best_j[good]]


def estimate_rotation(matcher: Matcher, f1, f2, camera: CameraModel, radius_m: float,
                      start: np.ndarray | None = None) -> StepMotion | None:
    """The rotation of a step the ordinary matches could not fit (module docstring), as a step with status
    ``rotation``; None when guided matching finds fewer than :data:`MIN_GUIDED_MATCHES` (the matcher mode's; in
    fast mode with its rescue, :attr:`~bodyslam.vision.matching.Matcher.rescue`, the keypoints are the rescue's
    full-frame ones, ``sift`` mode's budget, and so is the threshold). ``start``: the ordinary fit's 10-vector,
    when there was one (an ``uncertain`` step), tried beside the hypotheses."""
    level = "full" if matcher.rescue else "default"
    min_matches = MIN_GUIDED_MATCHES["sift" if level == "full" else matcher.mode]
    (pts1, d1), (pts2, d2) = matcher.keypoints(f1, level), matcher.keypoints(f2, level)
    if d1 is None or d2 is None or len(pts1) < min_matches or len(pts2) < min_matches:
        return None
    # the frame-2 keypoints' kd-tree only where numpy finds the window's pairs
    tree, dist12 = (None if _pairs_compiled() else cKDTree(pts2)), descriptor_distances(d1, d2)

    def matches(x, window_rad):
        return guided_matches(matcher, pts1, pts2, tree, dist12, x, camera, radius_m, window_rad, level=level)

    forward = hypotheses(radius_m)
    starts = ([] if start is None else [np.asarray(start, float)]) + forward

    def candidates(xs):
        return [guided_candidates(pts1, pts2, tree, dist12, x, camera, radius_m, WINDOW_RAD) for x in xs]

    cands = candidates(starts)
    best, best_h = _most_verified(matcher, cands, level)
    _, x = fit_tube(best, camera, radius_m, min_matches=8, max_sigma_distance_m=math.inf, start="rotation")
    if x is None:
        return None
    refined = matches(x, REFINE_WINDOW_RAD)
    if len(refined) < min_matches:
        return None
    s, x = fit_tube(refined, camera, radius_m, min_matches=8, max_sigma_distance_m=math.inf,
                    start="rotation")
    if x is None:
        return None
    # does the pair overlap as a slow step does? The short-step hypotheses against the forward ones, on the first
    # pass's window (the rotation above is the forward search's either way) ...
    n_forward = len(best) if start is None or best_h > 0 else len(_most_verified(matcher, cands[1:], level)[0])
    n_short = len(_most_verified(matcher, candidates(short_hypotheses(radius_m)), level)[0])
    slow = n_short >= SLOW_MATCH_RATIO * n_forward
    if slow:  # ... read both ways: a step backward overlaps as a rest does when read forward (MOVING_STEPS_R)
        tree1, dist21 = (None if _pairs_compiled() else cKDTree(pts1)), np.ascontiguousarray(dist12.T)

        def reversed_best(xs):
            c = [guided_candidates(pts2, pts1, tree1, dist21, x, camera, radius_m, WINDOW_RAD) for x in xs]
            return len(_most_verified(matcher, c, level)[0])

        slow = reversed_best(short_hypotheses(radius_m)) >= SLOW_MATCH_RATIO * reversed_best(hypotheses(radius_m))
    return rotation_step(Rotation.from_matrix(s.R_c1_c2), len(refined), rotation_sigma_rad(len(refined), min_matches),
                         slow=slow)


def _most_verified(matcher: Matcher, cands: list, level: str) -> tuple[Matches, int]:
    """The first candidate set (in list order) with the most verified matches, and its index (``len(cands)`` and
    no matches when none verifies). Verification (a RANSAC per set) is the cost, and it can only remove matches:
    sets are verified in decreasing order of their candidates, and only while one could still win."""
    best, best_h = Matches(np.zeros((0, 2)), np.zeros((0, 2)), 0), len(cands)
    for h in sorted(range(len(cands)), key=lambda h: (-len(cands[h][0]), h)):
        n = len(cands[h][0])
        if n == 0 or n < len(best) or (n == len(best) and h > best_h):
            break
        m = matcher.verify(*cands[h], level=level)
        if len(m) > len(best) or (len(m) == len(best) and h < best_h):
            best, best_h = m, h
    return best, best_h


def rotation_sigma_rad(n_matches: int, min_matches: int) -> float:
    """The stated 1-sigma (rad, largest axis) of a rotation step that ``n_matches`` guided matches verified, the
    mode's threshold being ``min_matches`` (:data:`MIN_GUIDED_MATCHES`; the fit above)."""
    return max(SIGMA_AT_MIN_RAD * (n_matches / min_matches) ** -SIGMA_POWER, SIGMA_FLOOR_RAD)

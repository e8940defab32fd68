"""Per-step capsule motion from matched features (dissertation Sec. 3.2.4-3.2.5).

Two estimators, same output (:class:`StepMotion`, conventions of :mod:`bodyslam.geometry`):

``thesis`` -- the dissertation's equations, with their signs derived:
  - distance (Eq. 3.12-3.15): a wall point at axial distance ``D`` has angular depth ``theta1 = atan(R / D)``;
    after moving forward by ``d`` it has ``theta2 = atan(R / (D - d))``. Hence ``d = R / tan(theta1) -
    R / tan(theta2)``. Eq. 3.14 as printed, ``R / tan(theta2) (1 - tan(theta2) / tan(theta1))``, equals
    ``R / tan(theta2) - R / tan(theta1) = -d``: its sign is wrong (forward motion would come out negative).
    The step is the mean over features (Eq. 3.15).
  - roll (Eq. 3.22): the mean change of the features' azimuth around the image centre. When the capsule rolls
    by ``+gamma`` about its optical axis the scene turns by ``-gamma`` in its image, so ``gamma = -mean(dphi)``;
    Eq. 3.22 as printed returns the scene's turn (opposite sign).
  - tilt (Eq. 3.19-3.21): the thesis compares the angular-depth changes of two feature groups P and Q and takes
    ``phi = (dQ - dP) / max(dP, dQ)`` (Eq. 3.20). That ratio does not scale with the tilt: for a pure tilt by
    ``phi`` toward Q, ``dQ = -dP`` and the ratio is -2 whatever ``phi`` is. Derived instead, in the same unrolled
    domain: a small rotation (pitch ``wx``, yaw ``wy``) changes a ray's angular depth by
    ``wx sin(psi) - wy cos(psi)`` at azimuth ``psi``, so a least-squares sinusoid fit of the features' ``d theta``
    against their azimuth gives pitch and yaw (forward motion adds an azimuth-independent part).
  ``literal_signs=True`` reproduces the printed equations exactly: Eq. 3.14's and Eq. 3.22's signs, and
  Eq. 3.20-3.21 with 8 azimuth sectors (P: largest mean change, Q: smallest, tilt direction = Q's azimuth).

``tube`` -- the project's estimator: a full 6-DOF solve that uses what the thesis assumes but does not exploit,
  that matched points lie on a tube of known radius ``R``. Unknowns: the motion ``T_c1_c2`` (6) and the tube's
  axis in frame 1 (direction: 2, offset: 2). Each feature's ray in frame 1 meets the cylinder at a point ``X``
  (closed form); ``X`` seen from frame 2 must lie along the feature's ray there. Robust (soft-L1) nonlinear least
  squares on the ray-angle residuals, weak priors keep the axis near the optical axis when motion does not
  determine it (a stopped capsule). Scale comes from ``R``; the capsule can be off-centre and tilted. The fit
  starts from the essential matrix's rotation and direction of translation (:func:`essential_start`): from a pure
  rotation it fell into minima that trade translation for tilt.

Status values (``StepMotion.status``): ``ok``; ``too_few_matches`` (fewer than ``min_matches`` verified
matches); ``wall`` and ``no_lumen`` (a frame of the pair faces the wall: fitted with a wider 1-sigma, or not
used; set by the caller, :meth:`bodyslam.vision.odometry.VisualOdometry.estimate_wall`);
``solver_failed``; ``uncertain`` (the fit's 1-sigma distance uncertainty exceeds ``max_sigma_distance_m``,
1 mm by default, a quarter of the mean step: few or badly spread matches after a large jump); ``bad_frame`` (a frame of the pair could not be read; set by the sequence reader). Rows without an estimate carry NaN, never an invented number.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from bodyslam.camera import CameraModel
from bodyslam.errors import ConfigError
from bodyslam.geometry import rotvec_to_matrix
from bodyslam.vision.matching import Matches, essential_ransac
from bodyslam.steps import StepMotion, motion_from_transform  # noqa: F401  (re-exported)
from bodyslam.vision.unroll import Unroller

__all__ = ["ESTIMATORS", "StepMotion", "essential_start", "estimate_thesis", "estimate_tube", "fit_tube",
           "tube_predict", "axis_tilt_rad", "camera_off_axis_radii", "motion_from_transform"]

from bodyslam.choices import ESTIMATORS  # noqa: E402

log = logging.getLogger(__name__)

try:  # the tube fit's residuals compiled (setup.py builds them where a C compiler is at hand); else numpy's
    from bodyslam.vision import _tube_fit as _tube_c
except ImportError:
    _tube_c = None
_warned = False
# The robust Levenberg-Marquardt loop compiled too (``_tube_fit.lm``, :func:`lm_compiled`): the numpy loop took
# ~2.5 ms a fit, 0.4 of it in the compiled residuals (576-px realistic exam, fast mode, 3,195 fits; session 67).
# The same loop, the same decisions; only the order of a few sums differs (tests/bodyslam/vision/test_motion.py
# compares the two). False: the numpy loop (:func:`_lm_soft_l1`) wherever it is built.
LM_COMPILED = True

NAN = float("nan")


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def estimate_thesis(m: Matches, unroller: Unroller, radius_m: float, min_matches: int = 8,
                    literal_signs: bool = False, sectors: int = 8) -> StepMotion:
    """The dissertation's estimator (module docstring), angles from ``unroller`` (its mode picks Eq. 3.11)."""
    n = len(m)
    if n < min_matches:
        return StepMotion(n_matches=n, status="too_few_matches")
    phi1, th1 = unroller.angles(m.pts1_px)
    phi2, th2 = unroller.angles(m.pts2_px)
    ok = (th1 > 1e-3) & (th2 > 1e-3) & (th1 < np.pi / 2) & (th2 < np.pi / 2)
    if ok.sum() < min_matches:
        return StepMotion(n_matches=int(ok.sum()), status="too_few_matches")
    phi1, th1, phi2, th2 = phi1[ok], th1[ok], phi2[ok], th2[ok]
    d_i = radius_m / np.tan(th1) - radius_m / np.tan(th2)  # derived; Eq. 3.14 as printed is -d_i
    distance = float(np.mean(d_i)) * (-1.0 if literal_signs else 1.0)
    dphi = _wrap(phi2 - phi1)
    roll = float(np.mean(dphi)) * (1.0 if literal_signs else -1.0)
    dth = th2 - th1
    if not literal_signs:
        # Derived tilt: a small rotation (pitch wx, yaw wy) changes the angular depth of a ray at azimuth psi by
        # d(theta) = wx sin(psi) - wy cos(psi); forward motion adds a part that does not depend on psi. A least-
        # squares fit of d(theta) = a + c sin(psi) + b cos(psi) over the features gives wx = c, wy = -b.
        A = np.c_[np.ones_like(phi1), np.sin(phi1), np.cos(phi1)]
        (_, c, b), *_ = np.linalg.lstsq(A, dth, rcond=None)
        pitch, yaw = float(c), float(-b)
        return StepMotion(distance, roll, pitch, yaw, float(math.hypot(pitch, yaw)), int(ok.sum()), "ok")
    sector = np.floor(np.mod(phi1, 2 * np.pi) / (2 * np.pi / sectors)).astype(int)
    means = np.array([dth[sector == k].mean() if np.any(sector == k) else np.nan for k in range(sectors)])
    if np.sum(np.isfinite(means)) < 2:
        return StepMotion(distance_m=distance, roll_rad=roll, n_matches=int(ok.sum()), status="ok")
    kP, kQ = int(np.nanargmax(means)), int(np.nanargmin(means))
    dP, dQ = means[kP], means[kQ]
    denom = max(dP, dQ)
    phi_t = (dQ - dP) / denom if abs(denom) > 1e-12 else 0.0  # Eq. 3.20
    psi = (kQ + 0.5) * 2 * np.pi / sectors  # direction of tilting: the group with the smallest change
    pitch, yaw = phi_t * math.cos(psi), phi_t * math.sin(psi)  # Eq. 3.21 as printed
    return StepMotion(distance, roll, float(pitch), float(yaw), float(math.hypot(pitch, yaw)), int(ok.sum()), "ok")


def _tube_points_xyz(P: np.ndarray, b1: np.ndarray, radius: float, max_depth: float) -> tuple[np.ndarray, ...]:
    """Where frame-1 rays ``b1 (n, 3)`` meet the tube, in frame 2's axes, for a batch of parameter vectors
    ``P (B, 10)``: the coordinates ``(x, y, z)``, each ``(B, n)`` (depth capped at ``max_depth``). Written on
    coordinate arrays, not 3-vectors: the fit evaluates it ~20 times on ~11 x 150 rays, where numpy's per-call
    cost, not arithmetic, is the time (the fit's batched Jacobian 0.24 ms against 0.48 with stacked vectors and
    einsum)."""
    R = rotvec_to_matrix(P[:, 0:3])
    ax, ay = P[:, 6:7], P[:, 7:8]
    inv = 1.0 / np.sqrt(ax * ax + ay * ay + 1.0)
    ax, ay, az = ax * inv, ay * inv, inv  # the axis direction (ax, ay, 1), normalised, (B, 1) each
    ox, oy = P[:, 8:9], P[:, 9:10]  # the axis's offset (ox, oy, 0)
    bx, by, bz = b1[:, 0], b1[:, 1], b1[:, 2]
    # ray-cylinder depth: |lam w - u| = R with w = b x a, u = o x a
    wx, wy, wz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
    ux, uy, uz = oy * az, -ox * az, ox * ay - oy * ax
    ww = wx * wx + wy * wy + wz * wz
    wu = wx * ux + wy * uy + wz * uz
    disc = wu * wu - ww * (ux * ux + uy * uy + uz * uz - radius * radius)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (wu + np.sqrt(np.maximum(disc, 0.0))) / ww
    lam = np.where(np.isfinite(lam) & (lam > 0), np.minimum(lam, max_depth), max_depth)
    Xx, Xy, Xz = lam * bx - P[:, 3:4], lam * by - P[:, 4:5], lam * bz - P[:, 5:6]
    c = R[:, :, :, None]  # rows of the result: R^T (X - t)
    return (c[:, 0, 0] * Xx + c[:, 1, 0] * Xy + c[:, 2, 0] * Xz,
            c[:, 0, 1] * Xx + c[:, 1, 1] * Xy + c[:, 2, 1] * Xz,
            c[:, 0, 2] * Xx + c[:, 1, 2] * Xy + c[:, 2, 2] * Xz)


def _tube_residuals_batch(P: np.ndarray, b1: np.ndarray, b2: np.ndarray, radius: float, max_depth: float,
                          noise_rad: float, prior_sigma: np.ndarray) -> np.ndarray:
    """Residuals of the tube model for a batch of parameter vectors ``P (B, 10)`` -> ``(B, 3 n + 4)``: per
    match the cross product of its frame-2 ray with the direction to its tube point (the sine of their angle),
    over ``noise_rad``; then the axis priors. Compiled where ``_tube_fit.c`` was built (the same formulas, ~1e-15
    relative; a whole fit, its essential-matrix start included, 7.7 -> 3.5-3.9 ms on exam frames), else numpy."""
    if _tube_c is not None:
        out = np.empty((len(P), 3 * len(b1) + 4))
        _tube_c.residuals(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(b1, np.float64),
                          np.ascontiguousarray(b2, np.float64), float(radius), float(max_depth), float(noise_rad),
                          np.ascontiguousarray(prior_sigma, np.float64), out)
        return out
    global _warned
    if not _warned:
        _warned = True
        log.info("tube fit: the compiled residuals (bodyslam/vision/_tube_fit.c) are not built here; using numpy's, "
                 "~2x slower fits (reinstall with a C compiler: pip install -e .)")
    return _tube_residuals_numpy(P, b1, b2, radius, max_depth, noise_rad, prior_sigma)


def _tube_residuals_numpy(P: np.ndarray, b1: np.ndarray, b2: np.ndarray, radius: float, max_depth: float,
                          noise_rad: float, prior_sigma: np.ndarray) -> np.ndarray:
    """:func:`_tube_residuals_batch` in numpy."""
    x, y, z = _tube_points_xyz(P, b1, radius, max_depth)
    inv = 1.0 / (noise_rad * np.sqrt(x * x + y * y + z * z))
    cx, cy, cz = b2[:, 0], b2[:, 1], b2[:, 2]
    r = np.stack([(cy * z - cz * y) * inv, (cz * x - cx * z) * inv, (cx * y - cy * x) * inv], axis=-1)
    return np.concatenate([r.reshape(len(P), -1), P[:, 6:10] / prior_sigma], axis=1)


# The tube fit's start (:func:`essential_start`): the translation's length, in lumen radii, along the direction
# the essential matrix gives. The fit's cost has several minima where the capsule both turns and moves (a
# forward step read as a tilt, or no translation and a larger turn). Started from a pure rotation, as it was to
# session 17, it converged to those on some steps. Measured in session 18 on realistic tuning seeds 503-509
# (`bodyslam motion`, then `testbed evaluate realistic --reuse`): Table 4.1 tilt error 0.843 -> 0.777 deg, roll
# 0.302 -> 0.289 deg, distance 0.0745 -> 0.0717 cm; smoothed localization 3.93 -> 3.73 cm (the guard below
# changes no start on those seeds). On thesis seed 7 (300 frames, 320 px, sift): tilt 0.137 -> 0.110 deg, roll
# 0.039 -> 0.028, distance 0.0052 -> 0.0053 cm. 0.3 radii is the middle of the steps seen; 0.1-0.8 gave the same
# within 0.02 deg. Guided matching's fits keep the pure-rotation start: with this one, the rotation steps' roll
# error rose from 3.77 to 4.18 deg mean on the same seeds.
ESSENTIAL_START_STEP = 0.3
# An essential matrix has two rotations 180 degrees apart about its translation (the "twisted pair"). On a
# stationary step the translation is noise, and the cheirality test can pick the wrong one. That start made the
# fit converge to a roll of ~180 degrees on 3 of 199 steps of thesis seed 709, and the fused track then erred by
# 4 cm. A start more than 90 degrees from the pure rotation that best aligns the rays is therefore refused. Real
# departures between the two, from parallax, were at most 39 degrees on realistic tuning seeds 503-509.
ESSENTIAL_START_MAX_TURN_RAD = math.radians(90.0)


def essential_start(b1: np.ndarray, b2: np.ndarray, step_m: float,
                    near: Rotation | None = None) -> np.ndarray | None:
    """A start for :func:`fit_tube` from matched unit rays ``b1``, ``b2`` (n, 3): the rotation and the direction
    of translation of the essential matrix (OpenCV's USAC, the 0.5 degree threshold of the matcher's check, the
    cheirality test of ``recoverPose``), the translation ``step_m`` long, the tube's axis on the optical axis.
    None when fewer than 8 rays lie in front of both cameras, no essential matrix is found, or its rotation lies
    more than :data:`ESSENTIAL_START_MAX_TURN_RAD` from ``near`` (``R_c1_c2`` of the pure-rotation alignment:
    the wrong one of the twisted pair)."""
    E, x1, x2, used, inliers = essential_ransac(b1, b2, np.radians(0.5))
    if E is None or E.shape[0] < 3 or E.shape[1] != 3:
        return None
    mask = inliers[used].astype(np.uint8).reshape(-1, 1)
    _, R, t, _ = cv2.recoverPose(E[:3], x1, x2, focal=1.0, pp=(0.0, 0.0), mask=mask)
    # OpenCV's (R, t) map frame-1 points into frame 2: X2 = R X1 + t, so R_c1_c2 = R^T and t_c1_c2 = -R^T t
    t12 = -(R.T @ t).ravel()
    n = float(np.linalg.norm(t12))
    if not (np.all(np.isfinite(R)) and n > 0):
        return None
    R12 = Rotation.from_matrix(R.T)
    if near is not None and (R12 * near.inv()).magnitude() > ESSENTIAL_START_MAX_TURN_RAD:
        return None
    p0 = np.zeros(10)
    p0[0:3] = R12.as_rotvec()
    p0[3:6] = t12 / n * step_m
    return p0


def _soft_l1_cost(f: np.ndarray, f_scale: float) -> float:
    """``0.5 sum rho(f^2)`` with scipy's ``soft_l1`` at ``f_scale``: the cost :func:`_lm_soft_l1` lowers."""
    c2 = f_scale * f_scale
    return float(c2 * np.sum(np.sqrt(1.0 + f * f / c2) - 1.0))  # rho = 2 c2 (sqrt(1 + z / c2) - 1)


def _lm_soft_l1(p0: np.ndarray, fun_jac, fun, x_scale: np.ndarray, f_scale: float, max_iter: int = 100,
                xtol: float = 1e-5, ftol: float = 1e-5):
    """Levenberg-Marquardt on the robust cost ``0.5 sum rho(f^2)``, ``rho`` scipy's ``soft_l1`` (iteratively
    reweighted: the Gauss-Newton system with weights ``rho'(f^2)``), steps damped in the ``x_scale`` metric.

    The problem of ``least_squares(..., loss="soft_l1", x_scale=...)``, written out because scipy's trust-region
    solver spends milliseconds of Python per call on these 10-parameter problems (a fit is a fifth of a frame's
    budget in fast mode). It stops when a step lowers the cost by less than ``ftol`` of it or moves the
    parameters by less than ``xtol`` (scaled): with 1e-5 it takes 4.3 ms per fit against scipy's 8.9 and lands
    within 0.6 um and 0.002 deg of scipy's solution on 120 testbed pairs (errors of the estimate itself: ~40 um,
    ~0.1 deg). ``fun_jac(p) -> (f, J)``, ``fun(p) -> f``. Returns ``(p, f, J, cost)`` with
    ``J`` scaled as scipy scales it for a robust loss (``J^T J`` approximates the cost's Hessian: rows times
    ``(rho' + 2 rho'' f^2)^0.5 = (1 + f^2/c^2)^-0.75`` for soft-L1), so covariances are the same as before.
    """
    c2 = f_scale * f_scale
    p = p0.copy()
    f, J = fun_jac(p)
    cost = _soft_l1_cost(f, f_scale)
    D = 1.0 / (x_scale * x_scale)
    lam = 1e-1  # conservative first steps: from 1e-3 one hard pair in 120 jumped to a worse minimum

    def robust_jac(f, J):
        return J * ((1.0 + f * f / c2) ** -0.75)[:, None]

    for _ in range(max_iter):
        w = 1.0 / np.sqrt(1.0 + f * f / c2)
        JW = J * w[:, None]
        A = J.T @ JW
        g = JW.T @ f
        while True:
            try:
                step = -np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), D)), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e12:
                    return p, f, robust_jac(f, J), cost
                continue
            f_new = fun(p + step)
            cost_new = _soft_l1_cost(f_new, f_scale)
            if np.isfinite(cost_new) and cost_new < cost:
                break
            lam *= 10.0
            if lam > 1e12:
                return p, f, robust_jac(f, J), cost
        p = p + step
        done = (cost - cost_new) < ftol * cost or np.linalg.norm(step / x_scale) < xtol * (
            np.linalg.norm(p / x_scale) + xtol)
        f, J = fun_jac(p)
        cost = cost_new
        lam = max(lam / 10.0, 1e-9)
        if done:
            break
    return p, f, robust_jac(f, J), cost


def lm_compiled(model: int, p0: np.ndarray, k: int, b1: np.ndarray, b2: np.ndarray, radius: float, max_depth: float,
                noise_rad: float, prior_sigma: np.ndarray, x_scale: np.ndarray, h: np.ndarray, f_scale: float,
                grid: np.ndarray | None = None, ring: np.ndarray | None = None, max_iter: int = 100,
                xtol: float = 1e-5, ftol: float = 1e-5):
    """:func:`_lm_soft_l1` in C on one of the two models, its forward-difference Jacobian included: ``model`` 0 the
    cylinder (:func:`_tube_residuals_batch`, 10 parameters), 1 the ringed tube
    (:func:`bodyslam.vision.lumen_scale._ring_residuals`, 12; ``grid`` and ``ring`` as there). Only the first ``k``
    parameters of ``p0`` are fitted (steps ``h``, scales ``x_scale``, both ``(k,)``); the others stay as given.
    Returns ``(p[:k], f, J, cost)`` as :func:`_lm_soft_l1` does; None where the compiled loop is not built or
    :data:`LM_COMPILED` is off (the caller then runs :func:`_lm_soft_l1`)."""
    if not (LM_COMPILED and _tube_c is not None and hasattr(_tube_c, "lm")):
        return None
    p = np.array(p0, np.float64)  # a copy: the loop writes the solution into it
    m = 3 * len(b1) + (4 if model == 0 else 6)
    f, J = np.empty(m), np.empty((m, k))
    empty = np.empty(0)
    cost = _tube_c.lm(int(model), p, int(k), np.ascontiguousarray(b1, np.float64),
                      np.ascontiguousarray(b2, np.float64), float(radius), float(max_depth), float(noise_rad),
                      np.ascontiguousarray(prior_sigma, np.float64),
                      empty if grid is None else np.ascontiguousarray(grid, np.float64),
                      empty if ring is None else np.ascontiguousarray(ring, np.float64),
                      np.ascontiguousarray(x_scale, np.float64), np.ascontiguousarray(h, np.float64),
                      float(f_scale), int(max_iter), float(xtol), float(ftol), f, J)
    return p[:k].copy(), f, J, cost


def estimate_tube(m: Matches, camera: CameraModel, radius_m: float, min_matches: int = 20,
                  noise_rad: float = 0.003, max_depth_m: float = 0.3, init: np.ndarray | None = None,
                  max_points: int = 150, max_sigma_distance_m: float = 1e-3, solver: str = "lm") -> StepMotion:
    """The tube-constrained 6-DOF estimator (module docstring). ``init``: optional 10-vector to start from;
    ``solver``: ``lm`` (the hand-written robust Levenberg-Marquardt) or ``trf`` (scipy's ``least_squares``)."""
    return fit_tube(m, camera, radius_m, min_matches, noise_rad, max_depth_m, init, max_points,
                    max_sigma_distance_m, solver)[0]


def fit_tube(m: Matches, camera: CameraModel, radius_m: float, min_matches: int = 20,
             noise_rad: float = 0.003, max_depth_m: float = 0.3, init: np.ndarray | None = None,
             max_points: int = 150, max_sigma_distance_m: float = 1e-3,
             solver: str = "lm", start: str = "essential", hold_axis: bool = False,
             starts: list[np.ndarray] | None = None) -> tuple[StepMotion, np.ndarray | None]:
    """:func:`estimate_tube` and the fitted 10-vector (rotation vector of ``R_c1_c2``, ``t_c1_c2_m``, the tube
    axis's direction ``(ax, ay, 1)`` and offset ``(ox, oy, 0)`` in frame 1; :func:`tube_predict` reads it), or
    None where no fit was made. An ``uncertain`` step keeps its parameters. ``start`` (without ``init``):
    ``essential`` (:func:`essential_start`, a pure rotation where it finds none) or ``rotation`` (the pure
    rotation that best aligns the rays: guided matching's fits, whose matches lie along the hypotheses' radial
    epipolar lines, keep it). ``hold_axis``: the tube's axis held on the optical axis and the camera on it (the
    last four parameters 0), only the motion fitted (a fit beside the wall of its own cylinder is fitted again so:
    :data:`bodyslam.vision.odometry.BESIDE_WALL_HELD_AXIS`), from each of ``starts`` (10-vectors whose motion part
    is used; default: ``init``'s or the start above), the lowest robust cost kept."""
    n = len(m)
    if n < min_matches:
        return StepMotion(n_matches=n, status="too_few_matches"), None
    if not radius_m > 0:
        raise ConfigError(f"tube radius must be positive, got {radius_m}")
    b1, v1 = camera.unproject(m.pts1_px)
    b2, v2 = camera.unproject(m.pts2_px)
    ok = v1 & v2
    b1, b2 = b1[ok], b2[ok]
    if len(b1) < min_matches:
        return StepMotion(n_matches=len(b1), status="too_few_matches"), None
    n_used = len(b1)
    if len(b1) > max_points:  # 150 well-spread rays fix 10 parameters; more only costs time
        sel = np.linspace(0, len(b1) - 1, max_points).astype(int)
        b1, b2 = b1[sel], b2[sel]
    R_max = radius_m
    prior_sigma = np.array([0.35, 0.35, 0.5 * R_max, 0.5 * R_max])  # axis tilt (rad), axis offset (m)

    x_scale = np.r_[[0.05] * 3, [0.003] * 3, [0.2] * 2, [0.005] * 2]
    steps = 1e-6 * x_scale  # forward-difference steps, relative to each parameter's scale

    def residuals(p):
        return _tube_residuals_batch(p[None], b1, b2, R_max, max_depth_m, noise_rad, prior_sigma)[0]

    def fun_jac(p):
        # the residuals and all 10 forward differences in one batched evaluation
        P = np.repeat(p[None], 11, axis=0)
        P[1:] += np.diag(steps)
        F = _tube_residuals_batch(P, b1, b2, R_max, max_depth_m, noise_rad, prior_sigma)
        return F[0], ((F[1:] - F[0]) / steps[:, None]).T

    if start not in ("essential", "rotation"):
        raise ConfigError(f"start must be 'essential' or 'rotation', got {start!r}")
    if init is not None:  # a caller's start (measured: the previous step's solution does not save iterations)
        p0 = np.asarray(init, float).copy()
    elif hold_axis and starts:  # the caller's starts stand in for the essential matrix's (its RANSAC not run)
        p0 = None
    else:
        aligned = Rotation.align_vectors(b1, b2)[0]  # the pure rotation with b1 ~= R_c1_c2 b2
        p0 = essential_start(b1, b2, ESSENTIAL_START_STEP * R_max, aligned) if start == "essential" else None
        if p0 is None:  # too few rays in front of both cameras, no essential matrix, or the twisted pair's
            p0 = np.zeros(10)
            p0[0:3] = aligned.as_rotvec()
    if hold_axis:
        if solver != "lm":
            raise ConfigError("a fit with the axis held runs the 'lm' solver only")

        def fun_jac6(q):
            f, J = fun_jac(np.r_[q, 0.0, 0.0, 0.0, 0.0])
            return f, J[:, :6]

        best = None
        for s0 in (starts if starts else [p0]):
            q = lm_compiled(0, np.r_[np.asarray(s0, float)[:6], 0.0, 0.0, 0.0, 0.0], 6, b1, b2, R_max, max_depth_m,
                            noise_rad, prior_sigma, x_scale[:6], steps[:6], 2.0)
            if q is None:
                q = _lm_soft_l1(np.asarray(s0, float)[:6].copy(), fun_jac6,
                                lambda q: residuals(np.r_[q, 0.0, 0.0, 0.0, 0.0]), x_scale[:6], 2.0)
            if best is None or q[3] < best[3]:
                best = q
        q, fval, J, cost = best
        x = np.r_[q, 0.0, 0.0, 0.0, 0.0]
    elif solver == "lm":
        sol = lm_compiled(0, p0, 10, b1, b2, R_max, max_depth_m, noise_rad, prior_sigma, x_scale, steps, 2.0)
        x, fval, J, cost = sol if sol is not None else _lm_soft_l1(p0, fun_jac, residuals, x_scale, 2.0)
    elif solver == "trf":
        try:
            sol = least_squares(residuals, p0, jac=lambda p: fun_jac(p)[1], loss="soft_l1", f_scale=2.0,
                                x_scale=x_scale, max_nfev=200, method="trf")
        except (ValueError, np.linalg.LinAlgError):
            return StepMotion(n_matches=len(b1), status="solver_failed"), None
        x, fval, J, cost = sol.x, sol.fun, sol.jac, float(sol.cost)
    else:
        raise ConfigError(f"solver must be 'lm' or 'trf', got {solver!r}")
    if not np.all(np.isfinite(x)):
        return StepMotion(n_matches=len(b1), status="solver_failed"), None
    R, t = Rotation.from_rotvec(x[0:3]), x[3:6]
    # Uncertainty: Gauss-Newton covariance at the solution, scaled by the robust residual variance.
    m_res = len(fval) - 4
    dof = max(1, 2 * (m_res // 3) - J.shape[1])  # two independent components per 3-vector cross-product residual
    s2 = max(float(2.0 * cost) / dof, 1.0)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return StepMotion(n_matches=n_used, status="solver_failed"), None
    d = t / max(np.linalg.norm(t), 1e-12) if np.linalg.norm(t) > 1e-6 else np.array([0.0, 0.0, 1.0])
    sig_d = float(np.sqrt(max(d @ cov[3:6, 3:6] @ d, 0.0)))
    sig_r = float(np.sqrt(max(np.linalg.eigvalsh(cov[0:3, 0:3]).max(), 0.0)))
    out = motion_from_transform(R, t, n_used)
    out = replace(out, sigma_distance_m=sig_d, sigma_rotation_rad=sig_r)
    if sig_d > max_sigma_distance_m:
        return replace(StepMotion(n_matches=n_used, status="uncertain"), sigma_distance_m=sig_d,
                       sigma_rotation_rad=sig_r), x
    return out, x


def axis_tilt_rad(params: np.ndarray) -> float:
    """The angle (rad) between the optical axis and the axis of the cylinder a :func:`fit_tube` 10-vector holds
    (direction ``(ax, ay, 1)`` in frame 1)."""
    return math.atan(math.hypot(float(params[6]), float(params[7])))


def camera_off_axis_radii(params: np.ndarray, radius_m: float) -> float:
    """The camera's distance from the axis of the cylinder a :func:`fit_tube` 10-vector holds (direction ``(ax, ay,
    1)``, offset ``(ox, oy, 0)`` in frame 1), in radii ``radius_m``: 0 on the axis, 1 on the wall. The length of
    ``o x a`` for the unit direction ``a``."""
    ax, ay, ox, oy = (float(v) for v in params[6:10])
    return math.sqrt(ox * ox + oy * oy + (ox * ay - oy * ax) ** 2) / math.sqrt(ax * ax + ay * ay + 1.0) / radius_m


def tube_predict(params: np.ndarray, pts1_px: np.ndarray, camera: CameraModel, radius_m: float,
                 max_depth_m: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Where frame-1 pixels ``pts1_px (n, 2)`` land in frame 2 under the tube model ``params`` (the 10-vector of
    :func:`fit_tube`): each ray meets the tube (depth capped at ``max_depth_m``, as in the fit), the point is
    moved into frame 2 and projected. Returns ``(uv_px (n, 2), valid (n,))``."""
    b1, v1 = camera.unproject(pts1_px)
    X2 = np.stack([c[0] for c in _tube_points_xyz(np.asarray(params, float).reshape(1, 10), b1, radius_m,
                                                   max_depth_m)], axis=-1)
    uv, v2 = camera.project(X2)
    return uv, v1 & v2

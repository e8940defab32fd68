"""The whole exam solved at once: the smoothed trajectory refined to the joint maximum a posteriori of every step and
every RSS reading (Gauss-Newton with Levenberg-Marquardt damping).

Why: the RTS smoother (:func:`bodyslam.fusion.body_slam.rts_smooth`) is the optimum of the model *linearised along
the forward filter's run*. Where that run's orientation is tens of degrees off (a start or a gap re-start decided
under correlated shadowing, ``realistic``), the smoother inherits the linearisation: its orientation errs 70-95 deg
on ``realistic`` while the same readings and steps bound it near 20 (docs/RESULTS.md, "The bound under the
realistic channel"). Re-linearising at every iteration is the iterated smoother (Bell 1994: the iterated
Kalman smoother is Gauss-Newton on the batch problem); here it is written as the batch problem directly.

Unknowns: the pose of every frame, ``p_k`` (m, body frame) and ``R_k = R_k_hat exp([phi_k]x)`` (``R_w_c``); 6 per
frame. Factors, each a whitened residual:

- each step ``k -> k+1`` (the fusion's process rule, :func:`bodyslam.fusion.ekf.process_noise`): position
  ``(p_{k+1} - p_k - R_k (1 + s_k) t_k) / sigma_t`` and rotation ``log(R_s^T R_k^T R_{k+1}) / sigma_r``; ``s_k`` is
  the smoother's visual scale state where it has one (held fixed here), and ``sigma_t`` then keeps the radius's
  share (the state no longer carries it);
- each RSS reading (the path-loss model the filter uses): ``(rss - mean_rss(p_k)) / sigma``, capped at the
  filter's per-reading 99.9% gate (a reading beyond it adds a constant: it cannot pull the solution, as in the
  filter's likelihood).

No prior on the start: the readings place the path, as they do the filter's. The solve starts from the smoother's
trajectory, accepts a step only if the cost falls, and stops when the largest update is below 1e-6 (m, rad), the
cost falls by less than a millionth of itself, or after ``max_iter`` (30; the tuning runs took 15-40 to the first
two rules, with the same errors at 15 as at 60). The normal equations are block tridiagonal (sparse, solved
directly): time and memory linear in the frames (a 10,000-frame exam: 2.5-3 s, 6 iterations). Covariances: the
smoother's (the same information, linearised elsewhere; the caller scales them by the readings' measured
correlation at the refined positions).

Measured on tuning seeds only (docs/RESULTS.md, "The whole exam solved at once"), smoother -> refined, mean
position error / orientation error (optical axis):

- realistic 503-509, session 18's motion: 3.73 -> 3.73 cm, 85 -> 52 deg (37 -> 28); session 15's motion: 3.93 ->
  3.74 cm, 80 -> 62 deg (39 -> 30);
- thesis 510-512: 1.34 -> 1.34 cm, 17 -> 20 deg (14 -> 16).

Started from the true trajectory instead, the solve ends where it ends from the smoother (realistic 503-509: six of
seven runs within 0.25 cm of it; the seventh 0.7 cm better, at a higher cost): the optimum of this model, not a
local minimum, is what remains off. Tried and not used (realistic 503-509): the readings weighted by their measured
correlation (``kappa`` or its square root: 4.37 / 3.81 cm against 3.74, session 15's motion), per-sensor constant
offsets as unknowns (4 or 2 dB priors: 4.32 / 4.15 cm, same motion), and the readings' normalised residuals
whitened as a Gauss-Markov process along the visual path (correlation distance 1, 3 or 10 cm: 3.66 / 3.89 / 4.28 cm
and 68 / 75 / 76 deg against 3.73 cm and 52 deg, session 18's motion; under that model the cost is nearly flat:
from the truth it ends 1.5-4.5 cm off, at costs within 1% of the solution from the smoother).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import FusionResult
from bodyslam.fusion.ekf import Z_GATE_999, _skew, process_noise, step_rotation_matrices
from bodyslam.fusion.rf import PathLossModel
from bodyslam.geometry import matrix_to_rotvec, rotvec_to_matrix
from bodyslam.steps import StepMotion

log = logging.getLogger(__name__)

__all__ = ["refine_map", "MapProblem"]


class MapProblem:
    """The batch problem of one exam (module docstring): residuals, cost and the sparse Jacobian at a trajectory."""

    def __init__(self, steps: list[StepMotion], rss: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray,
                 pl: PathLossModel, scale: np.ndarray | None = None, gate: float = Z_GATE_999):
        t, self.sig_t, self.sig_r = process_noise(steps, 0.0)
        n = len(steps) + 1
        s = np.zeros(n) if scale is None else np.asarray(scale, float)
        self.t = t * (1.0 + s[:-1, None])
        self.R_steps = step_rotation_matrices(steps)
        self.rss = np.asarray(rss, float)
        self.sensors, self.normals, self.pl, self.gate = sensors_w_m, normals_w, pl, float(gate)
        self.n = n

    def _rss_terms(self, p):
        diff = self.sensors[None] - p[:, None, :]  # (n, m, 3)
        d = np.linalg.norm(diff, axis=2)
        depth = np.maximum(np.einsum("kij,ij->ki", diff, self.normals), 0.0)
        _, alpha, sigma = self.pl.params(depth)
        z = (self.rss - self.pl.mean_rss_dbm(d, depth)) / sigma
        return z, diff, d, alpha, sigma

    def residuals(self, p, R):
        """Whitened residuals ``(step position (n-1, 3), step rotation (n-1, 3), readings (n, m))``."""
        rp = (p[1:] - p[:-1] - np.einsum("kij,kj->ki", R[:-1], self.t)) / self.sig_t[:, None]
        E = np.swapaxes(self.R_steps, 1, 2) @ np.swapaxes(R[:-1], 1, 2) @ R[1:]  # R_s^T R_k^T R_{k+1}
        rr = matrix_to_rotvec(E) / self.sig_r[:, None]
        return rp, rr, self._rss_terms(p)[0]

    def cost(self, p, R) -> float:
        """Half the sum of squares, each reading's term capped at the gate."""
        rp, rr, z = self.residuals(p, R)
        zz = np.where(np.isfinite(z), np.minimum(z * z, self.gate**2), 0.0)
        return 0.5 * float(np.sum(rp**2) + np.sum(rr**2) + np.sum(zz))

    def linearise(self, p, R):
        """``(J, r)``: the sparse Jacobian over ``[dp_k, dphi_k]`` per frame and the residual vector (readings
        outside the gate left out: their capped term is flat)."""
        n, K = self.n, self.n - 1
        rp, rr, _ = self.residuals(p, R)
        z, diff, d, alpha, sigma = self._rss_terms(p)
        k = np.arange(K)
        rows, cols, vals = [], [], []

        def put(r, c, v):
            rows.append(np.ravel(r))
            cols.append(np.ravel(c))
            vals.append(np.broadcast_to(v, np.shape(r)).ravel())

        # step position: d/dp_{k+1} = I / s, d/dp_k = -I / s, d/dphi_k = R_k [t_k]x / s
        Jphi = R[:-1] @ _skew(self.t) / self.sig_t[:, None, None]
        for a in range(3):
            put(3 * k + a, 6 * (k + 1) + a, 1.0 / self.sig_t)
            put(3 * k + a, 6 * k + a, -1.0 / self.sig_t)
            for b in range(3):
                put(3 * k + a, 6 * k + 3 + b, Jphi[:, a, b])
        r0 = 3 * K
        # step rotation: d/dphi_{k+1} = I / s, d/dphi_k = -(R_{k+1}^T R_k) / s (the log's Jacobian taken as I)
        A = np.swapaxes(R[1:], 1, 2) @ R[:-1] / self.sig_r[:, None, None]
        for a in range(3):
            put(r0 + 3 * k + a, 6 * (k + 1) + 3 + a, 1.0 / self.sig_r)
            for b in range(3):
                put(r0 + 3 * k + a, 6 * k + 3 + b, -A[:, a, b])
        r0 += 3 * K
        # readings: z = (rss - mean(p)) / sigma, d mean / dp = (10 alpha / ln 10) (s - p) / d^2
        use = np.isfinite(z) & (np.abs(z) < self.gate)
        kf, jf = np.nonzero(use)
        g = (10.0 * alpha[kf, jf] / np.log(10.0))[:, None] * diff[kf, jf] / (d[kf, jf] ** 2)[:, None]
        Jz = -g / sigma[kf, jf][:, None]
        m = len(kf)
        for b in range(3):
            put(r0 + np.arange(m), 6 * kf + b, Jz[:, b])
        r0 += m
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(r0, 6 * n))
        return J, np.concatenate([rp.ravel(), rr.ravel(), z[kf, jf]])


def refine_map(res: FusionResult, steps: list[StepMotion], rss: np.ndarray, sensors_w_m: np.ndarray,
               normals_w: np.ndarray, pl: PathLossModel, max_iter: int = 30, tol: float = 1e-6,
               rel_tol: float = 1e-6) -> FusionResult:
    """The smoothed run ``res`` (:func:`bodyslam.fusion.body_slam.rts_smooth`) refined to the whole exam's joint
    optimum (module docstring); a copy with the refined positions and orientations, everything else as ``res``."""
    prob = MapProblem(steps, rss, sensors_w_m, normals_w, pl, res.scale)
    p = np.array(res.positions_w_m, float)
    R = res.rotations_w_c.as_matrix()
    f = f_start = prob.cost(p, R)
    lam, it = 1e-3, 0
    for it in range(1, max_iter + 1):
        f_before = f
        J, r = prob.linearise(p, R)
        H = (J.T @ J).tocsc()
        g = J.T @ r
        D = sp.diags(H.diagonal() + 1e-9)
        while True:
            dx = -spsolve(H + lam * D, g).reshape(-1, 6)
            p2, R2 = p + dx[:, :3], R @ rotvec_to_matrix(dx[:, 3:])
            f2 = prob.cost(p2, R2)
            if f2 < f:
                p, R, f = p2, R2, f2
                lam = max(lam / 3.0, 1e-6)
                break
            lam *= 5.0
            if lam > 1e6:
                break
        if lam > 1e6 or np.abs(dx).max() < tol or f_before - f < rel_tol * f:
            break
    log.info("whole-exam refinement: cost %.1f -> %.1f in %d iterations", f_start, f, it)
    return replace(res, positions_w_m=p, rotations_w_c=Rotation.from_matrix(R))

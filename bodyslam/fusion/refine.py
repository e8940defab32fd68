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
two rules, with the same errors at 15 as at 60). The normal equations are block tridiagonal: built block by
block without the Jacobian (the readings in chunks of frames) and solved as a banded system, so time is linear in
the frames and memory little more than the trajectory's (a 10,000-frame exam: ~1.5 s, 6 iterations, +15 MB).
Covariances: the solution's own, each pose's block of the inverse of the Gauss-Newton system at the solution
(:func:`marginal_covariances`, ``O(n)``), stated with the readings' measured correlation at the refined positions
(``reading_kappa``, :func:`stated_covariances`: the position's scaled by it, the orientation's the sandwich with
the readings' share scaled, ``O(n)`` too). Until session 26 the smoother's were stated (within 4% in position,
docs/RESULTS.md), but they were linearised along the filter's run: where the refinement turned the orientation,
its 1-sigma stayed the smoother's (realistic tuning: 91% of frames inside the orientation's 68% ellipsoid, 83% with
the solution's own). With RSS bias states the solve takes the filter's biases as known; its covariance adds their
variances to the readings' (``reading_var_db2``).

Measured on tuning seeds only (docs/RESULTS.md, "The whole exam solved at once"), smoother -> refined, mean
position error / orientation error (optical axis):

- realistic 503-509, session 18's motion: 3.73 -> 3.73 cm, 85 -> 52 deg (37 -> 28); session 15's motion: 3.93 ->
  3.74 cm, 80 -> 62 deg (39 -> 30);
- thesis 510-512: 1.34 -> 1.34 cm, 17 -> 20 deg (14 -> 16).

Started from the true trajectory instead, the solve ends where it ends from the smoother (realistic 503-509: six of
seven runs within 0.25 cm of it; the seventh 0.7 cm better, at a higher cost): the optimum of this model, not a
local minimum, is what remains off. On thesis runs the cost has several minima close in value, and the lowest is not
the nearest to the truth: starting from the smoother turned 10 deg either way about each axis and keeping the lowest
cost made 6 of 7 tuning runs worse (0.95 -> 1.21 cm). The solve therefore starts from the smoother only. Tried and
not used (realistic 503-509): the readings weighted by their measured correlation (``kappa`` or its square root:
4.37 / 3.81 cm against 3.74, session 15's motion), per-sensor constant offsets as unknowns (4 or 2 dB priors: 4.32 /
4.15 cm, same motion), and the readings' normalised residuals whitened as a Gauss-Markov process along the visual
path (correlation distance 1, 3 or 10 cm: 3.66 / 3.89 / 4.28 cm and 68 / 75 / 76 deg against 3.73 cm and 52 deg,
session 18's motion; under that model the cost is nearly flat: from the truth it ends 1.5-4.5 cm off, at costs
within 1% of the solution from the smoother).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.linalg import solveh_banded
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import FusionResult
from bodyslam.fusion.ekf import Z_GATE_999, _skew, process_noise, step_rotation_matrices
from bodyslam.fusion.rf import PathLossModel
from bodyslam.geometry import matrix_to_rotvec, rotvec_to_matrix
from bodyslam.parallel import available_cores
from bodyslam.steps import StepMotion

try:  # the marginal covariances' two passes compiled (setup.py builds them where a C compiler is at hand)
    from bodyslam.fusion import _block_tridiag as _bt
except ImportError:
    _bt = None

log = logging.getLogger(__name__)

__all__ = ["refine_map", "MapProblem", "marginal_covariances", "sandwich_share", "stated_covariances"]

CHUNK_FRAMES = 4096  # frames per block of the readings' terms (~3 MB per array at 32 sensors)
# frames per block of the readings' rows in the normal equations: ~8 arrays of (f, m, 3) at once on each thread
# (~50 MB at 4,096 frames, 32 sensors and 2 threads: the whole-exam solve's peak); each frame writes its own rows,
# so the system is the same whatever the blocks (the cost sums its blocks in order: CHUNK_FRAMES stays its own)
NORMAL_CHUNK_FRAMES = 1024


class MapProblem:
    """The batch problem of one exam (module docstring) at a trajectory ``p (n, 3)``, ``R (n, 3, 3)``: its
    residuals, cost and Gauss-Newton system (:meth:`normal_equations`; :meth:`linearise` the sparse reference)."""

    def __init__(self, steps: list[StepMotion], rss: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray,
                 pl: PathLossModel, scale: np.ndarray | None = None, gate: float = Z_GATE_999,
                 lost_floor_m: float = 0.0):
        t, self.sig_t, self.sig_r = process_noise(steps, 0.0, lost_floor_m)
        n = len(steps) + 1
        s = np.zeros(n) if scale is None else np.asarray(scale, float)
        self.t = t * (1.0 + s[:-1, None])
        self.R_steps = step_rotation_matrices(steps)
        self.rss = np.asarray(rss, float)
        self.sensors, self.normals, self.pl, self.gate = sensors_w_m, normals_w, pl, float(gate)
        self.n = n

    def _rss_terms(self, p, rows=slice(None)):
        """The readings' normalised residuals ``z`` and what their Jacobian needs, for the frames ``rows``."""
        p = p[rows]
        diff = self.sensors[None] - p[:, None, :]  # (f, m, 3)
        d = np.linalg.norm(diff, axis=2)
        depth = np.maximum(np.einsum("kij,ij->ki", diff, self.normals), 0.0)
        _, alpha, sigma = self.pl.params(depth)
        z = (self.rss[rows] - self.pl.mean_rss_dbm(d, depth)) / sigma
        return z, diff, d, alpha, sigma

    def _chunks(self, n: int | None = None, size: int | None = None):
        """Blocks of ``size`` frames (default :data:`CHUNK_FRAMES`) over ``n`` frames (default: all of them; the
        readings' terms, the steps' Jacobians): memory bounded whatever the exam's length."""
        n = self.n if n is None else n
        size = CHUNK_FRAMES if size is None else size
        return (slice(a, min(a + size, n)) for a in range(0, n, size))

    def _per_chunk(self, fn, size: int | None = None) -> list:
        """``fn(rows)`` for every block of :meth:`_chunks` (of ``size`` frames), in order; the blocks on threads
        where there are several and more than one core (numpy leaves the interpreter lock in these array loops: 3
        blocks of a 10,000-frame exam's readings ~2x faster on 2 cores). What each block gives is combined in block
        order by the caller, so results do not depend on the threads."""
        rows = list(self._chunks(size=size))
        workers = min(len(rows), available_cores())
        if workers < 2:
            return [fn(r) for r in rows]
        with ThreadPoolExecutor(workers) as ex:
            return list(ex.map(fn, rows))

    def _steps(self, p, R, rows=slice(None)):
        """The step factors' whitened residuals ``(rp, rr)`` (each ``(n-1, 3)``; of the steps ``rows`` only)."""
        a, b, _ = rows.indices(self.n - 1)
        p0, p1, R0, R1 = p[a:b], p[a + 1:b + 1], R[a:b], R[a + 1:b + 1]
        rp = (p1 - p0 - np.einsum("kij,kj->ki", R0, self.t[a:b])) / self.sig_t[a:b, None]
        E = np.swapaxes(self.R_steps[a:b], 1, 2) @ np.swapaxes(R0, 1, 2) @ R1  # R_s^T R_k^T R_{k+1}
        return rp, matrix_to_rotvec(E) / self.sig_r[a:b, None]

    def residuals(self, p, R):
        """Whitened residuals ``(step position (n-1, 3), step rotation (n-1, 3), readings (n, m))``."""
        return (*self._steps(p, R), self._rss_terms(p)[0])

    def cost(self, p, R) -> float:
        """Half the sum of squares, each reading's term capped at the gate."""
        rp, rr = self._steps(p, R)
        total = float(np.sum(rp**2) + np.sum(rr**2))

        def block(rows):
            z = self._rss_terms(p, rows)[0]
            return float(np.sum(np.where(np.isfinite(z), np.minimum(z * z, self.gate**2), 0.0)))

        for part in self._per_chunk(block):
            total += part
        return 0.5 * total

    def _step_blocks(self, p, R, rows=slice(None)):
        """Each step's six whitened residual rows (position, rotation) and their Jacobians against the poses ``k``
        and ``k+1``: ``(Ja, Jb (n-1, 6, 6), r (n-1, 6))`` (of the steps ``rows`` only). Position rows
        ``[-I/s_t, R_k [t_k]x / s_t | I/s_t, 0]``; rotation rows ``[0, -(R_{k+1}^T R_k) / s_r | 0, I / s_r]`` (the
        log's Jacobian taken as the identity)."""
        a, b, _ = rows.indices(self.n - 1)
        K = b - a
        rp, rr = self._steps(p, R, rows)
        it, ir = 1.0 / self.sig_t[a:b, None, None], 1.0 / self.sig_r[a:b, None, None]
        Ja = np.zeros((K, 6, 6))
        Jb = np.zeros((K, 6, 6))
        Ja[:, :3, :3] = -np.eye(3) * it
        Ja[:, :3, 3:] = R[a:b] @ _skew(self.t[a:b]) * it
        Ja[:, 3:, 3:] = -(np.swapaxes(R[a + 1:b + 1], 1, 2) @ R[a:b]) * ir
        Jb[:, :3, :3] = np.eye(3) * it
        Jb[:, 3:, 3:] = np.eye(3) * ir
        return Ja, Jb, np.concatenate([rp, rr], axis=1)

    def _reading_rows(self, p, rows=slice(None), extra_var=None):
        """The readings of the frames ``rows`` that count (finite, inside the gate): ``(z, Jz (f, m, 3), use)``,
        ``Jz = dz / dp`` of the reading's own frame, zero where not used
        (``d mean / dp = (10 alpha / ln 10) (s - p) / d^2``). ``extra_var (n, m)`` (dB^2): variance added to each
        reading's (the gate still on the reading's own)."""
        z, diff, d, alpha, sigma = self._rss_terms(p, rows)
        use = np.isfinite(z) & (np.abs(z) < self.gate)
        Jz = -(10.0 * alpha / np.log(10.0) / (d**2 * sigma))[..., None] * diff
        if extra_var is not None:
            w = sigma / np.sqrt(sigma**2 + np.asarray(extra_var, float)[rows])
            z, Jz = z * w, Jz * w[..., None]
        return np.where(use, z, 0.0), np.where(use[..., None], Jz, 0.0), use

    def reading_information(self, p, extra_var=None) -> np.ndarray:
        """``(n, 3, 3)``: the readings' share of each frame's position information, ``Jz^T Jz`` of its readings that
        count (the rows :meth:`normal_equations` adds to ``D``; it also gives them as it builds them, its
        ``readings_out``; ``extra_var`` as there)."""
        H = np.zeros((self.n, 3, 3))

        def block(rows):
            Jz = self._reading_rows(p, rows, extra_var)[1]
            H[rows] = np.einsum("kmi,kmj->kij", Jz, Jz)

        self._per_chunk(block, NORMAL_CHUNK_FRAMES)
        return H

    def normal_equations(self, p, R, extra_var=None, readings_out: np.ndarray | None = None):
        """``(D, O, g)``: the Gauss-Newton system ``J^T J dx = -J^T r`` in blocks -- ``D (n, 6, 6)`` the diagonal
        blocks, ``O (n-1, 6, 6)`` the blocks ``(k, k+1)``, ``g (n, 6)`` the gradient ``J^T r`` -- without forming
        ``J`` (:meth:`linearise`, the same system as a sparse matrix, is the reference the tests hold it to).
        ``extra_var``: variance added to the readings' (:meth:`_reading_rows`; the covariance's system only).
        ``readings_out (n, 3, 3)``: filled with the readings' share of ``D`` (:meth:`reading_information`)."""
        D = np.zeros((self.n, 6, 6))
        g = np.zeros((self.n, 6))
        O = np.empty((self.n - 1, 6, 6))
        for rows in self._chunks(self.n - 1):  # the steps' Jacobians a block at a time (~3 kB a frame at once)
            Ja, Jb, r = self._step_blocks(p, R, rows)
            JaT, JbT = np.swapaxes(Ja, 1, 2), np.swapaxes(Jb, 1, 2)
            a, b = rows.start, rows.stop  # (D starts at zero and each block adds two terms: x + y = y + x,
            D[a:b] += JaT @ Ja  # so the sums do not depend on the blocks)
            D[a + 1:b + 1] += JbT @ Jb
            O[rows] = JaT @ Jb
            g[a:b] += np.einsum("kij,kj->ki", JaT, r)
            g[a + 1:b + 1] += np.einsum("kij,kj->ki", JbT, r)

        def block(rows):  # the readings: position rows of their own frame only (blocks write their own rows)
            z, Jz, _ = self._reading_rows(p, rows, extra_var)
            info = np.einsum("kmi,kmj->kij", Jz, Jz)
            D[rows, :3, :3] += info
            g[rows, :3] += np.einsum("kmi,km->ki", Jz, z)
            if readings_out is not None:
                readings_out[rows] = info

        self._per_chunk(block, NORMAL_CHUNK_FRAMES)
        return D, O, g

    def linearise(self, p, R):
        """``(J, r)``: the sparse Jacobian over ``[dp_k, dphi_k]`` per frame and the residual vector (the steps'
        position rows, their rotation rows, then the readings that count, frame by frame). The same blocks as
        :meth:`normal_equations`, assembled as one matrix: the reference the tests hold the normal equations to
        (small problems: its memory grows with every reading)."""
        n, K = self.n, self.n - 1
        Ja, Jb, r = self._step_blocks(p, R)
        z, Jz, use = self._reading_rows(p)
        kf, jf = np.nonzero(use)
        m = len(kf)
        k, i = np.arange(K)[:, None, None], np.arange(6)[None, :, None]
        row = np.where(i < 3, 3 * k + i, 3 * K + 3 * k + i - 3)  # (K, 6, 1): position rows, then rotation rows
        col = np.arange(6)[None, None, :]
        rows = [np.broadcast_to(row, Ja.shape), np.broadcast_to(row, Jb.shape),
                np.broadcast_to(6 * K + np.arange(m)[:, None], (m, 3))]
        cols = [np.broadcast_to(6 * k + col, Ja.shape), np.broadcast_to(6 * (k + 1) + col, Jb.shape),
                6 * kf[:, None] + np.arange(3)[None, :]]
        vals = [Ja, Jb, Jz[kf, jf]]
        J = sp.csr_matrix((np.concatenate([v.ravel() for v in vals]),
                           (np.concatenate([x.ravel() for x in rows]), np.concatenate([x.ravel() for x in cols]))),
                          shape=(6 * K + m, 6 * n))
        return J, np.concatenate([r[:, :3].ravel(), r[:, 3:].ravel(), z[kf, jf]])


def refine_map(res: FusionResult, steps: list[StepMotion], rss: np.ndarray, sensors_w_m: np.ndarray,
               normals_w: np.ndarray, pl: PathLossModel, max_iter: int = 30, tol: float = 1e-6,
               rel_tol: float = 1e-6, lost_floor_m: float = 0.0, own_cov: bool = True,
               reading_var_db2: np.ndarray | None = None, reading_kappa=None) -> FusionResult:
    """The smoothed run ``res`` (:func:`bodyslam.fusion.body_slam.rts_smooth`) refined to the whole exam's joint
    optimum (module docstring); a copy with the refined positions, orientations and their covariances
    (``own_cov``; False: the smoother's, as ``res``; also where the system is singular), everything else as
    ``res``. ``lost_floor_m``: the filters' least length of a step lost to motion
    (:func:`bodyslam.fusion.ekf.process_noise`). ``reading_var_db2 (n, m)``: variance (dB^2) the covariance adds
    to each reading's, where ``rss`` is net of estimated offsets (the filter's RSS bias states' variances): the
    solution takes them as known, its 1-sigma should not. ``reading_kappa``: a function of the solution's positions
    ``(n, 3)`` giving the readings' correlation factor (a number or one per frame,
    :mod:`bodyslam.fusion.channel`); with it the covariance is the stated one, :func:`stated_covariances` (the
    caller does not scale it again)."""
    prob = MapProblem(steps, rss, sensors_w_m, normals_w, pl, res.scale, lost_floor_m=lost_floor_m)
    p = np.array(res.positions_w_m, float)
    R = res.rotations_w_c.as_matrix()
    f = f_start = prob.cost(p, R)
    lam, it = 1e-3, 0
    D = O = g = None
    for it in range(1, max_iter + 1):
        f_before = f
        D = O = g = None  # (the last iteration's system freed before this one's is built: 0.6 kB a frame)
        D, O, g = prob.normal_equations(p, R)
        while True:
            dx = _solve_damped(D, O, g, lam)
            if dx is not None:
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
    cov = None
    del D, O, g  # (the loop's system: not held while the covariance's is built, 0.6 kB a frame)
    kappa = None if reading_kappa is None else reading_kappa(p)
    if own_cov:
        H_rf = None if kappa is None else np.zeros((prob.n, 3, 3))
        D, O, _ = prob.normal_equations(p, R, reading_var_db2, readings_out=H_rf)
        cov = marginal_covariances(D, O) if kappa is None else stated_covariances(D, O, H_rf, kappa)
        if cov is None:
            log.warning("whole-exam refinement: its information matrix is singular; the smoother's covariances kept")
    if cov is None:
        cov = res.cov if kappa is None else res.cov * _per_frame(kappa, len(res.cov))[:, None, None]
    return replace(res, positions_w_m=p, rotations_w_c=Rotation.from_matrix(R), cov=cov)


def _per_frame(kappa, n: int) -> np.ndarray:
    """A correlation factor (a number or one per frame) as ``(n,)``."""
    return np.broadcast_to(np.asarray(kappa, float), (n,))


def stated_covariances(D: np.ndarray, O: np.ndarray, H_rf: np.ndarray, kappa) -> np.ndarray | None:
    """``(n, 6, 6)``: the whole-exam solve's stated covariances with the readings' errors correlated by ``kappa``
    (a number or one per frame, :mod:`bodyslam.fusion.channel`; ``D``, ``O``: its information matrix ``H``,
    :func:`marginal_covariances`; ``H_rf (n, 3, 3)``: the readings' share of each frame's position information,
    :meth:`MapProblem.reading_information`). None where ``H`` is not positive definite.

    - Orientation (and its cross blocks with the position): the sandwich ``H^-1 (H + sum_j (kappa_j - 1) H_rf,j)
      H^-1``, the covariance of the same solution when each reading's noise variance is ``kappa`` times what the
      solve assumed (:func:`sandwich_share`). The readings inform the orientation through the heading they give
      the path; the roll about it and the turns between frames are the steps', whose noise ``kappa`` does not
      describe. Until session 65 the whole covariance was scaled by ``kappa``. On the realistic testbed that put
      92-94% of frames inside the orientation's 68% ellipsoid. With the sandwich: 68.75% on realistic tuning
      renders 540-549 and 56% on reporting renders 700-719 (the steps' own rotations err more than they state
      there); on ``benchmarks/bench_stated_sigma.py``, 74% at the dissertation's pace with a matcher's gaps and 65% at
      a real exam's (docs/RESULTS.md, "The orientation's 1-sigma from the readings' share").
    - Position: ``kappa`` times the marginal covariance, as before. The sandwich's position is narrower (on the
      bench 54-55% of frames inside at either pace, against 74-77%). The position's 1-sigma was chosen on tuning
      runs as it is (the correlations and what the fit takes up, :mod:`bodyslam.fusion.channel`), and the scaled
      form carries what the white-noise picture leaves out: slow per-sensor errors, and what the fit absorbs.

    A frame whose combined matrix is not positive definite (the per-frame factors differ from frame to frame, so
    the scaled position can fall short of the sandwich's) keeps ``kappa`` times its marginal covariance."""
    n = len(D)
    k = _per_frame(kappa, n)
    W = np.zeros((n, 6, 6))
    W[:, :3, :3] = (k - 1.0)[:, None, None] * H_rf
    share = sandwich_share(D, O, W)
    if share is None:
        return None
    C, M = share
    out = C + M
    out[:, :3, :3] = k[:, None, None] * C[:, :3, :3]
    bad = np.linalg.eigvalsh(out)[:, 0] <= 0.0
    if bad.any():
        log.info("stated covariance: %d frame(s) keep kappa x the marginal covariance (not positive definite)",
                 int(bad.sum()))
        out[bad] = k[bad, None, None] * C[bad]
    return out


def sandwich_share(D: np.ndarray, O: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(C, M)``, each ``(n, 6, 6)``: the diagonal blocks of ``H^-1`` (:func:`marginal_covariances`) and of
    ``H^-1 W H^-1`` for the block-diagonal ``W (n, 6, 6)``, in ``O(n)``. The cross blocks of ``H^-1`` are
    ``C_kj = A_k ... A_(j-1) C_j`` for ``j > k``, ``A_k = -S_k^-1 O_k``, so ``M_k = C_k U_k C_k + B_k`` with a forward
    pass ``U_k = A_(k-1)^T (W_(k-1) + U_(k-1)) A_(k-1)`` (the frames before ``k``) and a backward one ``B_k = C_k W_k
    C_k + A_k B_(k+1) A_k^T`` (frame ``k`` and those after it). None where ``H`` is not positive definite.
    Compiled where ``_block_tridiag.c`` was built, else numpy (the same arithmetic; tests hold both to the dense
    product)."""
    n = len(D)
    passes = _marginal_passes(D, O)
    if passes is None:
        return None
    Sinv, C = passes
    if _bt is not None and n >= 1:
        M = np.empty_like(C)
        _bt.readings_share(np.ascontiguousarray(O, np.float64), Sinv, C, np.ascontiguousarray(W, np.float64), M)
        return C, M
    A = -(Sinv[:-1] @ O)
    AT = np.swapaxes(A, 1, 2)
    M = np.empty_like(D)
    U = np.zeros((6, 6))
    for k in range(n):
        if k:
            U = AT[k - 1] @ (W[k - 1] + U) @ A[k - 1]
        M[k] = C[k] @ U @ C[k]
    Bk = None
    for k in range(n - 1, -1, -1):
        Bk = C[k] @ W[k] @ C[k] + (0.0 if Bk is None else A[k] @ Bk @ AT[k])
        M[k] += Bk
    return C, M


def marginal_covariances(D: np.ndarray, O: np.ndarray) -> np.ndarray | None:
    """``(n, 6, 6)`` the diagonal blocks of ``H^-1`` for the symmetric block-tridiagonal ``H`` (diagonal blocks
    ``D``, blocks ``O`` at ``(k, k+1)``): each pose's marginal covariance at the solution, in ``O(n)``. A forward
    pass of Schur complements ``S_k = D_k - O_{k-1}^T S_{k-1}^-1 O_{k-1}`` (the information of frames ``0..k``
    about pose ``k``, as a filter's), then a backward pass ``C_k = S_k^-1 + G_k C_{k+1} G_k^T`` with
    ``G_k = S_k^-1 O_k`` (the RTS smoother's form). None where ``H`` is not positive definite. Compiled where
    ``_block_tridiag.c`` was built (the same arithmetic, ~1e-15 relative; 0.40 s -> 0.02 on 10,000 frames), else
    :func:`_marginal_passes_numpy`."""
    passes = _marginal_passes(D, O)
    return None if passes is None else passes[1]


def _marginal_passes(D: np.ndarray, O: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The forward pass's inverses ``S_k^-1`` and the marginal covariances (:func:`marginal_covariances`), compiled
    where ``_block_tridiag.c`` was built, else numpy; None where ``H`` is not positive definite."""
    if _bt is not None and len(D) >= 1:
        D = np.ascontiguousarray(D, np.float64)
        O = np.ascontiguousarray(O, np.float64)
        Sinv, C = np.empty_like(D), np.empty_like(D)
        return (Sinv, C) if _bt.marginals(D, O, Sinv, C) else None
    return _marginal_passes_numpy(D, O)


def _marginal_passes_numpy(D: np.ndarray, O: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The forward pass's inverses ``S_k^-1`` and the marginal covariances (:func:`marginal_covariances`)."""
    n = len(D)
    Sinv = np.empty_like(D)
    OT = np.swapaxes(O, 1, 2)
    S = D[0]
    for k in range(n):
        if k:
            S = D[k] - OT[k - 1] @ Sinv[k - 1] @ O[k - 1]
        try:
            L = np.linalg.cholesky(0.5 * (S + S.T))
        except np.linalg.LinAlgError:
            return None
        Li = np.linalg.inv(L)
        Sinv[k] = Li.T @ Li
    C = np.empty_like(D)
    C[-1] = Sinv[-1]
    G = Sinv[:-1] @ O  # every frame's gain at once: the loop below is two small products a frame
    GT = np.swapaxes(G, 1, 2)
    for k in range(n - 2, -1, -1):
        C[k] = Sinv[k] + G[k] @ C[k + 1] @ GT[k]
    return Sinv, C


def _solve_damped(D: np.ndarray, O: np.ndarray, g: np.ndarray, lam: float) -> np.ndarray | None:
    """``dx (n, 6)`` of ``(H + lam diag(H)) dx = -g`` for the block-tridiagonal ``H`` (diagonal blocks ``D``,
    blocks ``O`` above them): a symmetric banded Cholesky solve (bandwidth 11: ``O(n)`` time and memory); None
    where the damped system is not positive definite (the caller damps more)."""
    n = len(D)
    N = 6 * n
    # lower form ab[i - j, j] = H[i, j], column-major as LAPACK takes it (a row-major one is copied on the way:
    # 576 bytes a frame more), filled entry by entry (no index arrays per frame): abk[k, j, r] = ab[r, 6k + j]
    abk = np.zeros((n, 6, 12))
    ab = abk.reshape(N, 12).T
    for i in range(6):
        for j in range(i + 1):
            abk[:, j, i - j] = D[:, i, j]
    ab[0] += lam * (ab[0] + 1e-9)
    for i in range(6):  # H[6(k+1) + i, 6k + j] = O[k, j, i]
        for j in range(6):
            abk[:n - 1, j, 6 + i - j] = O[:, j, i]
    try:  # (ab is built for this one solve: LAPACK overwrites it instead of a copy)
        return -solveh_banded(ab, g.ravel(), overwrite_ab=True, lower=True).reshape(n, 6)
    except np.linalg.LinAlgError:
        return None

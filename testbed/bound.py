"""The posterior Cramer-Rao bound (PCRB) of Body-SLAM filtering (paper 000, Sec. 4, Eq. 28-29, Algorithm 2).

Model (the one :func:`bodyslam.fusion.body_slam.fuse` assumes, in its error-state form): state ``x = [p, theta]``;
process ``x_(k+1) = A_k x_k + w``, ``A_k = [[I, -R_k [t_k]x], [0, R_s,k^T]]`` evaluated on the *true* trajectory
(``R_k`` the true orientation, ``t_k``, ``R_s,k`` the true step), ``w ~ N(0, Q_k)`` with the visual steps' own
1-sigma (steps without an estimate: the filter's bridging noise); measurements: the RSS of every sensor,
``H_k`` the gradient of Eq. 2.1's mean at the true position, ``Z_k = diag(sigma_dB^2)``.

Recursion (Eq. 28): ``J_(k+1) = H^T Z^-1 H + (Q + A J_k^-1 A^T)^-1``, ``J_0 = P_0^-1``; position bound (Eq. 29):
``tr(J_p^-1)`` with ``J_p`` the Schur complement of the position block. This bounds *causal* filters (the EKF);
a smoother uses future readings too and may go below it.

Units: m^2 for the bound; report ``RMSE / sqrt(mean PCRB)`` (SPEC.md).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.fusion.ekf import process_model
from bodyslam.fusion.rf import PathLossModel

__all__ = ["pcrb_positions", "smoothing_bound_positions", "position_bounds", "channel_bounds", "efficient_mean_error"]


def _transition(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, k):
    """Step ``k -> k+1`` of the error-state model on the true trajectory: ``(A_k, Q_k)``."""
    R = rotations_w_c[k]
    Rs = rotations_w_c[k].inv() * rotations_w_c[k + 1]
    t = R.inv().apply(positions_w_m[k + 1] - positions_w_m[k])
    A, Q = process_model(R.as_matrix()[None], t, Rs.as_matrix(), sigma_t_m[k], sigma_r_rad[k])  # the filter's own
    return A[0], Q[0]


def _forward(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, sensors_w_m, normals_w, pl, P0):
    """The recursion of Eq. 28: per frame the position bound ``J_p^-1`` (n, 3, 3) and the whole filtering
    bound ``J^-1`` (n, 6, 6); per step ``(A_k, Q_k)``."""
    n = len(positions_w_m)
    pos_bound = np.zeros((n, 3, 3))
    full = np.zeros((n, 6, 6))
    steps = []

    def info(p):
        _, sigma, Hp = pl.predict(p, sensors_w_m, normals_w)
        Jm = np.zeros((6, 6))
        Jm[:3, :3] = Hp.T @ (Hp / (sigma**2)[:, None])
        return Jm

    def keep(k, J):
        Jp = J[:3, :3] - J[:3, 3:] @ np.linalg.solve(J[3:, 3:], J[3:, :3])
        pos_bound[k] = np.linalg.inv(Jp)
        full[k] = np.linalg.inv(J)

    J = np.linalg.inv(P0) + info(positions_w_m[0])
    keep(0, J)
    for k in range(n - 1):
        A, Q = _transition(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, k)
        steps.append((A, Q))
        J = info(positions_w_m[k + 1]) + np.linalg.inv(Q + A @ np.linalg.solve(J, A.T))
        keep(k + 1, J)
    return pos_bound, full, steps


def pcrb_positions(positions_w_m: np.ndarray, rotations_w_c: Rotation, sigma_t_m: np.ndarray,
                   sigma_r_rad: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray, pl: PathLossModel,
                   P0: np.ndarray, full: bool = False) -> np.ndarray:
    """``tr(J_p^-1)`` per frame (m^2); with ``full`` the 3x3 position bounds ``J_p^-1`` (n, 3, 3).
    ``sigma_t_m``, ``sigma_r_rad``: per-step process 1-sigma (n - 1,)."""
    out = _forward(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, sensors_w_m, normals_w, pl, P0)[0]
    return out if full else np.trace(out, axis1=1, axis2=2)


def position_bounds(positions_w_m: np.ndarray, rotations_w_c: Rotation, sigma_t_m: np.ndarray,
                    sigma_r_rad: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray, pl: PathLossModel,
                    P0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The filtering bound (:func:`pcrb_positions`, ``full``) and the smoothing bound
    (:func:`smoothing_bound_positions`) from one forward pass: ``(n, 3, 3)`` each, m^2."""
    pos_bound, Pf, steps = _forward(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, sensors_w_m, normals_w,
                                    pl, P0)
    # The model is linear-Gaussian in the bound's linearisation, so the inverse of the whole run's Fisher
    # information is what a Rauch-Tung-Striebel pass over the filtering bounds gives: O(n) memory, where the
    # block-tridiagonal matrix itself would be (6n)^2 (29 GB for a 10,000-frame run).
    Ps = Pf[-1].copy()
    smooth = np.zeros_like(pos_bound)
    smooth[-1] = Ps[:3, :3]
    for k in range(len(Pf) - 2, -1, -1):
        A, Q = steps[k]
        P_pred = Q + A @ Pf[k] @ A.T
        C = Pf[k] @ A.T @ np.linalg.inv(P_pred)
        Ps = Pf[k] + C @ (Ps - P_pred) @ C.T
        smooth[k] = Ps[:3, :3]
    return pos_bound, smooth


def smoothing_bound_positions(positions_w_m: np.ndarray, rotations_w_c: Rotation, sigma_t_m: np.ndarray,
                              sigma_r_rad: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray,
                              pl: PathLossModel, P0: np.ndarray) -> np.ndarray:
    """The Cramer-Rao bound of *smoothing* (every reading of the run used for every frame) with the model of
    :func:`pcrb_positions`: the inverse of the whole run's Fisher information (block tridiagonal over the
    states ``[p_k, theta_k]``: prior, RSS information per frame, and per step ``x_(k+1) = A_k x_k + w``),
    computed by a backward pass (:func:`position_bounds`); returns its 3x3 position blocks (n, 3, 3), m^2. This
    is the reference for an offline smoother (RTS), which the causal PCRB does not bound."""
    return position_bounds(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, sensors_w_m, normals_w, pl,
                           P0)[1]


def efficient_mean_error(bounds_m2: np.ndarray, n_samples: int = 20000) -> np.ndarray:
    """``E||e||`` per frame for ``e ~ N(0, C_k)``, ``C_k`` the 3x3 position bounds (n, 3, 3): the mean Euclidean
    error of a filter that attains the bound with Gaussian errors (the mean error is what the issue's goals are
    stated in; the bound itself is on the mean *squared* error). Fixed-seed Monte Carlo (0.3% standard error per frame)."""
    z = np.random.default_rng(0).normal(size=(n_samples, 3))
    L = np.linalg.cholesky(bounds_m2 + 1e-18 * np.eye(3))
    return np.linalg.norm(np.einsum("kij,sj->ksi", L, z), axis=2).mean(axis=1)


# --- the bound under a channel that departs from the calibration (issue 15) ---------------------------------------
#
# Model (testbed.rf's real channel): the reading of sensor j at frame k is
#     y_kj = h_j(p_k; b_j, a_j, q_j) + sigma_kj u_kj,
# h Eq. 2.1's mean with the sensor's PL(d0) off the calibration by b_j ~ N(0, pl0_sd^2), its exponent by
# a_j ~ N(0, alpha_sd^2) and its position by q_j ~ N(0, placement_sd^2 I) (nuisance parameters nu, unknown to any
# estimator, with those priors), and u_kj a unit Gauss-Markov process along the path: u_kj = rho_k u_(k-1)j +
# sqrt(1 - rho_k^2) e, rho_k = exp(-|p_k - p_(k-1)| / d_corr) (Gudmundson). Whitened, z_kj = y_kj / sigma_kj and
# w_kj = z_kj - rho_k z_(k-1)j have independent unit / (1 - rho_k^2) variances, so each reading's information ties
# x_(k-1), x_k and nu: the whole run's Fisher information is block tridiagonal in the states plus dense nuisance
# rows. Jacobians are taken at the truth and at nu = 0 (as the ideal bound's are); the depth switch of the
# path-loss set is not differentiated.
#
# Dropouts and outliers are left out: every reading is counted, as a Gaussian one. Both only add information
# (a lost reading has none; a contaminated Gaussian has less Fisher information than its core), so the result
# stays a lower bound, looser than the exact one. A capsule that does not move between frames gets the same
# shadowing twice (rho = 1): the whitened variance is floored at RHO_FLOOR_VAR, which ties the two positions
# along the sensors' gradients as the exact model does, without an infinite information.

RHO_FLOOR_VAR = 1e-6
# the information form inverts each step's Q: its 1-sigma floored at 1 um / 1 urad (far below any visual step's
# error; a run scored with perfect steps would otherwise have Q = 0)
STEP_SD_FLOOR = 1e-6


def _nuisance_jacobian(p_w_m, sensors_w_m, normals_w, pl, channel):
    """``(d mean / d p (S, 3), d mean / d nu (S, m), sigma (S,))`` at ``p`` with the nuisance block ordered PL(d0)
    offsets, exponent offsets, placement offsets (x, y, z per sensor), each kind present only if its prior spread
    is > 0."""
    _, sigma, grad_p = pl.predict(p_w_m, sensors_w_m, normals_w)
    S = len(sensors_w_m)
    cols = []
    if channel.pl0_sd_db > 0:
        cols.append(-np.eye(S))  # RSS = Pt - (PL(d0) + b) - ...
    if channel.alpha_sd > 0:
        d = np.linalg.norm(sensors_w_m - p_w_m, axis=1)
        cols.append(np.diag(-10.0 * np.log10(np.maximum(d, 1e-4) / pl.d0_m)))
    if channel.placement_sd_m > 0:  # the mean depends on p - s: d/ds = -d/dp, one sensor's block per row
        block = np.zeros((S, 3 * S))
        for j in range(S):
            block[j, 3 * j:3 * j + 3] = -grad_p[j]
        cols.append(block)
    grad_nu = np.hstack(cols) if cols else np.zeros((S, 0))
    return grad_p, grad_nu, sigma


def _nuisance_prior(channel, S):
    sd = ([channel.pl0_sd_db] * S if channel.pl0_sd_db > 0 else []) + \
         ([channel.alpha_sd] * S if channel.alpha_sd > 0 else []) + \
         ([channel.placement_sd_m] * (3 * S) if channel.placement_sd_m > 0 else [])
    return np.diag(1.0 / np.square(np.asarray(sd, float))) if sd else np.zeros((0, 0))


def _channel_information(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, sensors_w_m, normals_w, pl, P0,
                         channel):
    """The whole run's Fisher information in blocks: diagonal ``D (n, 6, 6)``, off-diagonal ``E (n-1, 6, 6)``
    (``J[x_k, x_(k+1)]``), state-nuisance ``B (n, 6, m)`` and nuisance ``N (m, m)``; and per frame the terms a
    causal pass adds (:func:`channel_bounds`)."""
    n = len(positions_w_m)
    S = len(sensors_w_m)
    sigma_t_m = np.maximum(sigma_t_m, STEP_SD_FLOOR)
    sigma_r_rad = np.maximum(sigma_r_rad, STEP_SD_FLOOR)
    jac = [_nuisance_jacobian(p, sensors_w_m, normals_w, pl, channel) for p in positions_w_m]
    a = np.array([g / s[:, None] for g, _, s in jac])  # (n, S, 3): the whitened readings' position gradients
    c = np.array([g / s[:, None] for _, g, s in jac])  # (n, S, m)
    m = c.shape[2]
    step = np.linalg.norm(np.diff(positions_w_m, axis=0), axis=1)
    rho = np.exp(-step / channel.shadowing_corr_m) if channel.shadowing_corr_m > 0 else np.zeros(n - 1)
    D = np.zeros((n, 6, 6))
    E = np.zeros((max(n - 1, 0), 6, 6))
    B = np.zeros((n, 6, m))
    N = _nuisance_prior(channel, S) if m else np.zeros((0, 0))
    D[0] += np.linalg.inv(P0)
    # per frame k the reading terms: (k-1, k-1), (k-1, k), (k, k) position blocks, (k-1, nu), (k, nu), (nu, nu)
    meas = []
    for k in range(n):
        if k == 0:
            r, v, cw = 0.0, 1.0, c[0]
        else:
            r = rho[k - 1]
            v = max(1.0 - r * r, RHO_FLOOR_VAR)
            cw = c[k] - r * c[k - 1]
        prev = a[k - 1] if k else np.zeros((S, 3))
        t = {"pp": r * r * prev.T @ prev / v, "pc": -r * prev.T @ a[k] / v, "cc": a[k].T @ a[k] / v,
             "pn": -r * prev.T @ cw / v, "cn": a[k].T @ cw / v, "nn": cw.T @ cw / v}
        meas.append(t)
        D[k, :3, :3] += t["cc"]
        B[k, :3] += t["cn"]
        N = N + t["nn"]
        if k:
            D[k - 1, :3, :3] += t["pp"]
            E[k - 1, :3, :3] += t["pc"]
            B[k - 1, :3] += t["pn"]
    steps = []
    for k in range(n - 1):
        A, Q = _transition(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad, k)
        Qi = np.linalg.inv(Q)
        steps.append((A, Qi))
        D[k] += A.T @ Qi @ A
        D[k + 1] += Qi
        E[k] += -A.T @ Qi
    return D, E, B, N, meas, steps


def _smoothing_from_information(D, E, B, N):
    """The 6x6 state blocks of ``J^-1`` for ``J = [[T, B], [B^T, N]]``, ``T`` block tridiagonal (``D``, ``E``):
    ``T^-1``'s diagonal blocks by the block LDL^T recursion, ``T^-1 B`` by its two sweeps, then
    ``J^-1`` top-left ``= T^-1 + (T^-1 B) (N - B^T T^-1 B)^-1 (T^-1 B)^T``. O(n m^2), no (6n)^2 matrix."""
    n = len(D)
    S = np.zeros_like(D)
    S[0] = D[0]
    for k in range(1, n):
        S[k] = D[k] - E[k - 1].T @ np.linalg.solve(S[k - 1], E[k - 1])
    Sinv = np.linalg.inv(S)
    sig = np.zeros_like(D)
    sig[-1] = Sinv[-1]
    for k in range(n - 2, -1, -1):
        G = Sinv[k] @ E[k]
        sig[k] = Sinv[k] + G @ sig[k + 1] @ G.T
    m = N.shape[0]
    if m == 0:
        return sig
    y = np.zeros_like(B)
    y[0] = B[0]
    for k in range(1, n):
        y[k] = B[k] - E[k - 1].T @ Sinv[k - 1] @ y[k - 1]
    X = np.zeros_like(B)
    X[-1] = Sinv[-1] @ y[-1]
    for k in range(n - 2, -1, -1):
        X[k] = Sinv[k] @ (y[k] - E[k] @ X[k + 1])
    schur = N - np.einsum("kim,kin->mn", B, X)
    return sig + X @ np.linalg.solve(schur, np.transpose(X, (0, 2, 1)))


def channel_bounds(positions_w_m: np.ndarray, rotations_w_c: Rotation, sigma_t_m: np.ndarray,
                   sigma_r_rad: np.ndarray, sensors_w_m: np.ndarray, normals_w: np.ndarray, pl: PathLossModel,
                   P0: np.ndarray, channel, full_state: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The filtering (causal) and smoothing bounds ``(n, 3, 3)`` each (m^2) under a real channel
    (``testbed.rf.ChannelModel``; the model above): correlated shadowing and the per-sensor departures as
    nuisance parameters with their priors. With an ideal channel they equal :func:`position_bounds`.
    ``full_state``: the whole state's blocks ``(n, 6, 6)`` instead, position (m^2) then orientation (rad^2).

    Causal: frame ``k``'s bound is the position block of the inverse information of states ``0..k`` and ``nu``
    from readings ``0..k``, carried as the information of ``(x_k, nu)`` with the earlier states marginalised (a
    reading ties ``x_(k-1)`` and ``x_k``, so each step works on ``(x_k, x_(k+1), nu)``)."""
    positions_w_m = np.asarray(positions_w_m, float)
    D, E, B, N, meas, steps = _channel_information(positions_w_m, rotations_w_c, sigma_t_m, sigma_r_rad,
                                                   sensors_w_m, normals_w, pl, P0, channel)
    n, m = len(D), N.shape[0]
    filt = np.zeros((n, 6, 6))
    # (x_k, nu) information from frames <= k: the prior, frame 0's readings
    M = np.zeros((6 + m, 6 + m))
    M[:6, :6] = np.linalg.inv(P0) + np.pad(meas[0]["cc"], ((0, 3), (0, 3)))
    M[:3, 6:] = meas[0]["cn"]
    M[6:, :3] = meas[0]["cn"].T
    if m:
        M[6:, 6:] = _nuisance_prior(channel, len(sensors_w_m)) + meas[0]["nn"]
    filt[0] = np.linalg.inv(M)[:6, :6]
    for k in range(n - 1):
        A, Qi = steps[k]
        t = meas[k + 1]
        big = np.zeros((12 + m, 12 + m))  # (x_k, x_(k+1), nu)
        big[:6, :6] = M[:6, :6] + A.T @ Qi @ A
        big[:6, 6:12] = -A.T @ Qi
        big[6:12, 6:12] = Qi
        big[:3, :3] += t["pp"]
        big[:3, 6:9] += t["pc"]
        big[6:9, 6:9] += t["cc"]
        if m:
            big[:6, 12:] = M[:6, 6:]
            big[12:, 12:] = M[6:, 6:] + t["nn"]
            big[:3, 12:] += t["pn"]
            big[6:9, 12:] += t["cn"]
        big = np.triu(big) + np.triu(big, 1).T
        filt[k + 1] = np.linalg.inv(big)[6:12, 6:12]
        M = big[6:, 6:] - big[6:, :6] @ np.linalg.solve(big[:6, :6], big[:6, 6:])
    smooth = _smoothing_from_information(D, E, B, N)
    return (filt, smooth) if full_state else (filt[:, :3, :3], smooth[:, :3, :3])

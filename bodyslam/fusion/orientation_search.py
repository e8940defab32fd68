"""Where the filter starts, and restarts: the orientation under which it best explains the RF readings.

Vision alone has no world frame and RF alone no orientation, so the fusion's start is searched, and searched
again after long runs of steps without a visual estimate (the capsule may have turned any way meanwhile, and a
linearised filter does not recover from errors of tens of degrees: measured on seeds 301, 306, 308).

:func:`search_orientation` runs the filter (:class:`bodyslam.fusion.ekf.ErrorStateEkf`, all candidates as one batch)
over the window ``k0 .. k1-1`` from: the centre orientation (the rigid alignment, or the filter's own
prediction), the centre turned by each of the 59 other rotations of the icosahedral group (no orientation is
more than 44 deg from one of the 60), and given extras; at a quarter and at half of the window, turns of 20 and
10 deg about 14 axes of the candidate leading then join (no look-ahead). The committed candidate explains the
whole window best (negative log-likelihood of the readings: a decision with a ``k1 - k0`` frame lag); while the
decision is open the online output is the candidates' likelihood-weighted mixture on the readings so far (a
Gaussian-sum filter whose covariance includes the candidates' spread).

A search may score a later part of its run only (``score_from``): the start's recheck runs every candidate from
frame 0, each with its own start position and fresh RSS bias states, and compares them on the next window's
readings. Searched from the committed run's pose at the window's start instead, the candidates inherit a position
and bias states fitted under the orientation in question (with bias states on, a start put 150 deg off had
drifted 14 cm and its biases absorbed the misfit: the recheck turned it 120 deg, the wrong way).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.fusion.ekf import ErrorStateEkf

__all__ = ["SearchResult", "search_orientation"]


@dataclass
class SearchResult:
    R: Rotation  # the committed orientation at the frame the candidates start from (k0; 0 for the recheck)
    p_w_m: np.ndarray  # its start position
    frames: tuple[int, int]  # the window scored, k0 .. k1-1 (score_from .. k1-1 with score_from)
    n_candidates: int
    turn_from_centre_deg: float
    nll_centre: float
    nll_best: float
    mixture_positions_w_m: np.ndarray  # (k1 - k0, 3): the online output while the decision is open
    mixture_cov: np.ndarray  # (k1 - k0, 6, 6)
    # per frame, on the readings so far: how far the leading candidate's negative log-likelihood is below the
    # centre's (nats, >= 0); its last value is nll_centre - nll_best
    lead_nll: np.ndarray | None = None
    # per frame, the orientation of the candidate leading on the readings so far (k1 - k0, 3, 3): the online
    # orientation while the decision is open (a mixture of rotations is not one)
    leader_rotations: np.ndarray | None = None
    # per frame, the least cumulative negative log-likelihood of any candidate on the readings so far (nats)
    least_nll: np.ndarray | None = None


def _cube_axes() -> np.ndarray:
    """The 14 axes through a cube's faces (6) and corners (8), unit length."""
    axes = np.array([v for v in np.ndindex(3, 3, 3) if sum(abs(np.array(v) - 1)) in (1, 3)], float) - 1.0
    return axes / np.linalg.norm(axes, axis=1, keepdims=True)


def search_orientation(ekf: ErrorStateEkf, k0: int, k1: int, R_centre: Rotation,
                       position_of: Callable[[Rotation], np.ndarray], P: np.ndarray,
                       extra: list[Rotation], bias: np.ndarray | None = None,
                       score_from: int | None = None) -> SearchResult:
    """The orientation at frame ``k0`` under which the filter best explains frames ``k0 .. k1-1`` (module
    docstring). ``position_of(R)``: the start position that goes with ``R``; every candidate starts from the
    covariance ``P`` (6 x 6, or the filter's whole state) and the RSS bias states ``bias`` (default zero).
    ``score_from``: the candidates run from ``k0`` but are compared, mixed and refined on frames ``score_from ..
    k1-1`` only, and the per-frame outputs cover those frames."""
    ks = k0 if score_from is None else int(score_from)
    if not k0 <= ks < k1:
        raise ValueError(f"score_from {ks} outside the run {k0} .. {k1 - 1}")
    group = Rotation.create_group("I")
    cands = [R_centre] + [R_centre * g for g in group if g.magnitude() > 1e-6] + list(extra)
    pool = []  # (R, p, cumulative nll per frame, positions, covariances, first frame it may be used, rotations)

    def add(Rs, first):
        ps = np.array([position_of(R) for R in Rs])
        pos, rot, covs, nll_k, _ = ekf.run(ps, np.array([R.as_matrix() for R in Rs]),
                                           np.repeat(P[None], len(Rs), axis=0), k0, k1,
                                           b=None if bias is None else np.repeat(bias[None], len(Rs), axis=0))
        pool.extend((R, pr, nk, x, c, first, o) for R, pr, nk, x, c, o in zip(Rs, ps, nll_k, pos, covs, rot))

    def scored(nk):  # the cumulative nll over frames ks .. k1-1
        return nk[ks - k0:] - (nk[ks - k0 - 1] if ks > k0 else 0.0)

    add(cands, ks)
    for frac, step_deg in ((0.25, 20.0), (0.5, 10.0)):
        kc = ks + max(1, int((k1 - ks) * frac))
        if kc >= k1:
            break
        lead = pool[int(np.argmin([scored(c[2])[kc - 1 - ks] for c in pool]))][0]
        add([lead * Rotation.from_rotvec(np.radians(step_deg) * a) for a in _cube_axes()], kc)
    pool = [(R, pr, scored(nk), x[ks - k0:], c[ks - k0:], first, o[ks - k0:]) for R, pr, nk, x, c, first, o in pool]
    nll_k = np.array([c[2] for c in pool])  # (candidates, frames)
    frames = np.arange(ks, k1)
    avail = np.array([c[5] for c in pool])[:, None] <= frames[None, :]
    nll_k = np.where(avail, nll_k, np.inf)
    wgt = np.exp(-(nll_k - nll_k.min(axis=0)))
    wgt /= wgt.sum(axis=0)
    X = np.array([c[3] for c in pool])  # (c, f, 3)
    mix_pos = np.einsum("cf,cfi->fi", wgt, X)
    mix_cov = np.einsum("cf,cfij->fij", wgt, np.array([c[4] for c in pool]))
    d = X - mix_pos[None]
    mix_cov[:, :3, :3] += np.einsum("cf,cfi,cfj->fij", wgt, d, d)
    best = int(np.argmin(nll_k[:, -1]))
    R, p = pool[best][0], pool[best][1]
    leader = np.argmin(nll_k, axis=0)
    lead_rot = np.array([pool[c][6][i] for i, c in enumerate(leader)])
    return SearchResult(R, p, (ks, k1), len(pool), float(np.degrees((R_centre.inv() * R).magnitude())),
                        float(nll_k[0, -1]), float(nll_k[best, -1]), mix_pos, mix_cov, nll_k[0] - nll_k.min(axis=0),
                        lead_rot, nll_k.min(axis=0))

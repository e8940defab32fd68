"""Centre lines of intestine tubes: ordered 3D curves resampled by arc length, with a lumen radius per point.

Data form: a :class:`Centerline` holds ``n`` samples at uniform arc-length spacing ``ds_m``: arc length ``s_m (n,)``,
points ``points_w (n, 3)`` in metres in the body (world) frame, unit tangents ``tangents_w (n, 3)``, a rotation-
minimising frame ``normals_w``/``binormals_w`` (``normal x binormal = tangent``) and the lumen radius ``radius_m (n,)``.

Two sources: :func:`procedural_centerline` (a seeded small-intestine-like curve packed in the abdomen volume)
and :mod:`testbed.anatomy` (extracted from an anatomical mesh). Both go through :meth:`Centerline.from_curve`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import BSpline, make_splprep
from scipy.spatial import cKDTree

from bodyslam.errors import ConfigError, GeometryError, InputError
from bodyslam.io import write_csv

log = logging.getLogger(__name__)

__all__ = ["Centerline", "procedural_centerline", "rotation_minimizing_frames", "min_self_distance"]


def rotation_minimizing_frames(points: np.ndarray, tangents: np.ndarray, normal0: np.ndarray | None = None):
    """Rotation-minimising frames along a polyline (double reflection, Wang et al. 2008, ACM TOG 27(1)).

    Parameters
    ----------
    points : (n, 3) float, curve samples.
    tangents : (n, 3) float, unit tangents at the samples.
    normal0 : (3,) float, optional first normal (projected to be orthogonal to the first tangent).

    Returns
    -------
    normals, binormals : (n, 3) float, unit, with ``normal x binormal = tangent``.
    """
    n = len(points)
    t = tangents
    if normal0 is None:
        a = np.eye(3)[np.argmin(np.abs(t[0]))]
        normal0 = np.cross(t[0], a)
    r = np.asarray(normal0, dtype=np.float64) - np.dot(normal0, t[0]) * t[0]
    r /= np.linalg.norm(r)
    normals = np.empty((n, 3))
    normals[0] = r
    for i in range(n - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        if c1 < 1e-30:
            normals[i + 1] = normals[i]
            continue
        rl = normals[i] - (2.0 / c1) * (v1 @ normals[i]) * v1
        tl = t[i] - (2.0 / c1) * (v1 @ t[i]) * v1
        v2 = t[i + 1] - tl
        c2 = v2 @ v2
        rn = rl if c2 < 1e-30 else rl - (2.0 / c2) * (v2 @ rl) * v2
        rn -= (rn @ t[i + 1]) * t[i + 1]
        normals[i + 1] = rn / np.linalg.norm(rn)
    binormals = np.cross(t, normals)
    return normals, binormals


def min_self_distance(points: np.ndarray, s_m: np.ndarray, exclude_arc_m: float) -> float:
    """Smallest distance between two samples more than ``exclude_arc_m`` apart along the curve (inf if none)."""
    tree = cKDTree(points)
    best = math.inf
    # Query a generous radius and keep pairs far apart in arc length.
    r = exclude_arc_m
    for radius in (r, 4 * r):
        pairs = tree.query_pairs(radius, output_type="ndarray")
        if len(pairs):
            far = np.abs(s_m[pairs[:, 0]] - s_m[pairs[:, 1]]) > exclude_arc_m
            if far.any():
                d = np.linalg.norm(points[pairs[far, 0]] - points[pairs[far, 1]], axis=1)
                return float(min(best, d.min()))
    return best


@dataclass(frozen=True, eq=False)
class Centerline:
    """An ordered centre line sampled at uniform arc length (see module docstring for the data form)."""

    s_m: np.ndarray
    points_w: np.ndarray
    tangents_w: np.ndarray
    normals_w: np.ndarray
    binormals_w: np.ndarray
    radius_m: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    @property
    def ds_m(self) -> float:
        return float(self.s_m[1] - self.s_m[0])

    @classmethod
    def from_curve(cls, curve: BSpline, radius_fn, ds_m: float = 5e-4, n_dense: int | None = None) -> "Centerline":
        """Resample a parametric curve ``curve(u) -> (3,)`` by arc length.

        ``radius_fn(s_m (n,)) -> (n,)`` gives the lumen radius at arc length ``s``.
        """
        t = curve.t
        u0, u1 = t[curve.k], t[-curve.k - 1]
        n_dense = n_dense or 200_000
        u = np.linspace(u0, u1, n_dense)
        p = curve(u)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s_dense = np.concatenate([[0.0], np.cumsum(seg)])
        length = s_dense[-1]
        if not length > 10 * ds_m:
            raise GeometryError(f"centre line too short ({length:.4f} m) for spacing {ds_m} m")
        n = int(math.floor(length / ds_m)) + 1
        s = np.arange(n) * ds_m
        u_s = np.interp(s, s_dense, u)
        pts = curve(u_s)
        der = curve.derivative()(u_s)
        tan = der / np.linalg.norm(der, axis=1, keepdims=True)
        normals, binormals = rotation_minimizing_frames(pts, tan)
        radius = np.asarray(radius_fn(s), dtype=np.float64)
        if radius.shape != s.shape or not np.all(radius > 0):
            raise GeometryError("radius profile must be positive at every sample")
        return cls(s, pts, tan, normals, binormals, radius)

    @classmethod
    def from_points(cls, points_w: np.ndarray, radius_m: np.ndarray | float, ds_m: float = 5e-4,
                    smoothing_m: float = 0.0) -> "Centerline":
        """Fit a cubic smoothing spline through ordered points and resample it.

        ``smoothing_m`` is the RMS distance the spline may stay away from the points (0 interpolates).
        ``radius_m`` is a scalar or one radius per input point (interpolated along the arc length).
        """
        pts = np.asarray(points_w, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
            raise InputError(f"centre line needs at least 4 points of shape (n, 3), got {pts.shape}")
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        pts = pts[keep]
        chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        u = chord / chord[-1]
        spl, _ = make_splprep(pts.T, u=u, k=3, s=len(pts) * smoothing_m**2)
        curve = _VectorSpline(spl)
        r_in = np.broadcast_to(np.asarray(radius_m, dtype=np.float64), (len(keep),))[keep]

        def radius_fn(s):
            return np.interp(s / s[-1] * chord[-1], chord, r_in)

        return cls.from_curve(curve, radius_fn, ds_m=ds_m)

    def index_at(self, s_m: np.ndarray | float) -> np.ndarray:
        """Fractional sample index of arc length ``s_m`` (clipped to the curve)."""
        return np.clip(np.asarray(s_m, dtype=np.float64) / self.ds_m, 0.0, len(self.s_m) - 1.0)

    def frame_at(self, s_m: np.ndarray | float):
        """Interpolated ``(point (n,3), R_w_tube (n,3,3), radius (n,))`` at arc lengths ``s_m``.

        ``R_w_tube`` has columns ``[normal, binormal, tangent]``: the tube frame whose z axis runs down the lumen.
        """
        f = np.atleast_1d(self.index_at(s_m))
        i0 = np.minimum(np.floor(f).astype(int), len(self.s_m) - 2)
        w = (f - i0)[:, None]
        lerp = lambda a: (1.0 - w) * a[i0] + w * a[i0 + 1]  # noqa: E731
        p = lerp(self.points_w)
        t = lerp(self.tangents_w)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        nrm = lerp(self.normals_w)
        nrm -= np.sum(nrm * t, axis=1, keepdims=True) * t
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        b = np.cross(t, nrm)
        R = np.stack([nrm, b, t], axis=-1)
        r = (1.0 - w[:, 0]) * self.radius_m[i0] + w[:, 0] * self.radius_m[i0 + 1]
        return p, R, r

    def curvature_per_m(self) -> np.ndarray:
        """(n,) curvature from the tangent's turn rate, 1/m."""
        dt = np.gradient(self.tangents_w, self.ds_m, axis=0)
        return np.linalg.norm(dt, axis=1)

    def write_csv(self, path: str | Path) -> None:
        rows = np.column_stack([self.s_m, self.points_w, self.radius_m])
        write_csv(path, ["s_m", "x_m", "y_m", "z_m", "radius_m"], rows.tolist())

    @classmethod
    def read_csv(cls, path: str | Path, ds_m: float = 5e-4) -> "Centerline":
        """Read ``s_m,x_m,y_m,z_m,radius_m`` (as written by :meth:`write_csv`) and resample it."""
        path = Path(path)
        try:
            a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except FileNotFoundError:
            raise InputError(f"{path}: file not found") from None
        except ValueError as exc:
            raise InputError(f"{path}: malformed centre-line CSV ({exc})") from None
        if a.shape[1] != 5:
            raise InputError(f"{path}: expected columns s_m,x_m,y_m,z_m,radius_m, got {a.shape[1]} columns")
        return cls.from_points(a[:, 1:4], a[:, 4], ds_m=ds_m)


class _VectorSpline:
    """Adapter: a scipy vector-valued BSpline from make_splprep returns (3, n); we want (n, 3)."""

    def __init__(self, spl: BSpline):
        self.spl = spl
        self.t = spl.t
        self.k = spl.k

    def __call__(self, u):
        out = np.asarray(self.spl(u))
        return out.T if out.shape[0] == 3 and out.ndim == 2 else out

    def derivative(self):
        return _VectorSpline(self.spl.derivative())


def _lattice_walk(shape: tuple[int, int, int], n_nodes: int, rng: np.random.Generator,
                  straight_bonus: float = 2.5) -> list[tuple[int, int, int]]:
    """A self-avoiding walk of ``n_nodes`` nodes on a 3D lattice (randomised DFS with Warnsdorff's rule)."""
    dirs = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]

    def inside(p):
        return all(0 <= p[i] < shape[i] for i in range(3))

    def free_neighbours(p, used):
        return [q for q in ((p[0] + d[0], p[1] + d[1], p[2] + d[2]) for d in dirs) if inside(q) and q not in used]

    budget = [200_000]
    start = tuple(int(rng.integers(0, s)) for s in shape)
    path = [start]
    used = {start}

    def dfs() -> bool:
        if len(path) >= n_nodes:
            return True
        budget[0] -= 1
        if budget[0] < 0:
            return False
        cand = free_neighbours(path[-1], used)
        rng.shuffle(cand)
        # Warnsdorff (fewest onward moves first) finds long walks; a bonus for going straight on keeps the number
        # of bends (and so the capsule's tilt per step) near a real small bowel's instead of turning at every node.
        prev = path[-2] if len(path) > 1 else None

        def key(q):
            straight = prev is not None and all(q[i] - path[-1][i] == path[-1][i] - prev[i] for i in range(3))
            return len(free_neighbours(q, used)) - (straight_bonus if straight else 0.0)

        cand.sort(key=key)
        for q in cand:
            path.append(q)
            used.add(q)
            if dfs():
                return True
            path.pop()
            used.discard(q)
        return False

    import sys

    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 10 * n_nodes + 1000))
    try:
        ok = dfs()
    finally:
        sys.setrecursionlimit(old)
    if not ok:
        raise GeometryError(f"no self-avoiding walk of {n_nodes} nodes found on a {shape} lattice")
    return path


def procedural_centerline(
    length_m: float,
    rng: np.random.Generator | int | None,
    radius_fn=None,
    radius_max_m: float = 0.015,
    abdomen_box_m: tuple[float, float, float] = (0.32, 0.24, 0.34),
    min_self_distance_diameters: float = 2.0,
    jitter: float = 0.04,
    ds_m: float = 5e-4,
    max_tries: int = 20,
) -> Centerline:
    """A seeded small-intestine-like centre line packed inside the abdomen volume.

    Construction: a self-avoiding walk on a cubic lattice of spacing ``a = 1.15 * d_min`` filling the abdomen box
    (centred at the body origin, axes x left, y anterior, z cranial), nodes jittered by ``jitter * a``, smoothed by a
    uniform quintic B-spline with the nodes as control points, cut to ``length_m``. The result is checked: any two
    points farther apart than ``d_min * pi / 2`` along the curve are at least ``d_min`` apart in space
    (``d_min = min_self_distance_diameters * 2 * radius_max_m``), and the bend radius stays above 1.2 tube radii so
    the swept tube never folds onto itself. A draw that fails is redrawn (same seed, next sub-stream).

    Raises
    ------
    ConfigError
        Length or box that cannot hold the curve.
    GeometryError
        No valid curve found in ``max_tries`` draws.
    """
    if not length_m > 0:
        raise ConfigError(f"path length must be positive, got {length_m} m")
    rng = np.random.default_rng(rng)
    if radius_fn is None:
        radius_fn = lambda s: np.full_like(s, radius_max_m)  # noqa: E731
    d_min = min_self_distance_diameters * 2.0 * radius_max_m
    a = 1.15 * d_min
    box = np.asarray(abdomen_box_m, dtype=np.float64)
    usable = box - 2.0 * (radius_max_m + jitter * a)
    shape = tuple(int(max(1, math.floor(u / a) + 1)) for u in usable)
    n_lattice = shape[0] * shape[1] * shape[2]
    n_nodes = int(math.ceil(length_m / (0.72 * a))) + 3  # the B-spline is ~25% shorter than its control polygon
    if n_nodes > 0.9 * n_lattice:
        raise ConfigError(
            f"a {length_m} m path with self-distance >= {d_min * 100:.1f} cm does not fit the abdomen box "
            f"{tuple(float(x) for x in box)} m (at most about {0.9 * n_lattice * a * 0.72:.1f} m); enlarge the box or shorten the path"
        )
    origin = -(np.array(shape) - 1) * a / 2.0
    for attempt in range(max_tries):
        walk = np.array(_lattice_walk(shape, n_nodes, rng), dtype=np.float64)
        ctrl = origin + walk * a + rng.uniform(-jitter * a, jitter * a, size=walk.shape)
        k = 5  # quintic: curvature-continuous and gentler bends than cubic
        n_ctrl = len(ctrl)
        knots = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, n_ctrl - k + 1), np.ones(k)])
        curve = BSpline(knots, ctrl, k)
        full = Centerline.from_curve(curve, lambda s: np.full_like(s, radius_max_m), ds_m=ds_m)
        if full.length_m < length_m:
            log.debug("draw %d too short (%.3f m)", attempt, full.length_m)
            continue
        n_keep = int(math.floor(length_m / ds_m)) + 1
        pts = full.points_w[:n_keep]
        s = full.s_m[:n_keep]
        kappa = full.curvature_per_m()[:n_keep]
        if kappa.max() * 1.2 * radius_max_m >= 1.0:
            log.debug("draw %d bends too tightly (min bend radius %.4f m)", attempt, 1 / kappa.max())
            continue
        dmin = min_self_distance(pts, s, d_min * math.pi / 2.0)
        if dmin < d_min:
            log.debug("draw %d comes %.4f m close to itself (< %.4f m)", attempt, dmin, d_min)
            continue
        radius = np.asarray(radius_fn(s), dtype=np.float64)
        return Centerline(s, pts, full.tangents_w[:n_keep], full.normals_w[:n_keep], full.binormals_w[:n_keep],
                          radius)
    raise GeometryError(f"no valid {length_m} m centre line in {max_tries} draws; relax the box or the spacing")

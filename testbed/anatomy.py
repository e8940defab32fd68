"""Centre lines from anatomical meshes (the dissertation's 3D skeletonisation, Sec. 4.2.1.2).

Method: the closed surface is scaled to millimetres (``voxel_size_mm`` per mesh unit: CT meshes are often in grid
units), voxelised at ``pitch_mm`` and filled; the Euclidean distance transform gives the lumen radius at every
voxel; the volume is thinned to a one-voxel skeleton (scikit-image). The skeleton's 26-neighbour graph is reduced
to a tree by a minimum spanning tree whose edge cost favours the thick middle of the lumen (cost = length x
(1 + (r_ref / r)^2)), so thin bridges where two loops touch are the edges that get cut. The longest path of that tree
(double Dijkstra) is the centre line from one end to the other; it is smoothed by a spline and resampled by arc
length, with the distance-transform radius along it.

Loop repair: where two loops of bowel touch, the voxelised lumen has a bridge, and when a loop is also narrow
somewhere (a collapsed segment) the spanning tree cuts the loop instead of the bridge, so the longest path takes
the shortcut and skips the loop. :func:`_reroute_through_loops` then swaps edges: it re-adds a skeleton edge that
closes a long cycle and cuts the thinnest edge of that cycle lying on the current path (the bridge), keeping the
swap when the end-to-end path grows by at least ``min_gain_mm``. Each accepted swap adds a whole loop; small
gains are detours into a contact region and are refused. The 50 mm default was chosen on the one real gut we
have (EdinGCA_3D_00090: gains 473, 91, 75, 71, 60 mm, then 48, 37, 27 ... which no longer improve the score), so
it is tuned on the data it is scored on; see ``benchmarks/bench_centerline.py``.

Meshes that are not watertight (issue 15: real segmentations come in open pieces with holes of several cm): every
boundary loop -- a hole in the wall or the open end of a piece -- is capped by a fan of triangles from the loop's
centroid (:func:`cap_boundaries`), which closes the voxelised shell so the fill finds each piece's inside. Each
piece is skeletonised on its own (pieces that touch must not merge). Its skeleton tree (the same spanning tree)
is split into branches at its junctions (:func:`_piece_branches`), after leaf branches shorter than ``SPUR_MM``
are pruned (the spurs a thinning leaves toward a cap's rim), and ends are trimmed where the lumen radius falls
below half the piece's median (:func:`_trim_spurs`). Splitting matters where two loops of bowel touch inside one
open piece: its skeleton is an X, and one end-to-end path would run from one loop into the other and leave
half of each out (session 17; before it, pieces gave their longest path only). All branches of all pieces are
chained end to end (:func:`_chain_pieces`: greedy matching of ends, the cheapest gap first, a gap counted longer
the more either end would have to turn to meet it, plus ``TURN_MM`` per unit of that turn so that arms meeting at
one junction pair straight on; the gap limit doubled for what is left; a branch shorter than ``SHORT_MM`` joins
only across ``SHORT_GAP_MM`` or less, so loose spurs are not strung in); the longest chain's order is then
repaired by local search, which also leaves out side branches whose joining costs more than ``DROP_RATIO`` times
their length (:func:`_improve_order`, session 31); gaps are bridged by a cubic Hermite curve along the two end
tangents, its radius interpolated. Pieces shorter than ``min_piece_mm`` (debris), pieces whose
skeleton's median lumen radius is under 1.5 voxels (an open sheet: capped, it fills a slab, not a lumen) and
branches no chain reaches are left out, with a warning. A watertight mesh takes none of these steps: its figure is
unchanged. Scored on the CT gut cut open (``benchmarks/bench_centerline.py --open``; the constants were chosen on
cuts 0-9, docs/RESULTS.md).

Data form: returns a :class:`~testbed.centerline.Centerline` in metres (mesh frame scaled to mm, then to m).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from bodyslam.errors import InputError
from testbed.centerline import Centerline

log = logging.getLogger(__name__)

# Open pieces (module docstring), chosen on the CT gut's development cuts 0-9 (docs/RESULTS.md): a thinned tube's
# spurs toward a cap's rim are ~one lumen radius (5-8 mm) long and thin; 22 mm pruned real arms (coverage 0.87-0.96
# against 0.90-0.96 at 15); short branches strung in across any gap made the line 26-45% longer than the gut
TRIM_FRAC, TRIM_MAX_MM = 0.5, 15.0
SPUR_MM = 15.0
SHORT_MM, SHORT_GAP_MM = 30.0, 10.0
TURN_MM = 5.0  # mm of gap one unit of turn costs (0: the turn only scales the gap's length, nothing at a junction)
# a piece left out of the chain costs this times its length (:func:`_improve_order`; session 31, development cuts 0-9,
# precision / coverage, mean and worst cut: 1.5 -> 0.839 / 0.937, 0.887; 2 -> 0.839 / 0.940, 0.887; 3 -> 0.835 /
# 0.942, 0.908; 4 and 6 -> 0.832 / 0.943, 0.909; before: 0.811 / 0.943, 0.898)
DROP_RATIO = 3.0

__all__ = ["load_mesh", "extract_centerline", "load_reference", "load_reference_csv", "load_reference_json",
           "voxel_size_from_config", "score_centerline", "cap_boundaries"]


def load_mesh(path: str | Path, repair: bool = False, allow_open: bool = False):
    """Load a closed triangle mesh (OBJ/STL/PLY/OFF/GLB, or legacy VTK POLYDATA as the GCA gut models ship their
    surfaces: :mod:`testbed.vtk_legacy`); ``allow_open``: an open one as it is.

    Raises
    ------
    InputError
        Missing file, not a mesh, empty, or not watertight unless ``allow_open`` (with ``repair``: holes are
        filled first, documented as trimesh's ``fill_holes``; still open afterwards is an error).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh file not found")
    if path.suffix.lower() == ".vtk":  # trimesh has no reader for it; the same processing as its loaders apply
        from testbed.vtk_legacy import read_polydata

        mesh = trimesh.Trimesh(*read_polydata(path), process=True)
    else:
        try:
            mesh = trimesh.load(path, force="mesh", process=True)
        except ImportError as exc:  # trimesh decodes text that is not UTF-8 with an optional module: not a mesh file
            raise InputError(f"{path}: not a readable mesh (neither its binary format nor UTF-8 text; trimesh "
                             f"would try other text encodings with {exc.name or 'an optional module'}, which the "
                             f"toolkit does not install)") from None
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise InputError(f"{path}: not a readable mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: contains no triangles")
    if not mesh.is_watertight and repair:
        trimesh.repair.fill_holes(mesh)
        trimesh.repair.fix_normals(mesh)
    if not mesh.is_watertight and not allow_open:
        raise InputError(f"{path}: mesh is not watertight (open boundary), so its inside is undefined"
                         + ("" if repair else "; try --repair to fill holes"))
    return mesh


def cap_boundaries(mesh):
    """``(capped mesh, loops, largest loop span in mesh units)``: every boundary loop (edges of one face)
    closed by a fan from its centroid. Orientation is not kept: the caps are for the voxel fill, which needs a
    closed shell, not a consistent one."""
    import trimesh

    e = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    bnd = uniq[counts == 1]
    if len(bnd) == 0:
        return mesh, 0, 0.0
    nv = len(mesh.vertices)
    g = sparse.coo_matrix((np.ones(len(bnd)), (bnd[:, 0], bnd[:, 1])), shape=(nv, nv))
    _, label = csgraph.connected_components(g, directed=False)
    loop_of_edge = label[bnd[:, 0]]
    loops = np.unique(loop_of_edge)
    verts, faces, span = [np.asarray(mesh.vertices, float)], [np.asarray(mesh.faces)], 0.0
    for i, lp in enumerate(loops):
        ed = bnd[loop_of_edge == lp]
        ring = np.unique(ed)
        pts = mesh.vertices[ring]
        span = max(span, float(np.max(np.linalg.norm(pts - pts.mean(0), axis=1))) * 2)
        verts.append(pts.mean(0)[None])
        faces.append(np.c_[ed, np.full(len(ed), nv + i)])
    capped = trimesh.Trimesh(np.vstack(verts), np.vstack(faces), process=False)
    return capped, len(loops), span


def extract_centerline(
    mesh_or_path,
    voxel_size_mm: tuple[float, float, float] = (1.0, 1.0, 1.0),
    pitch_mm: float = 1.0,
    repair: bool = False,
    smoothing_mm: float | None = None,
    min_gain_mm: float = 50.0,
    min_piece_mm: float = 20.0,
    max_gap_mm: float = 80.0,
    detail: dict | None = None,
) -> Centerline:
    """Centre line of a tubular mesh, closed or in open pieces (see module docstring). ``mesh_or_path``: a trimesh,
    a mesh file, or a list of mesh files taken as one mesh (a model's segmented surfaces, one file per region).
    ``detail``: a dict that receives, for a mesh in open pieces, the skeleton branches chained (``pieces``: ``[(points
    (k, 3) mm, radii (k,) mm)]``), the chain's order (``order``: ``[(piece, reversed)]``), and the gap limit and
    smoothing used (``max_gap_mm``, ``smoothing_mm``), for diagnostics (``benchmarks/bench_centerline.py
    --diagnose``)."""
    if isinstance(mesh_or_path, (str, Path)):
        mesh = load_mesh(mesh_or_path, repair, allow_open=True)
    elif isinstance(mesh_or_path, (list, tuple)):
        import trimesh

        if not mesh_or_path:
            raise InputError("no mesh file given")
        parts = [load_mesh(p, repair, allow_open=True) for p in mesh_or_path]
        mesh = parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)
    else:
        mesh = mesh_or_path.copy()
    if not pitch_mm > 0:
        raise InputError(f"pitch must be positive, got {pitch_mm} mm")
    mesh.vertices = mesh.vertices * np.asarray(voxel_size_mm, dtype=np.float64)
    sm = pitch_mm * 0.7 if smoothing_mm is None else smoothing_mm
    if mesh.is_watertight:
        pts_mm, r_mm, n_comp = _piece_path(mesh, pitch_mm, min_gain_mm)
        if n_comp > 1:
            log.warning("skeleton has %d pieces; the centre line follows the largest", n_comp)
        return Centerline.from_points(pts_mm / 1000.0, r_mm / 1000.0, ds_m=1e-3, smoothing_m=sm / 1000.0)
    # open: each piece capped and skeletonised on its own (pieces that touch must not merge), then chained
    parts = mesh.split(only_watertight=False)
    pieces, n_loops, span = [], 0, 0.0
    for part in parts:
        if float(np.max(part.extents)) < min_piece_mm:
            continue  # debris
        capped, nl, sp = cap_boundaries(part)
        n_loops, span = n_loops + nl, max(span, sp)
        try:
            branches = _piece_branches(capped, pitch_mm)
        except InputError:
            continue  # encloses nothing at this pitch
        if sum(_length_mm(p) for p, _ in branches) < min_piece_mm:
            continue
        pieces.extend(_trim_spurs(p_mm, r_mm) for p_mm, r_mm in branches)
    if not pieces:
        raise InputError(f"mesh is in {len(parts)} open piece(s), none enclosing a tube of {min_piece_mm:.0f} mm "
                         "or more at this pitch")
    pts_mm, r_mm, n_used = _chain_pieces(pieces, max_gap_mm, detail=detail)
    if detail is not None:
        detail.update(pieces=pieces, max_gap_mm=max_gap_mm, smoothing_mm=sm)
    log.warning("mesh is not watertight: %d piece(s), %d open boundaries capped (the largest %.0f mm across); "
                "centre line chained from %d skeleton branch(es) over %d gap(s)", len(parts), n_loops, span, n_used,
                n_used - 1)
    return Centerline.from_points(pts_mm / 1000.0, r_mm / 1000.0, ds_m=1e-3, smoothing_m=sm / 1000.0)


def _skeleton_tree(mesh_mm, pitch_mm: float):
    """The voxelised inside's skeleton (module docstring): ``(voxel indices (n, 3), origin mm, radius (n,) mm,
    skeleton graph, spanning tree)``, the graphs weighted by length in mm."""
    from skimage.morphology import skeletonize

    vox = mesh_mm.voxelized(pitch_mm).fill()
    inside = np.asarray(vox.matrix, dtype=bool)
    if inside.sum() < 50:
        raise InputError("mesh encloses too few voxels at this pitch; lower --pitch-mm")
    origin = np.asarray(vox.transform)[:3, 3]
    radius_vox = ndimage.distance_transform_edt(np.pad(inside, 1))[1:-1, 1:-1, 1:-1]
    skel = skeletonize(inside)
    idx = np.argwhere(skel)
    log.info("voxels %s inside %d, skeleton %d", inside.shape, inside.sum(), len(idx))
    if len(idx) < 4:
        raise InputError("skeleton too small; the mesh is not tubular at this pitch")
    r = radius_vox[tuple(idx.T)] * pitch_mm
    tree = cKDTree(idx)
    pairs = tree.query_pairs(np.sqrt(3) + 1e-6, output_type="ndarray")
    length = np.linalg.norm(idx[pairs[:, 0]] - idx[pairs[:, 1]], axis=1) * pitch_mm
    r_edge = 0.5 * (r[pairs[:, 0]] + r[pairs[:, 1]])
    r_ref = np.median(r)
    cost = length * (1.0 + (r_ref / np.maximum(r_edge, 0.5 * pitch_mm)) ** 2)
    n = len(idx)
    g = sparse.coo_matrix((cost, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    mst = csgraph.minimum_spanning_tree(g)
    mst = mst + mst.T
    mst_len = mst.tocoo()
    L = np.linalg.norm(idx[mst_len.row] - idx[mst_len.col], axis=1) * pitch_mm
    tree_g = sparse.coo_matrix((L, (mst_len.row, mst_len.col)), shape=(n, n)).tocsr()
    skel_g = sparse.coo_matrix((length, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    return idx, origin, r, skel_g + skel_g.T, tree_g


def _piece_path(mesh_mm, pitch_mm: float, min_gain_mm: float):
    """``(points (k, 3) mm, radius (k,) mm, skeleton components)``: the end-to-end path of a closed mesh's
    voxelised inside (module docstring), in the largest skeleton component."""
    idx, origin, r, skel_g, tree_g = _skeleton_tree(mesh_mm, pitch_mm)
    # Tree diameter by physical length on the MST's edges, then loop repair (see _reroute_through_loops).
    n_comp = csgraph.connected_components(tree_g, directed=False)[0]
    path = _reroute_through_loops(skel_g, tree_g, r, min_gain_mm)
    return origin + idx[path] * pitch_mm, r[path], n_comp


def _piece_branches(mesh_mm, pitch_mm: float, spur_mm: float = SPUR_MM) -> list:
    """``[(points (k, 3) mm, radius (k,) mm)]``: the branches of an open piece's skeleton tree (module
    docstring), split at its junctions, after leaf branches shorter than ``spur_mm`` are pruned (repeatedly:
    pruning one can leave another a leaf)."""
    idx, origin, r, _, tree_g = _skeleton_tree(mesh_mm, pitch_mm)
    if np.median(r) < 1.5 * pitch_mm:  # a sheet or a sliver: its capped shell fills a slab a voxel or two thick
        raise InputError(f"encloses no lumen: median radius {np.median(r):.1f} mm at a {pitch_mm:g} mm pitch")
    return [(origin + idx[b] * pitch_mm, r[b]) for b, _ in _pruned_branches(tree_g, spur_mm) if len(b) >= 2]


def _pruned_branches(tree_g, spur_mm: float) -> list:
    """:func:`_tree_branches` of a forest after its leaf branches shorter than ``spur_mm`` are removed, again until
    none is left (pruning one can leave another a leaf, and a junction that loses a spur joins its two others)."""
    t = tree_g.tolil()
    while True:
        c = t.tocsr()
        branches, deg = _tree_branches(c), np.diff(c.indptr)
        spurs = [b for b, L in branches if L < spur_mm and (deg[b[0]] == 1) != (deg[b[-1]] == 1)]
        if not spurs:
            return branches
        for b in spurs:  # the leaf branch without its junction node
            inner = b if deg[b[0]] != 1 else b[::-1]
            for u, v in zip(inner[1:], inner[:-1]):
                t[u, v] = t[v, u] = 0


def _tree_branches(t) -> list:
    """``[(nodes, length mm)]``: a forest's paths between nodes that are not of degree 2 (leaves, junctions)."""
    deg = np.diff(t.indptr)
    stop = (deg != 2) & (deg > 0)
    seen_edges: set = set()
    out = []
    for s in np.nonzero(stop)[0].tolist():
        for nb in t.indices[t.indptr[s]:t.indptr[s + 1]].tolist():
            if (s, nb) in seen_edges:
                continue
            path, prev, cur, L = [s], s, nb, float(t[s, nb])
            while True:
                seen_edges.add((prev, cur))
                seen_edges.add((cur, prev))
                path.append(cur)
                if stop[cur]:
                    break
                a, b = t.indices[t.indptr[cur]:t.indptr[cur + 1]].tolist()
                prev, cur = cur, (b if a == prev else a)
                L += float(t[prev, cur])
            out.append((path, L))
    return out


def _trim_spurs(p: np.ndarray, r: np.ndarray, frac: float = TRIM_FRAC, max_mm: float = TRIM_MAX_MM):
    """A piece's path without its end spurs: from each end, the points where the lumen radius is below ``frac``
    of the piece's median, up to ``max_mm`` of path."""
    if len(p) < 3:
        return p, r
    thin = r < frac * np.median(r)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    a = 0
    while a < len(p) - 1 and thin[a] and s[a] < max_mm:
        a += 1
    b = len(p) - 1
    while b > a and thin[b] and s[-1] - s[b] < max_mm:
        b -= 1
    return p[a:b + 1], r[a:b + 1]


def _length_mm(p: np.ndarray) -> float:
    """Length of a polyline (its units)."""
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def _end_tangent(p: np.ndarray, at_end: bool, reach_mm: float = 10.0) -> np.ndarray:
    """Unit direction in which a polyline leaves through one of its ends (over its last ``reach_mm``)."""
    q = p if at_end else p[::-1]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    back = q[np.searchsorted(s, s[-1] - reach_mm, side="right") - 1]
    v = q[-1] - back
    return v / max(float(np.linalg.norm(v)), 1e-9)


def _bridge(a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray, step_mm: float = 1.0) -> np.ndarray:
    """Cubic Hermite points strictly between ``a`` (leaving along ``ta``) and ``b`` (arriving along ``tb``)."""
    gap = float(np.linalg.norm(b - a))
    n = max(int(gap / step_mm), 1)
    u = (np.arange(1, n) / n)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return h00 * a + h10 * gap * ta + h01 * b + h11 * gap * tb


def _chain_pieces(pieces: list, max_gap_mm: float, rounds: int = 3, detail: dict | None = None):
    """One polyline from pieces ``[(points (k, 3) mm, radius (k,) mm)]``: ``(points, radii, pieces used)``.

    :func:`_link` joins them into chains; while more than one chain is left, the chains are linked again as pieces
    with the gap limit doubled (``rounds`` times at most: a piece that no end reaches within ``max_gap_mm`` may
    still belong between two chains). The longest chain's order is then improved (:func:`_improve_order`: the
    greedy matching leaves out-of-order joins that local moves undo, and side branches strung in at a cost) and
    it is the centre line. ``detail``: a dict that receives that order (``order``, ``[(piece, reversed)]``).
    """
    chains = [(p, r, 1, [(i, False)]) for i, (p, r) in enumerate(pieces)]
    limit = max_gap_mm
    for _ in range(rounds):
        chains = _link(chains, limit)
        if len(chains) == 1:
            break
        limit *= 2.0
    best = max(chains, key=lambda c: _length_mm(c[0]))
    if best[2] < len(pieces):
        log.warning("%d of %d skeleton branch(es) not joined to the longest chain (gaps over %.0f mm, or over "
                    "%.0f mm for a branch under %.0f mm): left out", len(pieces) - best[2], len(pieces), limit / 2.0,
                    SHORT_GAP_MM, SHORT_MM)
    order = _improve_order(pieces, best[3])
    if detail is not None:
        detail["order"] = list(order)
    if order == best[3]:
        return best[:3]
    if len(order) < len(best[3]):
        log.warning("%d side branch(es) left out of the chain (joining them cost more than %.0fx their length)",
                    len(best[3]) - len(order), DROP_RATIO)
    return (*_build_chain(pieces, order), len(order))


def _build_chain(pieces: list, order: list) -> tuple[np.ndarray, np.ndarray]:
    """``(points, radii)`` of pieces in ``order`` (``[(piece, reversed)]``), joined by :func:`_bridge` curves."""
    pts: list = []
    rad: list = []
    for i, rev in order:
        p, r = pieces[i]
        _append_bridged(pts, rad, *((p[::-1], r[::-1]) if rev else (p, r)))
    return np.vstack(pts), np.concatenate(rad)


def _append_bridged(pts: list, rad: list, p: np.ndarray, r: np.ndarray) -> None:
    """Append a piece's points and radii to the lists of a chain, after a :func:`_bridge` from the chain's end (its
    radius interpolated) where the chain has one."""
    if pts:
        mid = _bridge(pts[-1][-1], _end_tangent(pts[-1], True), p[0], -_end_tangent(p, False))
        pts.append(mid)
        rad.append(np.interp(np.arange(1, len(mid) + 1) / (len(mid) + 1), [0, 1], [rad[-1][-1], r[0]]))
    pts.append(p)
    rad.append(r)


def _gap_costs(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """``(m, m)`` cost of a gap between every two piece ends (``points``, outward unit ``tangents``, ``(m, 3)``):
    its length counted longer the more the two ends would have to turn to meet it, ``d (1 + turn) + TURN_MM
    turn`` with ``turn = (1 - t_a.g) + (1 + t_b.g)``, ``g`` the gap's direction from ``a`` to ``b`` (symmetric);
    ends that coincide take the direction that suits them best, ``(t_a - t_b) / |t_a - t_b|``."""
    gap = points[None, :, :] - points[:, None, :]
    d = np.linalg.norm(gap, axis=2)
    tt = tangents[:, None, :] - tangents[None, :, :]
    g = np.where((d > 1e-6)[..., None], gap / np.maximum(d, 1e-12)[..., None],
                 tt / np.maximum(np.linalg.norm(tt, axis=2), 1e-9)[..., None])
    turn = (1.0 - np.einsum("ak,abk->ab", tangents, g)) + (1.0 + np.einsum("bk,abk->ab", tangents, g))
    return d * (1.0 + turn) + TURN_MM * turn


def _improve_order(pieces: list, order: list, drop_ratio: float | None = None) -> list:
    """A chain's pieces ``[(piece, reversed)]`` re-ordered, and side branches left out, by local moves.

    The objective is the chain's summed gap cost (:func:`_gap_costs`) plus ``drop_ratio`` times the length of every
    piece left out. The greedy matching of :func:`_link` is the travelling-salesman path's greedy heuristic, whose
    usual repair is local search; the moves are 2-opt (reverse a run of pieces), or-opt (move a run of 1-3 pieces
    elsewhere, either way round), leaving a piece out, and putting a left-out piece back in (either way round),
    and the best of them all is taken while it lowers the objective (steepest descent). Leaving out is part of the
    same search, not a pass before or after it: on the greedy order, a real piece joined out of order looks costly;
    on an order repaired without it, a side branch sits at an end, joined cheaply, and the real piece beside it looks
    costly. A side branch strung in across two long, turning gaps goes; a real piece between its neighbours costs
    little more than skipping it and stays. Chosen on the CT gut's development cuts 0-9 (docs/RESULTS.md, session
    31).
    """
    drop_ratio = DROP_RATIO if drop_ratio is None else drop_ratio
    if len(order) < 2:
        return list(order)
    used = sorted({i for i, _ in order})
    slot = {i: j for j, i in enumerate(used)}
    ends_p = np.array([pieces[i][0][k] for i in used for k in (0, -1)])
    ends_t = np.array([_end_tangent(pieces[i][0], bool(k)) for i in used for k in (0, 1)])
    m = len(ends_p)
    C = np.zeros((m + 1, m + 1))  # index m: the free end before the first piece and after the last (costs nothing)
    C[:m, :m] = _gap_costs(ends_p, ends_t)
    price = drop_ratio * np.array([_length_mm(pieces[i][0]) for i in used])
    # the chain as entry and exit end indices of each piece (a reversed piece is entered through its far end)
    ent = [2 * slot[i] + int(r) for i, r in order]
    ext = [2 * slot[i] + 1 - int(r) for i, r in order]
    out: list[int] = []  # slots of the pieces left out
    for _ in range(20 * len(order)):  # a bound: each move lowers the objective, so none repeats
        n = len(ent)
        E, X = np.array(ent), np.array(ext)
        xp = np.r_[m, X[:-1]]  # exit before each piece (the free end before the first)
        en = np.r_[E[1:], m]  # entry after each piece
        join_in, join_out = C[xp, E], C[X, en]
        best = (-1e-6, None)
        # 2-opt: reverse pieces i..j (j > i); the run is entered through j's exit and left through i's entry
        d2 = C[xp[:, None], X[None, :]] + C[E[:, None], en[None, :]] - join_in[:, None] - join_out[None, :]
        d2[np.tril_indices(n)] = np.inf
        k = int(np.argmin(d2))
        if d2.flat[k] < best[0]:
            best = (float(d2.flat[k]), ("2opt", *divmod(k, n)))
        # or-opt: move pieces i..i+L-1 between two others of what is left, as they are or reversed
        for L in (1, 2, 3):
            for i in range(0, n - L + 1):
                if L == n:
                    continue
                saved = join_in[i] + join_out[i + L - 1] - C[xp[i], en[i + L - 1]]
                rE, rX = np.r_[E[:i], E[i + L:]], np.r_[X[:i], X[i + L:]]
                a, b = np.r_[m, rX], np.r_[rE, m]  # the exits and entries either side of each gap of what is left
                for flip in (False, True):
                    e_in, e_out = (X[i + L - 1], E[i]) if flip else (E[i], X[i + L - 1])
                    add = C[a, e_in] + C[e_out, b] - C[a, b]
                    if not flip:
                        add[i] = np.inf  # back where it was
                    g = int(np.argmin(add))
                    if add[g] - saved < best[0]:
                        best = (float(add[g] - saved), ("move", i, L, g, flip))
        # leave a piece out
        dd = C[xp, en] - join_in - join_out + price[E // 2]
        k = int(np.argmin(dd))
        if dd[k] < best[0]:
            best = (float(dd[k]), ("drop", k))
        # put a left-out piece back
        a, b = np.r_[m, X], np.r_[E, m]
        for q in out:
            for flip in (False, True):
                e_in, e_out = (2 * q + 1, 2 * q) if flip else (2 * q, 2 * q + 1)
                add = C[a, e_in] + C[e_out, b] - C[a, b] - price[q]
                g = int(np.argmin(add))
                if add[g] < best[0]:
                    best = (float(add[g]), ("back", q, g, flip))
        move = best[1]
        if move is None:
            break
        if move[0] == "2opt":
            _, i, j = move
            ent[i:j + 1], ext[i:j + 1] = ext[i:j + 1][::-1], ent[i:j + 1][::-1]
        elif move[0] == "move":
            _, i, L, g, flip = move
            re, rx = ent[i:i + L], ext[i:i + L]
            if flip:
                re, rx = rx[::-1], re[::-1]
            del ent[i:i + L], ext[i:i + L]
            ent[g:g], ext[g:g] = re, rx
        elif move[0] == "drop":
            out.append(ent[move[1]] // 2)
            del ent[move[1]], ext[move[1]]
        else:
            _, q, g, flip = move
            out.remove(q)
            ent.insert(g, 2 * q + int(flip))
            ext.insert(g, 2 * q + 1 - int(flip))
    return [(used[e // 2], bool(e % 2)) for e in ent]


def _link(pieces: list, max_gap_mm: float) -> list:
    """Chains ``[(points, radii, pieces in it, order)]`` from ``pieces`` (the same form; ``order`` lists the original
    pieces in it as ``(piece, reversed)``).

    Greedy matching of piece ends, as the greedy heuristic of the travelling-salesman path: every pair of ends of
    different pieces within ``max_gap_mm`` is a candidate gap, costed by :func:`_gap_costs` (its length, counted
    longer the more the two ends would have to turn to meet it); gaps are taken cheapest first when both ends are
    still free and the gap joins two different chains.
    """
    ends = []  # (piece, at_end, point, outward tangent)
    for i, (p, _, _, _) in enumerate(pieces):
        ends.append((i, False, p[0], _end_tangent(p, False)))
        ends.append((i, True, p[-1], _end_tangent(p, True)))
    lens = np.array([_length_mm(p) for p, _, _, _ in pieces])
    pts = np.array([e[2] for e in ends])
    cost = _gap_costs(pts, np.array([e[3] for e in ends]))
    d = np.linalg.norm(pts[None, :, :] - pts[:, None, :], axis=2)
    piece = np.repeat(np.arange(len(pieces)), 2)
    short = np.minimum(lens[piece][:, None], lens[piece][None, :]) < SHORT_MM
    ok = (piece[:, None] != piece[None, :]) & (d <= max_gap_mm) & ~((d > SHORT_GAP_MM) & short)
    a_idx, b_idx = np.nonzero(np.triu(ok, 1))
    cand = list(zip(cost[a_idx, b_idx].tolist(), a_idx.tolist(), b_idx.tolist()))
    parent = list(range(len(pieces)))

    def root(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    link: dict[int, int] = {}  # end -> the end it is joined to
    for _, a, b in sorted(cand):
        if a in link or b in link or root(ends[a][0]) == root(ends[b][0]):
            continue
        link[a], link[b] = b, a
        parent[root(ends[a][0])] = root(ends[b][0])
    # walk each chain from a free end
    chains, seen = [], set()
    for start in range(len(ends)):
        if start in link or ends[start][0] in seen:
            continue
        pts, rad, n_used, e, order = [], [], 0, start, []
        while True:
            i, at_end, _, _ = ends[e]
            seen.add(i)
            p, r, k, sub = pieces[i]
            if at_end:  # entered at this end: run away from it
                p, r, sub = p[::-1], r[::-1], [(j, not rev) for j, rev in sub[::-1]]
            _append_bridged(pts, rad, p, r)
            n_used += k
            order += sub
            other = 2 * i + (0 if at_end else 1)  # the piece's far end
            if other not in link:
                break
            e = link[other]
        chains.append((np.vstack(pts), np.concatenate(rad), n_used, order))
    return chains


def load_reference_csv(path: str | Path, voxel_size_mm=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Reference mid-line points in mm from a CSV with ``x,y,z`` columns (``#`` comment lines skipped)."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    if not lines:
        raise InputError(f"{path}: empty (needs a header with x,y,z columns and one row per point)")
    header = [h.strip() for h in lines[0].split(",")]
    try:
        cols = [header.index(c) for c in ("x", "y", "z")]
    except ValueError:
        raise InputError(f"{path}: needs x,y,z columns, header is {header}") from None
    rows = []
    for i, ln in enumerate(lines[1:], start=2):
        try:
            cells = ln.split(",")
            if len(cells) <= max(cols):
                raise ValueError(f"{len(cells)} field(s), the header has {len(header)}")
            rows.append([float(cells[c]) for c in cols])
        except ValueError as exc:
            raise InputError(f"{path}: malformed row {i} (of the lines that are not comments): {ln!r} ({exc})") \
                from None
    return _reference_mm(path, np.array(rows, dtype=np.float64).reshape(-1, 3), voxel_size_mm)


def load_reference_json(path: str | Path, voxel_size_mm=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Reference mid-line points in mm from a GCA path file (``Paths/*.jsn``: ``{"n": N, "points": [[x, y, z],
    ...], "tangents": ..., "normals": ...}``, the points in the model's grid units); only ``points`` is read."""
    path = Path(path)
    doc = _read_json(path)
    if not isinstance(doc, dict) or "points" not in doc:
        raise InputError(f"{path}: expected a mid-line path object with a 'points' list ([[x, y, z], ...])")
    pts = doc["points"]
    if not isinstance(pts, list):
        raise InputError(f"{path}: 'points' must be a list of [x, y, z] numbers")
    bad = next((i for i, p in enumerate(pts) if not _three_numbers(p)), None)
    if bad is not None:
        raise InputError(f"{path}: 'points' must be a list of [x, y, z] numbers; point {bad} is {pts[bad]!r}")
    if "n" in doc and doc["n"] != len(pts):
        raise InputError(f"{path}: says n = {doc['n']} but holds {len(pts)} points (truncated?)")
    return _reference_mm(path, np.array(pts, dtype=np.float64).reshape(-1, 3), voxel_size_mm)


def load_reference(path: str | Path, voxel_size_mm=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A reference mid-line in mm: a GCA path file (``.jsn`` / ``.json``, :func:`load_reference_json`) or a CSV
    with ``x,y,z`` columns (:func:`load_reference_csv`)."""
    if Path(path).suffix.lower() in (".jsn", ".json"):
        return load_reference_json(path, voxel_size_mm)
    return load_reference_csv(path, voxel_size_mm)


def _three_numbers(v) -> bool:
    """A JSON ``[x, y, z]`` of numbers (not booleans, which JSON parsing turns into ints)."""
    return isinstance(v, list) and len(v) == 3 and all(isinstance(c, (int, float)) and not isinstance(c, bool)
                                                       for c in v)


def _read_json(path: Path):
    import json

    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None


def _reference_mm(path: Path, pts: np.ndarray, voxel_size_mm) -> np.ndarray:
    if len(pts) < 2:
        raise InputError(f"{path}: a mid-line needs at least 2 points, found {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise InputError(f"{path}: point {int(np.nonzero(~np.isfinite(pts).all(axis=1))[0][0])} is not finite")
    return pts * np.asarray(voxel_size_mm, dtype=np.float64)


def voxel_size_from_config(path: str | Path) -> tuple[float, float, float]:
    """The mm per mesh unit of a GCA model, from its config file (``EdinGCA_3D_*.json``: the ``voxel_size`` of its
    ``MODEL_PROP`` entry in ``model_objects``, or a top-level ``voxel_size``)."""
    path = Path(path)
    doc = _read_json(path)
    doc = doc if isinstance(doc, dict) else {}
    objs = doc.get("model_objects")
    found = [o["voxel_size"] for o in (objs if isinstance(objs, list) else [])
             if isinstance(o, dict) and "voxel_size" in o] + ([doc["voxel_size"]] if "voxel_size" in doc else [])
    if not found:
        raise InputError(f"{path}: no voxel_size (a GCA model config has one in its MODEL_PROP model object); "
                         "give --voxel-size X Y Z instead")
    vs = found[0]
    if not (_three_numbers(vs) and all(v > 0 for v in vs)):
        raise InputError(f"{path}: voxel_size must be three positive numbers (mm), found {vs!r}")
    if any(f != vs for f in found[1:]):
        raise InputError(f"{path}: holds different voxel sizes {found}; give --voxel-size X Y Z instead")
    return float(vs[0]), float(vs[1]), float(vs[2])


def score_centerline(ours_mm: np.ndarray, ref_mm: np.ndarray, tol_mm: float = 5.0) -> dict[str, float]:
    """Distances from each reference point to our centre line (densified to 0.25 mm), in mm.

    ``coverage`` is the fraction of reference points within ``tol_mm`` of our line; ``precision`` the fraction of
    our points within ``tol_mm`` of the reference (a spurious branch lowers it).
    """
    seg = np.diff(ours_mm, axis=0)
    steps = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / 0.25).astype(int))
    dense = np.concatenate([ours_mm[i] + np.outer(np.arange(k) / k, seg[i]) for i, k in enumerate(steps)]
                           + [ours_mm[-1:]])
    d, _ = cKDTree(dense).query(ref_mm)
    d_back, _ = cKDTree(ref_mm).query(ours_mm)
    return {
        "mean_mm": float(d.mean()),
        "median_mm": float(np.median(d)),
        "p95_mm": float(np.percentile(d, 95)),
        "max_mm": float(d.max()),
        "coverage": float(np.mean(d <= tol_mm)),
        "precision": float(np.mean(d_back <= tol_mm)),
    }


def _tree_diameter(tree_g):
    """Longest path of a forest's largest tree: ``(length, path nodes, predecessors from path[0], distances)``."""
    _, comp = csgraph.connected_components(tree_g, directed=False)
    start = int(np.nonzero(comp == np.argmax(np.bincount(comp)))[0][0])
    d0 = csgraph.dijkstra(tree_g, indices=start)
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    da, pred = csgraph.dijkstra(tree_g, indices=a, return_predecessors=True)
    b = int(np.argmax(np.where(np.isfinite(da), da, -1)))
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    return float(da[b]), np.array(path[::-1]), pred, da


def _reroute_through_loops(skel_g, tree_g, r_mm, min_gain_mm: float, max_rounds: int = 50) -> np.ndarray:
    """Edge swaps that route the end-to-end path around loops the spanning tree cut (module docstring)."""
    skel = sparse.triu(skel_g, 1).tocoo()
    D, path, pred, da = _tree_diameter(tree_g)
    tree = tree_g.tolil()
    for rnd in range(max_rounds):
        t = tree.tocsr()
        tu, tv = sparse.triu(t, 1).nonzero()
        in_tree = set(zip(tu.tolist(), tv.tolist()))
        n = t.shape[0]
        depth = np.full(n, -1)
        depth[path[0]] = 0
        for x in np.argsort(da):  # parents come before children in distance order
            if np.isfinite(da[x]) and depth[x] < 0 and pred[x] >= 0:
                depth[x] = depth[pred[x]] + 1
        on_path = np.zeros(n, bool)
        on_path[path] = True
        swaps: dict = {}  # cut edge -> (added edge, cycle length): one evaluation per distinct cut
        for u, v, w in zip(skel.row.tolist(), skel.col.tolist(), skel.data.tolist()):
            if (u, v) in in_tree or depth[u] < 0 or depth[v] < 0:
                continue
            x, y, pu, pv = u, v, [u], [v]
            while x != y:  # tree path u..v through their lowest common ancestor
                if depth[x] >= depth[y]:
                    x = int(pred[x])
                    pu.append(x)
                else:
                    y = int(pred[y])
                    pv.append(y)
            cycle_mm = (da[u] - da[x]) + (da[v] - da[x]) + w
            if cycle_mm < min_gain_mm:
                continue
            cyc = pu + pv[-2::-1]
            cut = [(cyc[i], cyc[i + 1]) for i in range(len(cyc) - 1) if on_path[cyc[i]] and on_path[cyc[i + 1]]]
            if not cut:
                continue
            f = min(cut, key=lambda e: r_mm[e[0]] + r_mm[e[1]])
            f = (min(f), max(f))
            if f not in swaps or swaps[f][1] < cycle_mm:
                swaps[f] = ((u, v, w), cycle_mm)
        best = None
        for f, ((u, v, w), _) in swaps.items():
            cand = tree.copy()
            cand[f[0], f[1]] = cand[f[1], f[0]] = 0
            cand[u, v] = cand[v, u] = w
            c = cand.tocsr()
            c.eliminate_zeros()
            res = _tree_diameter(c)
            if res[0] >= D + min_gain_mm and (best is None or res[0] > best[0][0]):
                best = (res, cand)
        if best is None:
            break
        log.info("centre line: loop %d re-routed, path %.0f -> %.0f mm", rnd + 1, D, best[0][0])
        (D, path, pred, da), tree = best
    return path

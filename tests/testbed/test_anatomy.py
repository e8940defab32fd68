"""Centre lines from meshes: a synthetic closed tube with a known centre line, and one-line errors for bad meshes."""

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bodyslam.errors import InputError
from testbed.anatomy import extract_centerline, load_mesh, score_centerline
from testbed.centerline import Centerline
from testbed.tube import Tube


def closed_tube_mesh(cl: Centerline, sections: int = 48):
    """Our tube mesh (mm) with the seam merged and both ends capped: a watertight trimesh."""
    import trimesh

    m = Tube(cl, sections=sections, ring_spacing_m=0.001).mesh()
    v = m.vertices_w * 1000.0
    faces = [m.faces]
    n_ring = sections + 1
    n_rings = len(v) // n_ring
    v = np.vstack([v, cl.points_w[[0, -1]] * 1000.0])
    c0, c1 = len(v) - 2, len(v) - 1
    first = np.arange(sections)
    last = (n_rings - 1) * n_ring + np.arange(sections)
    faces.append(np.c_[np.full(sections, c0), first + 1, first])
    faces.append(np.c_[np.full(sections, c1), last, last + 1])
    mesh = trimesh.Trimesh(v, np.vstack(faces), process=True)  # merges the duplicated seam vertices
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_watertight
    return mesh


def s_curve(radius_m=0.006):
    t = np.linspace(0, 1, 200)
    pts = np.c_[0.03 * np.sin(2 * math.pi * t), 0.02 * (1 - np.cos(2 * math.pi * t)), 0.12 * t]
    return Centerline.from_points(pts, radius_m, ds_m=5e-4)


def test_synthetic_tube_centre_line_is_recovered():
    cl = s_curve()
    got = extract_centerline(closed_tube_mesh(cl), pitch_mm=0.5)
    ref_mm = cl.points_w * 1000.0
    sc = score_centerline(got.points_w * 1000.0, ref_mm[10:-10])  # skeletons stop ~one radius short of a cap
    # 0.5 mm voxels: the skeleton lies within about one voxel of the true axis
    assert sc["mean_mm"] < 0.5, sc
    assert sc["max_mm"] < 1.5, sc
    assert sc["coverage"] == 1.0
    # the local lumen radius comes from the distance transform (6 mm tube; within a voxel)
    assert abs(np.median(got.radius_m) * 1000.0 - 6.0) < 0.6


def test_bad_meshes_get_one_clear_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "missing.obj")
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"\x00\x01 this is not a mesh" * 10)
    with pytest.raises(InputError, match=str(junk.name)):
        load_mesh(junk)
    # bytes that are neither binary STL nor UTF-8 text: trimesh's fallback import of an optional module was the
    # message ("ModuleNotFoundError: No module named 'charset_normalizer'"), as if the toolkit were broken
    noise = tmp_path / "noise.stl"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 2000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="noise.stl: (not a readable mesh|contains no triangles)") as exc:
        load_mesh(noise)
    assert "ModuleNotFoundError" not in str(exc.value)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(InputError, match="no triangles|not a readable mesh"):
        load_mesh(empty)
    import trimesh

    box = trimesh.creation.box((1, 1, 1))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])  # one side removed
    open_path = tmp_path / "open.ply"
    open_box.export(open_path)
    with pytest.raises(InputError, match="not watertight"):
        load_mesh(open_path)
    assert load_mesh(open_path, repair=True).is_watertight  # the documented repair fills the hole
    # an open sheet (a 50 mm square) encloses nothing: capping its rim doubles it into a slab one voxel thick,
    # which must not come back as a "centre line" of 1 mm radius
    sheet = trimesh.creation.box((50, 50, 1))
    with pytest.raises(InputError, match="none enclosing a tube"):
        extract_centerline(trimesh.Trimesh(sheet.vertices, sheet.faces[:2]))


def test_centerline_cli_reports_errors_in_one_line(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\n")
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "centerline", str(bad), "--out", str(tmp_path / "c.csv")],
                       capture_output=True, text=True)
    assert p.returncode == 1
    assert p.stderr.strip().startswith("error:") and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_a_tube_in_open_pieces_with_a_hole_keeps_its_centre_line(tmp_path):
    """The S tube cut through in two places (3 and 8 mm of tube missing: three open pieces) and a 12 mm hole in one
    side of its wall: the open ends and the hole are capped, each piece skeletonised, the pieces chained across
    the gaps. Measured: mean 0.25 mm, max 0.99 mm, coverage 1.0 against the true axis, 188 mm long; the closed
    tube gives 0.25 mm, max 0.85 mm, 188 mm (one 0.5 mm voxel; the axis is 199 mm)."""
    import trimesh

    cl = s_curve()
    mesh = closed_tube_mesh(cl)
    cen = mesh.triangles_center
    s_mm = cl.s_m[cKDTree(cl.points_w * 1000.0).query(cen)[1]] * 1000.0
    drop = (np.abs(s_mm - 60.0) < 1.5) | (np.abs(s_mm - 110.0) < 4.0)
    f0 = int(np.argmin(np.abs(s_mm - 85.0)))
    drop |= (np.linalg.norm(cen - cen[f0], axis=1) < 6.0) & (mesh.face_normals @ mesh.face_normals[f0] > 0.3)
    opened = trimesh.Trimesh(mesh.vertices, mesh.faces[~drop], process=False)
    opened.remove_unreferenced_vertices()
    assert not opened.is_watertight and len(opened.split(only_watertight=False)) == 3
    path = tmp_path / "open_tube.ply"
    opened.export(path)
    with pytest.raises(InputError, match="not watertight"):
        load_mesh(path)  # as a closed mesh it is refused; the centre line takes it
    detail: dict = {}
    got = extract_centerline(path, pitch_mm=0.5, detail=detail)
    sc = score_centerline(got.points_w * 1000.0, cl.points_w[10:-10] * 1000.0)
    # bridged gaps are cubic curves along the piece ends' directions: within a millimetre of a gently bending axis
    assert sc["mean_mm"] < 0.8 and sc["max_mm"] < 3.0 and sc["coverage"] == 1.0, sc
    assert abs(got.length_m - cl.length_m) < 0.015  # skeletons stop ~one radius short of each end cap
    # what the chain was made of (benchmarks/bench_centerline.py --diagnose reads it): every branch it used is one
    # of the pieces, once, and each lies within a few millimetres of the true axis (the tube's radius is 4 mm)
    order, pieces = detail["order"], detail["pieces"]
    assert len(order) >= 3 and len({i for i, _ in order}) == len(order)
    assert all(0 <= i < len(pieces) for i, _ in order)
    axis = cKDTree(cl.points_w * 1000.0)
    assert all(np.median(axis.query(pieces[i][0])[0]) < 1.5 for i, _ in order)


def test_open_piece_skeleton_splits_at_junctions_and_chains_straight_on():
    """Where two loops of an open segmentation touch, one piece's skeleton is an X: the branches are split at the
    junction, a short spur is pruned, and chaining pairs each arm with the one that goes straight on (the turn
    term: at the junction the gaps are all zero long, so length alone cannot choose)."""
    from scipy import sparse

    from testbed.anatomy import SPUR_MM, _chain_pieces, _pruned_branches, _tree_branches

    # four 40 mm arms from the origin (+x, -x, +y, -y), 1 mm nodes; a 5 mm spur off the +x arm at x = 20 mm
    pts, edges = [np.zeros(3)], []
    for d in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        prev = 0
        for k in range(1, 41):
            pts.append(np.asarray(d, float) * k)
            edges.append((prev, len(pts) - 1))
            prev = len(pts) - 1
    prev = 20  # node (20, 0, 0)
    for k in range(1, 6):
        pts.append(np.array([20.0, 0.0, k]))
        edges.append((prev, len(pts) - 1))
        prev = len(pts) - 1
    e = np.asarray(edges)
    n = len(pts)
    t = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    t = (t + t.T).tocsr()
    branches = _tree_branches(t)
    assert sorted(round(L) for _, L in branches) == [5, 20, 20, 40, 40, 40]  # split at both junctions
    assert 5 < SPUR_MM  # the spur is below the pruning length, the arms above it
    # pruned: the spur goes, and the +x arm's two halves join again at the junction it leaves behind
    assert sorted(round(L) for _, L in _pruned_branches(t, SPUR_MM)) == [40, 40, 40, 40]

    pts = np.asarray(pts)
    arms = [(pts[b], np.full(len(b), 5.0)) for b, L in branches if L > 10.0]
    for seed in range(5):  # whatever order the arms come in
        order = np.random.default_rng(seed).permutation(len(arms))
        line, _, used = _chain_pieces([arms[i] for i in order], 80.0)
        # the longest chain runs straight along one axis through the origin, never turning a corner there
        at0 = np.nonzero(np.all(np.abs(line) < 1e-9, axis=1))[0]
        assert len(at0) >= 1
        k = int(at0[0])
        before, after = line[max(k - 5, 0)], line[min(k + 5, len(line) - 1)]
        assert np.allclose(np.cross(before, after), 0.0, atol=1e-6), (before, after)


def _straight_pieces(xs_mm, r_mm=5.0):
    """Pieces along the x axis, each from x0 to x1 (mm), 1 mm nodes."""
    return [(np.c_[np.arange(x0, x1 + 0.5), np.zeros(int(x1 - x0) + 1), np.zeros(int(x1 - x0) + 1)],
             np.full(int(x1 - x0) + 1, r_mm)) for x0, x1 in xs_mm]


def test_chain_order_repaired_by_local_moves():
    """The greedy matching's out-of-order joins are undone: four pieces of one straight tube handed over in a
    scrambled order, one of them backwards, come out in order along the tube (2-opt / or-opt lower the summed gap
    cost; the order given costs three long turning gaps)."""
    from testbed.anatomy import _improve_order

    pieces = _straight_pieces([(0, 40), (45, 85), (90, 130), (135, 175)])
    got = _improve_order(pieces, [(0, False), (2, False), (1, True), (3, False)])
    assert [i for i, _ in got] in ([0, 1, 2, 3], [3, 2, 1, 0])
    assert len({rev for _, rev in got}) == 1  # all run the same way


def test_side_branch_left_out_but_a_real_piece_kept():
    """A branch beside the tube, strung in across two long gaps that turn through 90 degrees each way, is left out
    (joining it costs more than DROP_RATIO times its 30 mm); a piece on the tube between its neighbours, 5 mm
    gaps each side, stays."""
    from testbed.anatomy import _chain_pieces, _improve_order

    tube = _straight_pieces([(0, 40), (45, 85), (90, 130)])
    side = (np.c_[np.full(31, 60.0), np.arange(20.0, 51.0), np.zeros(31)], np.full(31, 5.0))  # x = 60, y 20..50
    pieces = tube + [side]
    order = [(0, False), (3, True), (1, False), (2, False)]  # tube, side branch (entered at y = 50), tube, tube
    got = _improve_order(pieces, order)
    assert sorted(i for i, _ in got) == [0, 1, 2], got
    # the whole chain: the side branch goes, the three real pieces stay, and the line runs along the tube
    line, _, used = _chain_pieces(pieces, 80.0)
    assert used == 3 and np.max(np.abs(line[:, 1])) < 1e-6
    # the middle piece alone, joined across 5 mm gaps straight on, is kept
    assert sorted(i for i, _ in _improve_order(tube, [(0, False), (1, False), (2, False)])) == [0, 1, 2]


def test_segmented_surfaces_in_several_files_give_one_centre_line(tmp_path):
    """A model's segmented surfaces (GCA: one closed surface per region, neighbours meeting at a cut): the S tube
    cut in two at 60 mm, each half capped at the cut and written to its own file, one of them legacy VTK. Taken
    together they give the whole tube's centre line (measured: mean 0.25 mm, max 0.85 mm, 188 mm, as the tube in one
    file); either file alone gives only its half."""
    import trimesh

    from testbed.anatomy import cap_boundaries
    from tests.testbed.test_vtk_legacy import write_vtk

    cl = s_curve()
    mesh = closed_tube_mesh(cl)
    s_mm = cl.s_m[cKDTree(cl.points_w * 1000.0).query(mesh.triangles_center)[1]] * 1000.0
    halves = []
    for keep in (s_mm < 60.0, s_mm >= 60.0):
        half = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
        half.remove_unreferenced_vertices()
        capped, n_loops, _ = cap_boundaries(half)
        assert n_loops == 1 and capped.is_watertight
        halves.append(capped)
    a = write_vtk(tmp_path / "a.vtk", np.asarray(halves[0].vertices), list(halves[0].faces), extras=False)
    b = tmp_path / "b.ply"
    halves[1].export(b)
    got = extract_centerline([a, b], pitch_mm=0.5)
    sc = score_centerline(got.points_w * 1000.0, cl.points_w[10:-10] * 1000.0)
    assert sc["mean_mm"] < 0.5 and sc["max_mm"] < 1.5 and sc["coverage"] == 1.0, sc  # as one tube (first test)
    one = extract_centerline([b], pitch_mm=0.5)
    assert one.length_m < 0.7 * got.length_m  # one region alone: its own stretch only

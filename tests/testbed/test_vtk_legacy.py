"""Legacy VTK surfaces (the GCA gut models' format): every layout read back exactly, faces split as VTK defines
them, and every malformed file refused with its name, the place and what is wrong."""

import subprocess
import sys

import numpy as np
import pytest

from bodyslam.errors import InputError
from testbed.anatomy import load_mesh, load_reference, voxel_size_from_config
from testbed.vtk_legacy import read_polydata


def write_vtk(path, verts, cells, binary=False, offsets=False, point_type="float", extras=True, strips=()):
    """A legacy VTK POLYDATA file written from the format's description (independent of the reader):
    classic cells (count then ids) or the 5.1 OFFSETS / CONNECTIVITY arrays; ASCII or big-endian binary; with
    ``extras`` a FIELD block, a METADATA block and point normals after the geometry, which the reader passes."""
    dt = {"float": ">f4", "double": ">f8"}[point_type]

    def block(a, dtype):
        a = np.asarray(a)
        if binary:
            return a.astype(dtype).tobytes() + b"\n"
        return (" ".join(repr(float(x)) if dtype[1] == "f" else str(int(x)) for x in a.ravel()) + "\n").encode()

    out = [f"# vtk DataFile Version {'5.1' if offsets else '3.0'}\nwritten by a test\n"
           f"{'BINARY' if binary else 'ASCII'}\nDATASET POLYDATA\n".encode()]
    if extras:
        out += [b"FIELD FieldData 1\nTimeValue 1 1 double\n", block([0.5], ">f8")]
    out += [f"POINTS {len(verts)} {point_type}\n".encode(), block(verts, dt)]
    if extras:
        out.append(b"METADATA\nINFORMATION 0\n\n")
    for name, cs in (("POLYGONS", cells), ("TRIANGLE_STRIPS", strips)):
        if not len(cs):
            continue
        if offsets:
            off = np.concatenate([[0], np.cumsum([len(c) for c in cs])])
            out += [f"{name} {len(off)} {off[-1]}\nOFFSETS vtktypeint64\n".encode(), block(off, ">i8"),
                    b"CONNECTIVITY vtktypeint64\n", block(np.concatenate(cs), ">i8")]
        else:
            flat = np.concatenate([[len(c), *c] for c in cs])
            out += [f"{name} {len(cs)} {len(flat)}\n".encode(), block(flat, ">i4")]
    if extras:
        out += [f"POINT_DATA {len(verts)}\nNORMALS Normals float\n".encode(), block(np.ones((len(verts), 3)), ">f4")]
    path.write_bytes(b"".join(out))
    return path


def sphere():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("offsets", [False, True])
@pytest.mark.parametrize("point_type", ["float", "double"])
def test_every_layout_reads_back_the_same_surface(tmp_path, binary, offsets, point_type):
    v, f = sphere()
    path = write_vtk(tmp_path / "s.vtk", v, list(f), binary=binary, offsets=offsets, point_type=point_type)
    got_v, got_f = read_polydata(path)
    # float32 points: the file's own rounding (ASCII repr of float64 reads back exactly)
    tol = 1e-5 if (point_type == "float" and binary) else 0.0
    np.testing.assert_allclose(got_v, v, rtol=tol, atol=0)
    np.testing.assert_array_equal(got_f, f)


def test_polygons_become_fans_and_strips_keep_their_winding(tmp_path):
    import trimesh

    # a unit cube as six outward-wound quads (counter-clockwise seen from outside)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    got_v, got_f = read_polydata(write_vtk(tmp_path / "cube.vtk", v, quads))
    assert got_f.shape == (12, 3)
    cube = trimesh.Trimesh(got_v, got_f, process=True)
    assert cube.is_watertight and cube.is_winding_consistent
    assert cube.volume == pytest.approx(1.0)  # positive: every fan kept its quad's outward winding
    # a pentagon: three triangles from its first point
    _, f5 = read_polydata(write_vtk(tmp_path / "pent.vtk", np.random.default_rng(0).random((5, 3)),
                                    [[0, 1, 2, 3, 4]], extras=False))
    np.testing.assert_array_equal(f5, [[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    # a strip over a flat zig-zag of 5 points: 3 triangles, all facing +z like the first
    zz = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [2, 0, 0]], float)
    _, fs = read_polydata(write_vtk(tmp_path / "strip.vtk", zz, [], strips=[[0, 1, 2, 3, 4]]))
    normals = np.cross(zz[fs[:, 1]] - zz[fs[:, 0]], zz[fs[:, 2]] - zz[fs[:, 0]])
    assert len(fs) == 3 and np.all(np.sign(normals[:, 2]) == np.sign(normals[0, 2])) and normals[0, 2] != 0


def test_a_vtk_mesh_loads_as_its_obj_does(tmp_path):
    import trimesh

    v, f = sphere()
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "s.obj")
    a = load_mesh(write_vtk(tmp_path / "s.vtk", v, list(f), binary=True, point_type="double"))
    b = load_mesh(tmp_path / "s.obj")
    assert a.is_watertight
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6)  # OBJ text keeps ~8 digits
    np.testing.assert_array_equal(a.faces, b.faces)


def _bad(tmp_path, text: bytes, name="bad.vtk"):
    p = tmp_path / name
    p.write_bytes(text)
    return p


HEAD = b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\n"


@pytest.mark.parametrize("body, match", [
    (b"solid x\nfacet normal 0 0 1\n", "not a legacy VTK file"),
    (b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET UNSTRUCTURED_GRID\n", "UNSTRUCTURED_GRID is not a surface"),
    (HEAD + b"POINTS 3 float\n0 0 0 1 0 0\nPOLYGONS 1 4\n3 0 1 2\n", r"line 5: POINTS: 9 values expected, 6 follow"),
    (HEAD + b"POINTS 3 float\n0 0 0 1 0 0 0 1 x\nPOLYGONS 1 4\n3 0 1 2\n", "line 5: POINTS: 'x' is not a number"),
    (HEAD + b"POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 1 4\n3 0 1 7\n", "names point 7, the file has 3 points"),
    (HEAD + b"POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 2 5\n3 0 1 2 4\n", r"line 7: POLYGONS: cell 1 has 4 points"),
    (HEAD + b"POINTS 3 float\n0 0 0 1 0 0 0 1 0\nLINES 1 3\n2 0 1\n", "no POLYGONS or TRIANGLE_STRIPS"),
    (HEAD + b"POINTS 3 complex\n0 0 0 1 0 0 0 1 0\n", "unknown data type 'complex'"),
    (HEAD + b"POLYGONS 1 4\n3 0 1 2\n", "no POINTS section"),
    (HEAD + b"VOXELS 3\n", "unexpected 'VOXELS'"),
    (b"# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS 3 float\n" + b"\x00" * 20,
     r"byte 53: POINTS: 9 float values need 36 bytes, the file ends after 20"),
])
def test_a_malformed_file_is_refused_with_where_and_what(tmp_path, body, match):
    p = _bad(tmp_path, body)
    with pytest.raises(InputError, match=match) as e:
        read_polydata(p)
    assert str(p) in str(e.value)


def test_missing_vtk_is_named(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "nope.vtk")


def test_gca_reference_paths_and_model_config(tmp_path):
    (tmp_path / "p.jsn").write_text('{"n": 3, "points": [[1, 2, 3], [2, 2, 3], [3, 2, 3.5]], "tangents": []}')
    got = load_reference(tmp_path / "p.jsn", (0.5, 0.5, 2.0))
    np.testing.assert_allclose(got, [[0.5, 1, 6], [1, 1, 6], [1.5, 1, 7]])
    (tmp_path / "p.csv").write_text("# a comment\nindex,x,y,z\n0,1,2,3\n1,2,2,3\n2,3,2,3.5\n")
    np.testing.assert_allclose(load_reference(tmp_path / "p.csv", (0.5, 0.5, 2.0)), got)
    for text, match in [('{"n": 4, "points": [[1, 2, 3], [2, 2, 3]]}', "says n = 4 but holds 2"),
                        ('{"points": [[1, 2, 3], [2, "a", 3]]}', "point 1 is"),
                        ('{"points": [[1, 2, 3]]}', "at least 2 points"),
                        ('[1, 2', "not JSON")]:
        (tmp_path / "b.jsn").write_text(text)
        with pytest.raises(InputError, match=match):
            load_reference(tmp_path / "b.jsn")
    (tmp_path / "b.csv").write_text("x,y,z\n1,2,3\n1,2\n")
    with pytest.raises(InputError, match=r"malformed row 3 .* \(2 field\(s\), the header has 3\)"):
        load_reference(tmp_path / "b.csv")
    # the GCA config keeps the voxel size in its MODEL_PROP model object
    (tmp_path / "m.json").write_text('{"model_objects": [{"group": "DISC"}, {"group": "MODEL_PROP", '
                                     '"voxel_size": [0.832031, 0.832031, 1.0]}]}')
    assert voxel_size_from_config(tmp_path / "m.json") == (0.832031, 0.832031, 1.0)
    for text, match in [('{"model_objects": []}', "no voxel_size"),
                        ('{"voxel_size": [1, 0, 1]}', "three positive numbers"),
                        ('{"voxel_size": [1, 1, 1], "model_objects": [{"voxel_size": [2, 2, 2]}]}', "different")]:
        (tmp_path / "m.json").write_text(text)
        with pytest.raises(InputError, match=match):
            voxel_size_from_config(tmp_path / "m.json")


def test_centerline_cli_checks_the_reference_and_units_before_extracting(tmp_path):
    v, f = sphere()
    mesh = write_vtk(tmp_path / "s.vtk", v, list(f))
    (tmp_path / "ref.jsn").write_text('{"points": [[1, 2, 3]]}')
    cmd = [sys.executable, "-m", "testbed.cli", "centerline", str(mesh), "--out", str(tmp_path / "c.csv")]
    p = subprocess.run(cmd + ["--reference", str(tmp_path / "ref.jsn")], capture_output=True, text=True)
    assert p.returncode == 1 and "at least 2 points" in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert not (tmp_path / "c.csv").exists()  # refused before any extraction
    (tmp_path / "m.json").write_text('{"voxel_size": [1, 1, 1]}')
    p = subprocess.run(cmd + ["--voxel-size", "1", "1", "1", "--model-config", str(tmp_path / "m.json")],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "not allowed with" in p.stderr  # one source of units, not two

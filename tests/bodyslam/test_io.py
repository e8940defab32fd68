import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.errors import InputError
from bodyslam.io import atomic_path, read_image, read_tum, write_image, write_tum


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(5) * 0.5
    p = rng.normal(size=(5, 3)) * 0.1
    R = Rotation.random(5, random_state=1)
    write_tum(tmp_path / "a.tum", t, p, R)
    t2, p2, R2 = read_tum(tmp_path / "a.tum")
    np.testing.assert_allclose(t2, t)
    np.testing.assert_allclose(p2, p, atol=1e-9)  # written with 9 decimals
    assert np.max((R2.inv() * R).magnitude()) < 1e-8
    # order in the file is qx qy qz qw (scalar last)
    line = (tmp_path / "a.tum").read_text().splitlines()[1].split()
    np.testing.assert_allclose([float(x) for x in line[4:]], R[0].as_quat(canonical=True), atol=1e-9)


@pytest.mark.parametrize(
    "text, match",
    [("0 1 2 3 0 0 0 1 9\n", "a.tum:1: expected 8 values"), ("# c\n0 1 2 x 0 0 0 1\n", "a.tum:2: not a number"),
     ("0 1 2 3 0 0 0 2\n", "not of unit length"), ("# only a comment\n", "no poses")],
)
def test_tum_errors_name_the_line(tmp_path, text, match):
    (tmp_path / "a.tum").write_text(text)
    with pytest.raises(InputError, match=match):
        read_tum(tmp_path / "a.tum")


def test_image_round_trip_and_bad_files(tmp_path):
    img = np.random.default_rng(0).integers(0, 255, (20, 30, 3), dtype=np.uint8)
    write_image(tmp_path / "x.png", img)
    np.testing.assert_array_equal(read_image(tmp_path / "x.png"), img)  # RGB in, RGB out (BGR only on disk)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="empty file"):
        read_image(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(InputError, match="not a decodable image"):
        read_image(tmp_path / "junk.png")
    with pytest.raises(InputError, match="file not found"):
        read_image(tmp_path / "missing.png")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_csv_rows_and_tables_number_the_lines_of_the_file(tmp_path):
    # csv.DictReader skips blank lines: counting the rows it gives put every later line number one short
    from bodyslam.io import csv_rows, csv_table

    p = tmp_path / "x.csv"
    p.write_text('a,b\n1,2\n\n3,4\n"five\nlines",6\n7,8\n')
    with csv_rows(p, ("a", "b")) as rows:
        assert [(k, r["a"]) for k, r in rows] == [(2, "1"), (4, "3"), (6, "five\nlines"), (7, "7")]
    with csv_table(p, ("a",)) as (header, rows):
        assert header == ["a", "b"]
        assert [(k, r) for k, r in rows if r] == [(2, ["1", "2"]), (4, ["3", "4"]), (6, ["five\nlines", "6"]),
                                                 (7, ["7", "8"])]


@pytest.mark.parametrize("text, match", [
    ("", r"x\.csv: empty file: no header line \(it needs the column\(s\) a, b\)"),
    ("\n\n", r"x\.csv: empty file: no header line"),
    ("a,c\n1,2\n", r"x\.csv: missing column\(s\) b; header is \['a', 'c'\]"),
])
def test_a_csv_without_its_columns_is_named_with_what_it_lacks(tmp_path, text, match):
    # an empty file has no header line: said so, not as "header is None" (session 73's check of bad input)
    from bodyslam.io import csv_rows, csv_table

    p = tmp_path / "x.csv"
    p.write_text(text)
    for opener in (csv_rows, csv_table):
        with pytest.raises(InputError, match=match):
            with opener(p, ("a", "b")):
                pass


def test_motion_csv_keeps_a_fit_beside_the_wall_and_reads_files_without_the_column(tmp_path):
    """``beside_wall`` (StepMotion.beside_wall, odometry.BESIDE_WALL_RADII) goes through motion.csv as 0 / 1; a file
    written before the column existed, or by another tool, reads as not beside the wall; any other cell is refused
    with its file and line."""
    from dataclasses import replace

    from bodyslam.io import MOTION_COLUMNS, read_motion_steps, write_motion_csv
    from bodyslam.steps import motion_from_transform

    s = motion_from_transform(Rotation.from_rotvec([0.0, 0.0, 0.1]), [0.0, 0.0, 0.002], 40, 1e-3, 0.01)
    write_motion_csv(tmp_path / "m.csv", [1, 2], [0.5, 1.0], [replace(s, beside_wall=True), s])
    rows = [ln.split(",") for ln in (tmp_path / "m.csv").read_text().splitlines()]
    i = MOTION_COLUMNS.index("beside_wall")
    assert rows[0][i] == "beside_wall" and rows[1][i] == "1" and rows[2][i] == "0"
    a, b = read_motion_steps(tmp_path / "m.csv", [1, 2])
    assert a.beside_wall and not b.beside_wall and a.distance_m == pytest.approx(0.002)

    old = [",".join(r[:i]) for r in rows]  # the columns before session 37
    (tmp_path / "old.csv").write_text("\n".join(old) + "\n")
    assert [x.beside_wall for x in read_motion_steps(tmp_path / "old.csv", [1, 2])] == [False, False]

    rows[1][i] = "yes"
    (tmp_path / "bad.csv").write_text("\n".join(",".join(r) for r in rows[:2]) + "\n")
    with pytest.raises(InputError, match=r"bad\.csv:2: beside_wall 'yes' is not 0 or 1"):
        read_motion_steps(tmp_path / "bad.csv", [1])


def test_motion_csv_keeps_a_steps_ring_ratio(tmp_path):
    """``ring_ratio`` (StepMotion.ring_ratio, bodyslam.vision.lumen_scale) goes through motion.csv; a step without
    one, or a file without the column, reads as NaN; a cell that is not a positive number is refused with its file
    and line."""
    from dataclasses import replace

    from bodyslam.io import MOTION_COLUMNS, read_motion_steps, write_motion_csv
    from bodyslam.steps import motion_from_transform

    s = motion_from_transform(Rotation.from_rotvec([0.0, 0.0, 0.1]), [0.0, 0.0, 0.002], 40, 1e-3, 0.01)
    write_motion_csv(tmp_path / "m.csv", [1, 2], [0.5, 1.0], [replace(s, ring_ratio=0.875), s])
    a, b = read_motion_steps(tmp_path / "m.csv", [1, 2])
    assert a.ring_ratio == pytest.approx(0.875) and math.isnan(b.ring_ratio)
    rows = [ln.split(",") for ln in (tmp_path / "m.csv").read_text().splitlines()]
    i = MOTION_COLUMNS.index("ring_ratio")
    (tmp_path / "old.csv").write_text("\n".join(",".join(r[:i]) for r in rows) + "\n")
    assert all(math.isnan(x.ring_ratio) for x in read_motion_steps(tmp_path / "old.csv", [1, 2]))
    for cell in ("abc", "-0.5", "0"):
        rows[1][i] = cell
        (tmp_path / "bad.csv").write_text("\n".join(",".join(r) for r in rows[:2]) + "\n")
        with pytest.raises(InputError, match=rf"bad\.csv:2: ring_ratio '{cell}' is not a"):
            read_motion_steps(tmp_path / "bad.csv", [1])


def test_motion_csv_keeps_a_steps_scale_link_and_chain_factor(tmp_path):
    """``scale_link``, ``scale_link_sd`` and ``chain_factor`` (bodyslam.vision.scale_chain) go through motion.csv;
    a step without them, or a file without the columns, reads as NaN; a link that is not a finite number, or a
    1-sigma or factor that is not a positive one, is refused with its file and line."""
    from dataclasses import replace

    from bodyslam.io import MOTION_COLUMNS, read_motion_steps, write_motion_csv
    from bodyslam.steps import motion_from_transform

    s = motion_from_transform(Rotation.from_rotvec([0.0, 0.0, 0.1]), [0.0, 0.0, 0.002], 40, 1e-3, 0.01)
    write_motion_csv(tmp_path / "m.csv", [1, 2], [0.5, 1.0],
                     [replace(s, scale_link=-0.125, scale_link_sd=0.11, chain_factor=0.96), s])
    a, b = read_motion_steps(tmp_path / "m.csv", [1, 2])
    assert (a.scale_link, a.scale_link_sd, a.chain_factor) == (pytest.approx(-0.125), pytest.approx(0.11),
                                                               pytest.approx(0.96))
    assert all(math.isnan(v) for v in (b.scale_link, b.scale_link_sd, b.chain_factor))
    rows = [ln.split(",") for ln in (tmp_path / "m.csv").read_text().splitlines()]
    i = MOTION_COLUMNS.index("scale_link")
    (tmp_path / "old.csv").write_text("\n".join(",".join(r[:i]) for r in rows) + "\n")
    assert all(math.isnan(x.chain_factor) for x in read_motion_steps(tmp_path / "old.csv", [1, 2]))
    for col, cell, what in (("scale_link", "abc", "not a number"), ("scale_link", "inf", "not a finite number"),
                            ("scale_link_sd", "-0.1", "not a positive number"),
                            ("chain_factor", "0", "not a positive number")):
        bad = [list(r) for r in rows]
        bad[1][MOTION_COLUMNS.index(col)] = cell
        (tmp_path / "bad.csv").write_text("\n".join(",".join(r) for r in bad[:2]) + "\n")
        with pytest.raises(InputError, match=rf"bad\.csv:2: {col} '{cell}' is {what}"):
            read_motion_steps(tmp_path / "bad.csv", [1])


@pytest.mark.parametrize("row, match", [("2,1.0", None), ("2,1.0,XX,fast,0.1", "label must be FT or FL"),
                                        ("two,1.0,FT,fast,0.1", "frame must be a whole number"),
                                        ("0,1.0,FL,fast,0.1", "frame 0 listed twice")])
def test_labels_csv_names_what_a_model_would_learn_wrong(tmp_path, row, match):
    # train-classifier split the lines by hand: a short row was an IndexError traceback, any label was learnt
    from bodyslam.io import read_labels

    p = tmp_path / "labels.csv"
    p.write_text(f"frame,t,label,phase,s_m\n0,0,FT,fast,0.1\n1,0.5,,fast,0.1\n{row}\n")
    if match is None:  # a short row has no label: left out, as an empty one
        assert read_labels(p) == {0: "FT"}
        return
    with pytest.raises(InputError, match=rf"labels\.csv:4: {match}"):
        read_labels(p)

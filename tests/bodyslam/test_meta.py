"""meta.json read, validated and written in one place: what ``check`` accepts the pipeline runs, what it
refuses is refused with one line naming the field and the value."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bodyslam.errors import InputError
from bodyslam.meta import meta_from_dict, read_meta

DEMO = Path(__file__).resolve().parents[2] / "data_samples" / "demo_seed0"


def run(*args):
    return subprocess.run([sys.executable, "-m", "bodyslam.cli", *args], capture_output=True, text=True)


def _seq(tmp_path: Path, n: int = 4, **changes) -> Path:
    d = tmp_path / "seq"
    (d / "frames").mkdir(parents=True)
    for k in range(n):
        shutil.copy(DEMO / "frames" / f"{k:06d}.png", d / "frames" / f"{k:06d}.png")
    meta = json.loads((DEMO / "meta.json").read_text())
    meta["n_frames"] = n
    meta.pop("rf", None)
    for k, v in changes.items():
        if v is ...:
            meta.pop(k, None)
        else:
            meta[k] = v
    (d / "meta.json").write_text(json.dumps(meta))
    return d


@pytest.mark.parametrize("field,value", [("frame_rate_hz", "two"), ("frame_rate_hz", None), ("frame_rate_hz", -2),
                                         ("tube_radius_m", -0.01), ("tube_radius_m", "wide"), ("tube_radius_m", 1.25),
                                         ("tube_radius_sd_m", -0.001),
                                         ("tube_radius_sd_m", 0.5), ("lumen_shape_sd_rel", -0.1),
                                         ("lumen_shape_sd_rel", 1.5), ("lumen_shape_sd_rel", "folded"),
                                         ("n_frames", "forty"),
                                         ("n_frames", 0), ("camera", {"model": "equidistant", "width": 320}),
                                         ("frames", {"dir": 7}), ("rf", {"pathloss": {"pt_dbm": "loud"}})])
def test_check_and_every_reader_refuse_the_same_bad_field(tmp_path, field, value):
    d = _seq(tmp_path, **{field: value})
    for cmd in (["check", str(d)], ["motion", str(d), "--out", str(tmp_path / "m.csv")],
                ["track", str(d), "--out", str(tmp_path / "t.tum")],
                ["batch", str(d), "--out", str(tmp_path / "b")], ["classify", str(d), "--out", str(tmp_path / "c.csv")]):
        p = run(*cmd)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 1 and len(lines) == 1 and "Traceback" not in p.stderr, (cmd, p.stderr)
        assert "meta.json" in lines[0] and field.split(".")[0] in lines[0], (cmd, lines[0])
    assert not (tmp_path / "m.csv").exists() and not (tmp_path / "b").exists()


def test_what_check_accepts_the_pipeline_runs(tmp_path):
    """Forms a reader must take: a whole number written as 4.0, no ``frames`` table, no tube radius with
    ``--radius-m`` given."""
    d = _seq(tmp_path, n_frames=4.0, frames=..., tube_radius_m=...)
    assert run("check", str(d)).returncode == 0
    assert read_meta(d).n_frames == 4
    p = run("motion", str(d), "--out", str(tmp_path / "m.csv"), "--radius-m", "0.0138", "--jobs", "1")
    assert p.returncode == 0, p.stderr
    p = run("motion", str(d), "--out", str(tmp_path / "m2.csv"))  # no radius anywhere: one line
    assert p.returncode == 1 and "tube_radius_m" in p.stderr and "--radius-m" in p.stderr


def test_messages_name_the_field_and_value():
    good = json.loads((DEMO / "meta.json").read_text())
    with pytest.raises(InputError, match=r"n_frames must be a positive whole number, got 'forty'"):
        meta_from_dict({**good, "n_frames": "forty"})
    with pytest.raises(InputError, match=r"frame_rate_hz must be a positive number, got True"):
        meta_from_dict({**good, "frame_rate_hz": True})
    with pytest.raises(InputError, match=r"rf.pathloss: path-loss model: deep must be 3 numbers"):
        meta_from_dict({**good, "rf": {"pathloss": {"deep": [1, 2]}}})
    with pytest.raises(InputError, match=r"malformed rear_camera"):
        meta_from_dict({**good, "rear_camera": {"camera": good["camera"]}})
    m = meta_from_dict(good)
    assert m.rf is not None and m.rf.file == "rf.csv" and m.tube_radius_m == pytest.approx(0.013497, abs=1e-6)


def test_the_lumen_shape_reaches_the_pipeline(tmp_path):
    """``lumen_shape_sd_rel`` (absent: 0, a cylinder) is what the motion and batch readers carry into each step's
    1-sigma; a sequence that states it is not assumed to have the default."""
    from bodyslam.exam.batch import open_exams
    from bodyslam.vision.odometry import Sequence

    assert read_meta(DEMO).lumen_shape_sd_rel == 0.0
    d = _seq(tmp_path, lumen_shape_sd_rel=0.07)
    assert read_meta(d).lumen_shape_sd_rel == 0.07 and Sequence.open(d).shape_sd_rel == 0.07
    (exam,) = open_exams([str(d)])
    assert exam.shape_sd_rel == 0.07 and not any("lumen shape" in a for a in exam.assumed)


def test_a_plain_frame_folder_or_a_file_is_pointed_to_the_command_that_takes_it(tmp_path):
    """A user's frame folder, video or image given to a command that reads sequence directories: the error says
    what the path is and which command takes it, instead of only that meta.json is missing."""
    (tmp_path / "000001.png").write_bytes(b"not decoded here")
    with pytest.raises(InputError, match="plain frame folder.*bodyslam batch"):
        read_meta(tmp_path)
    with pytest.raises(InputError, match="not a sequence directory.*bodyslam batch.*bodyslam classify"):
        read_meta(tmp_path / "000001.png")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="meta.json: file not found$"):
        read_meta(empty)

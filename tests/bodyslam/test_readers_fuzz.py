"""Every reader fuzzed (hypothesis): whatever a file holds, a reader returns or raises the project's one exception
family (:class:`bodyslam.errors.BodySlamError`) with one line that names the file -- never a traceback of another
kind. Inputs start from a valid file of each kind and are damaged the ways files get damaged: bytes cut, inserted
or replaced, a field replaced by junk (text, nan, inf, huge, empty, unicode), lines dropped or duplicated, or
random bytes. Example counts are kept small so the suite stays quick; hypothesis keeps failing examples in its
database and replays them first."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from bodyslam.errors import BodySlamError  # noqa: E402

DEMO = Path(__file__).resolve().parents[2] / "data_samples" / "demo_seed0"
FUZZ = settings(max_examples=int(os.environ.get("BODYSLAM_FUZZ_EXAMPLES", "40")), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                        HealthCheck.too_slow])
JUNK = st.sampled_from(["", "nan", "NaN", "inf", "-inf", "1e999", "-1", "0", "abc", "1,2", '"', "\u00e9\u4e2d",
                        "\x00", " ", "null", "[]", "{}", "true", "9" * 40, "-0.0", "1e-320"])


@st.composite
def damaged(draw, text: str) -> bytes:
    """A valid file's text, damaged."""
    kind = draw(st.sampled_from(["field", "field", "lines", "bytes", "cut", "random"]))
    if kind == "random":
        return draw(st.binary(max_size=400))
    if kind == "cut":
        data = text.encode()
        return data[: draw(st.integers(0, len(data)))]
    if kind == "bytes":
        data = bytearray(text.encode())
        for _ in range(draw(st.integers(1, 6))):
            i = draw(st.integers(0, max(len(data) - 1, 0)))
            data[i:i + draw(st.integers(0, 3))] = draw(st.binary(min_size=0, max_size=4))
        return bytes(data)
    lines = text.splitlines()
    if kind == "lines":
        for _ in range(draw(st.integers(1, 3))):
            i = draw(st.integers(0, max(len(lines) - 1, 0)))
            if lines and draw(st.booleans()):
                del lines[i]
            elif lines:
                lines.insert(i, lines[i])
        return ("\n".join(lines) + "\n").encode()
    # replace fields (comma, space or JSON-value separated) on a few lines with junk
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            break
        i = draw(st.integers(0, len(lines) - 1))
        sep = "," if "," in lines[i] else " "
        cells = lines[i].split(sep)
        j = draw(st.integers(0, len(cells) - 1))
        cells[j] = draw(JUNK)
        lines[i] = sep.join(cells)
    return ("\n".join(lines) + "\n").encode()


def _only_documented_errors(call, path: Path) -> None:
    """``call()`` returns, or raises a BodySlamError whose message is one line naming ``path``'s file."""
    try:
        call()
    except BodySlamError as exc:
        msg = str(exc)
        assert "\n" not in msg.strip(), msg
        assert path.name in msg or str(path.parent) in msg, msg


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """Valid files of each kind, written once."""
    d = tmp_path_factory.mktemp("valid")
    fs = cv2.FileStorage(str(d / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("K", np.array([[150.0, 0, 209.5], [0, 150.0, 209.5], [0, 0, 1]]))
    fs.write("D", np.zeros((4, 1)))
    fs.write("image_width", 420)
    fs.write("image_height", 420)
    fs.release()
    fs = cv2.FileStorage(str(d / "calib.xml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[150.0, 0, 209.5], [0, 150.0, 209.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((1, 4)))
    fs.release()
    (d / "calib.json").write_text(json.dumps(json.loads((DEMO / "meta.json").read_text())["camera"]))
    (d / "manifest.csv").write_text(f"input,name,fps,radius_m,marks\n{DEMO},a,2,0.0125,3;7\n")
    (d / "manifest.json").write_text(json.dumps([{"input": str(DEMO), "name": "b", "fps": 2, "marks": "4"}]))
    (d / "marks.csv").write_text("exam,frame,label\ndemo_seed0,10,polyp\ndemo_seed0,20,\n")
    motion = d / "motion.csv"
    from bodyslam.io import write_motion_csv
    from bodyslam.steps import motion_from_transform
    from scipy.spatial.transform import Rotation

    steps = [motion_from_transform(Rotation.from_rotvec([0, 0, 0.01 * k]), [0, 0, 0.003], 40, 1e-4, 0.002)
             for k in range(6)]
    write_motion_csv(motion, np.arange(1, 7), np.arange(1, 7) / 2.0, steps)
    return d


def _seq_copy(tmp: Path, name: str, data: bytes) -> Path:
    """The demo sequence's small files in ``tmp`` (frames linked by meta.json's dir), one of them replaced."""
    d = tmp / "seq"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    for f in ("meta.json", "rf.csv", "sensors.csv", "groundtruth.tum"):
        shutil.copy(DEMO / f, d / f)
    (d / name).write_bytes(data)
    return d


@FUZZ
@given(data=st.data())
def test_meta_json(tmp_path, data):
    from bodyslam.meta import read_meta

    d = _seq_copy(tmp_path, "meta.json", data.draw(damaged((DEMO / "meta.json").read_text())))
    _only_documented_errors(lambda: read_meta(d), d / "meta.json")


@FUZZ
@given(data=st.data())
def test_rf_and_sensors_csv(tmp_path, data):
    from bodyslam.fusion.localize import RfInput

    for name in ("rf.csv", "sensors.csv"):
        d = _seq_copy(tmp_path, name, data.draw(damaged((DEMO / name).read_text())))
        _only_documented_errors(lambda: RfInput.read(d / "rf.csv", d / "sensors.csv"), d / name)


@FUZZ
@given(data=st.data())
def test_tum(tmp_path, data):
    from bodyslam.io import read_tum

    d = _seq_copy(tmp_path, "groundtruth.tum", data.draw(damaged((DEMO / "groundtruth.tum").read_text())))
    _only_documented_errors(lambda: read_tum(d / "groundtruth.tum"), d / "groundtruth.tum")


@FUZZ
@given(data=st.data())
def test_labels_csv(tmp_path, data):
    from bodyslam.io import read_labels

    p = tmp_path / "labels.csv"
    p.write_bytes(data.draw(damaged((DEMO / "labels.csv").read_text())))
    _only_documented_errors(lambda: read_labels(p), p)


@FUZZ
@given(data=st.data())
def test_motion_csv(tmp_path, data, sample):
    from bodyslam.io import read_motion_steps

    p = tmp_path / "motion.csv"
    p.write_bytes(data.draw(damaged((sample / "motion.csv").read_text())))
    _only_documented_errors(lambda: read_motion_steps(p, range(1, 7)), p)


@FUZZ
@given(data=st.data(), kind=st.sampled_from(["calib.yaml", "calib.xml", "calib.json"]))
def test_calibration_files(tmp_path, data, kind, sample):
    from bodyslam.exam.batch import read_calibration

    p = tmp_path / kind
    p.write_bytes(data.draw(damaged((sample / kind).read_text())))
    _only_documented_errors(lambda: read_calibration(p, 420, 420), p)


@FUZZ
@given(data=st.data(), kind=st.sampled_from(["manifest.csv", "manifest.json"]))
def test_manifests(tmp_path, data, kind, sample):
    """A damaged manifest: a documented error, or its bad rows listed as problems (a study carries on)."""
    from bodyslam.exam.batch import open_exams

    p = tmp_path / kind
    p.write_bytes(data.draw(damaged((sample / kind).read_text())))
    problems: list = []
    _only_documented_errors(lambda: open_exams([str(p)], problems=problems), p)
    assert all(len(row) == 4 for row in problems)


@FUZZ
@given(data=st.data())
def test_marks_csv(tmp_path, data, sample):
    from bodyslam.exam.batch import open_exams, read_marks

    exams = open_exams([str(DEMO)])
    p = tmp_path / "marks.csv"
    p.write_bytes(data.draw(damaged((sample / "marks.csv").read_text())))
    _only_documented_errors(lambda: read_marks(p, exams), p)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A short TOA/DOA + IMU recording (Jeong 2017) and a magnetic-capsule one (Popek 2013), as the testbed writes
    them."""
    import copy

    from testbed import jeong, popek
    from testbed.scenario import load_scenario

    a = tmp_path_factory.mktemp("toa")
    jeong.simulate_hybrid(jeong._set(load_scenario("jeong2017"), "sequence.duration_s", 5.0), 7, a)
    b = tmp_path_factory.mktemp("mag")
    scn = copy.deepcopy(load_scenario("popek"))
    scn["path"].update({"length_m": 0.01, "max_duration_s": 3.0})
    popek.simulate_scenario(scn, 12, b)
    return a, b


@FUZZ
@given(data=st.data(), which=st.sampled_from([("toa", "imu.csv"), ("toa", "rf.csv"), ("toa", "meta.json"),
                                             ("mag", "hall.csv"), ("mag", "actuator.csv"), ("mag", "meta.json")]))
def test_imu_hall_and_actuator_logs(tmp_path, data, which, recordings):
    from bodyslam.systems import magnetic, toa_doa

    src = recordings[0] if which[0] == "toa" else recordings[1]
    d = tmp_path / "rec"
    if d.exists():
        shutil.rmtree(d)
    shutil.copytree(src, d)
    (d / which[1]).write_bytes(data.draw(damaged((src / which[1]).read_text())))
    if which[0] == "toa":  # loaded and run through the paper's scheme, as `bodyslam hybrid-localize` does
        def run():
            r = toa_doa.load_recording(d)
            toa_doa.run_scheme("toa_doa_imu", r["x0"], r["P0"], r["y"], r["snr"], r["imu"], r["arrays"], r["radio"],
                               r["sigma_acc"], r["delta_s"])

        _only_documented_errors(run, d / which[1])
    else:  # and replayed: a slot without its actuator pose is held and listed, a record cut short ends the replay
        _only_documented_errors(lambda: magnetic.replay(magnetic.load_recording(d)), d / which[1])


def test_a_frame_range_longer_than_any_exam_is_refused_at_once():
    """Found by the manifest fuzzing: ``marks = 0-99999999999`` built a list of 10^11 frames (the run hung)."""
    from bodyslam.exam.batch import parse_frame_list

    assert parse_frame_list("1-3;5") == [1, 2, 3, 5]
    for bad in ("0-99999999999", "5-3", "x-2"):
        with pytest.raises(BodySlamError):
            parse_frame_list(bad)

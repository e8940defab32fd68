"""bodyslam batch: outputs, marks, resuming after kill -9, bad files, videos, calibration files, Dask."""

from __future__ import annotations

import csv
import json
import math
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from bodyslam.exam.batch import DEFAULT_SHAPE_SD_REL, BatchSettings, open_exams, read_calibration, run_batch
from bodyslam.frames import list_frames
from bodyslam.vision.odometry import MotionSettings
from bodyslam.cli import main as cli_main
from bodyslam.errors import InputError

DEMO = Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0"
OUTPUTS = ("frames.csv", "motion.csv", "trajectory.tum", "uncertainty.csv", "marks.csv")
FAST = BatchSettings(chunk_frames=8)


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _plain_folder(dst: Path, n: int, start: int = 0) -> Path:
    dst.mkdir(parents=True)
    for k in range(start, start + n):
        shutil.copy(DEMO / "frames" / f"{k:06d}.png", dst / f"capsule_{k:05d}.png")
    return dst


def _same_outputs(a: Path, b: Path) -> None:
    for name in OUTPUTS:
        if (a / name).exists() or (b / name).exists():
            assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_batch_on_a_sequence_directory_writes_every_output(tmp_path):
    exams = open_exams([str(DEMO)], marks=[(10, "polyp"), (30, "")], landmarks=[5])
    stages: list[str] = []
    rep = run_batch(exams, tmp_path / "out", FAST, jobs=1, stage=stages.append)
    # what runs after the chunks is announced (a 55,000-frame exam with RF spends ~40 s there)
    assert [s.split(":")[0] for s in stages] == ["demo_seed0", "demo_seed0"]
    assert "bridging" in stages[0] and "fusing vision with RF over 40 frames" in stages[1]
    d = tmp_path / "out" / "demo_seed0"
    frames = _rows(d / "frames.csv")
    steps = _rows(d / "motion.csv")
    assert len(frames) == 40 and len(steps) == 39  # every frame once, every step once, across chunk seams
    assert [int(r["frame"]) for r in steps] == list(range(1, 40))
    assert [int(r["frame"]) for r in frames] == list(range(40))
    assert sum(r["status"] == "ok" for r in steps) >= 30  # fast mode estimates most demo steps
    marks = _rows(d / "marks.csv")
    assert [m["frame"] for m in marks] == ["10", "30"] and marks[0]["label"] == "polyp"
    # the path from the landmark is the path from the start minus the landmark's own
    m = marks[1]
    k5 = next(r for r in _rows(d / "uncertainty.csv") if r["frame"] == "5")
    assert float(m["path_from_5_m"]) == pytest.approx(float(m["path_from_start_m"]) - float(k5["path_m"]), abs=1e-9)
    # demo truth: the capsule travels ~15 cm in 40 frames; fast mode should be within a few cm of that path
    truth = np.loadtxt(DEMO / "motion_truth.csv", delimiter=",", skiprows=1, usecols=2)
    assert rep.exams[0]["path_travelled_m"] == pytest.approx(np.abs(truth).sum(), rel=0.25)
    assert rep.exams[0]["trajectory"].startswith("fused")  # the sequence's rf.csv + sensors.csv are used
    assert rep.n_problems == 0 and (tmp_path / "out" / "problems.csv").read_text().startswith("exam,file,frame")
    # what a person looks at: the page with the marked frames in its table and its 3-D view, and the plots
    page = (d / "report.html").read_text()
    assert "polyp" in page and 'class="view3d"' in page and 'src="trajectory.png"' in page
    # how the steps were measured is said (the default: fast mode with its full-frame rescue)
    assert rep.exams[0]["vision"].startswith("fast matcher (tracking") and "then on the full frame" in page
    assert (d / "trajectory.png").stat().st_size > 10000 and (d / "path.png").stat().st_size > 10000
    # the k-step check of the per-step 1-sigma is reported (the demo has runs of 3 estimated steps)
    c = rep.exams[0]["step_consistency"]
    assert c["k"] == 3 and c["pairs_estimated"] >= 3 and 0.8 < c["median_distance_ratio_pair_over_singles"] < 1.25
    # where the time went: when each phase ended, in order
    ph = json.loads((tmp_path / "out" / "summary.json").read_text())["phases_end_s"]
    assert list(ph) == ["first_chunk", "chunks", "bridges", "exams"] and list(ph.values()) == sorted(ph.values())


def test_two_landmarks_give_each_mark_its_fraction_of_the_way_by_path_and_by_time(tmp_path, monkeypatch):
    """Two landmarks (the pylorus and the ileocaecal valve, say): each mark's fraction of the path travelled
    from the first to the last, with its 1-sigma, and of the time (the clinical convention) beside it. A landmark
    is at 0 or 1 exactly, with no spread; a mark past the last lies above 1; the fraction is the ratio of the
    paths ``uncertainty.csv`` gives, and the page shows it; path.png and the 3-D view draw both landmarks."""
    import bodyslam.plots

    drawn = []
    path_figure = bodyslam.plots.path_figure
    monkeypatch.setattr(bodyslam.plots, "path_figure", lambda *a, **k: drawn.append(k) or path_figure(*a, **k))
    rep = run_batch(open_exams([str(DEMO)], marks=[(5, ""), (20, "lesion"), (35, ""), (38, "")],
                               landmarks=[35, 5]), tmp_path / "out", FAST, jobs=1)
    assert rep.n_problems == 0
    d = tmp_path / "out" / "demo_seed0"
    marks = {int(m["frame"]): m for m in _rows(d / "marks.csv")}
    path = {int(r["frame"]): float(r["path_m"]) for r in _rows(d / "uncertainty.csv")}
    f = {k: float(m["fraction_5_35"]) for k, m in marks.items()}
    sd = {k: float(m["sd_fraction_5_35"]) for k, m in marks.items()}
    assert f[5] == pytest.approx(0.0, abs=1e-12) and f[35] == pytest.approx(1.0, abs=1e-9)
    assert sd[5] == pytest.approx(0.0, abs=1e-9) and sd[35] == pytest.approx(0.0, abs=1e-6)
    assert f[20] == pytest.approx((path[20] - path[5]) / (path[35] - path[5]), rel=1e-6) and 0 < f[20] < 1
    assert 0 < sd[20] < 0.5 and f[38] > 1
    t = {k: float(m["time_fraction_5_35"]) for k, m in marks.items()}
    assert t == pytest.approx({5: 0.0, 20: 0.5, 35: 1.0, 38: 1.1})  # the demo's frames are evenly spaced
    page = (d / "report.html").read_text()
    assert "from frame 5 to 35: by the path" in page and f"{f[20]:.0%} +- {sd[20]:.0%}" in page
    assert drawn[0]["landmarks"] == [(17.5, "landmark 35"), (2.5, "landmark 5")]  # the demo: 2 frames/s
    assert '"name":"landmark 5"' in page and '"name":"landmark 35"' in page  # in the 3-D view too


def test_chunking_and_workers_do_not_change_results(tmp_path, monkeypatch):
    e = open_exams([str(DEMO)])
    run_batch(e, tmp_path / "a", BatchSettings(chunk_frames=40), jobs=1)
    run_batch(open_exams([str(DEMO)]), tmp_path / "b", BatchSettings(chunk_frames=7), jobs=2)
    # guided chunks, with a floor of 3 frames so the 40-frame demo gets several: 6, 5, 4, 4, 3, 3, ... steps
    monkeypatch.setattr("bodyslam.exam.batch.CHUNK_FRAMES_RANGE", (3, 500))
    run_batch(open_exams([str(DEMO)]), tmp_path / "c", BatchSettings(chunk_workers=2), jobs=2)
    chunks = [json.loads(f.read_text()) for f in sorted((tmp_path / "c" / "demo_seed0" / "chunks").glob("*.json"))]
    sizes = [c["last"] - c["first"] for c in chunks]
    assert len(sizes) >= 6 and sizes[0] > sizes[-2] and sum(sizes) == 39
    # chunk size is part of the plan but not of the results
    _same_outputs(tmp_path / "a" / "demo_seed0", tmp_path / "b" / "demo_seed0")
    _same_outputs(tmp_path / "a" / "demo_seed0", tmp_path / "c" / "demo_seed0")


def test_kill_9_then_same_command_resumes_with_identical_results(tmp_path):
    src = _plain_folder(tmp_path / "exam", 40)
    cmd = [sys.executable, "-m", "bodyslam.cli", "batch", str(src), "--out", str(tmp_path / "run"), "--jobs", "1",
           "--chunk-frames", "4", "--mark", "20", "--radius-m", "0.015"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    chunks = tmp_path / "run" / "exam" / "chunks"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120 and len(list(chunks.glob("chunk_*.json"))) < 3 and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.wait()
    done_before = len(list(chunks.glob("chunk_*.json")))
    assert 3 <= done_before < 10, "the kill must land mid-run for this test to mean anything"
    assert not (tmp_path / "run" / "exam" / "frames.csv").exists()
    p2 = subprocess.run(cmd, capture_output=True, text=True)
    assert p2.returncode == 0, p2.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["chunks_reused"] == done_before and summary["chunks_computed"] == 10 - done_before
    ref = subprocess.run([str(tmp_path / "ref") if c == str(tmp_path / "run") else c for c in cmd],
                         capture_output=True, text=True)
    assert ref.returncode == 0, ref.stderr
    _same_outputs(tmp_path / "run" / "exam", tmp_path / "ref" / "exam")


def test_existing_output_is_not_overwritten_without_force(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    src = _plain_folder(tmp_path / "exam", 6)
    with pytest.raises(InputError, match="not empty and holds no batch run"):
        run_batch(open_exams([str(src)]), out, FAST, jobs=1)
    assert (out / "precious.txt").read_text() == "keep me"
    out2 = tmp_path / "out2"
    run_batch(open_exams([str(src)]), out2, FAST, jobs=1)
    with pytest.raises(InputError, match="other inputs or settings"):
        run_batch(open_exams([str(src)]), out2, BatchSettings(MotionSettings("sift"), chunk_frames=8), jobs=1)
    rep = run_batch(open_exams([str(src)]), out2, BatchSettings(MotionSettings("sift"), chunk_frames=8), jobs=1,
                    force=True)
    assert rep.chunks_computed == 1 and rep.chunks_reused == 0
    # a run made by another version of the toolkit is not resumed: its chunks could differ from this code's
    plan_file = out2 / "batch.json"
    doc = json.loads(plan_file.read_text())
    doc["plan"]["code"] = "0" * 16
    plan_file.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="another version of the toolkit"):
        run_batch(open_exams([str(src)]), out2, BatchSettings(MotionSettings("sift"), chunk_frames=8), jobs=1)


def _write_bad_folder(d: Path) -> dict[str, str]:
    """A frame folder seeded with every kind of bad file; returns file name -> expected reason fragment."""
    _plain_folder(d, 12)
    img = cv2.imread(str(d / "capsule_00003.png"), cv2.IMREAD_COLOR)
    (d / "capsule_00004.png").write_bytes(b"")  # zero bytes
    data = (d / "capsule_00005.png").read_bytes()
    (d / "capsule_00005.png").write_bytes(data[: len(data) // 3])  # truncated
    (d / "capsule_00006.png").write_bytes(b"this is not a PNG at all" * 10)  # corrupt
    cv2.imwrite(str(d / "capsule_00007.png"), cv2.resize(img, (200, 200)))  # odd size
    cv2.imwrite(str(d / "capsule_00008.png"), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))  # grayscale
    cv2.imwrite(str(d / "capsule_00009.png"), img.astype(np.uint16) * 257)  # 16-bit
    ok, jpg = cv2.imencode(".jpg", img)
    (d / "capsule_00010.png").unlink()
    (d / "capsule_00010.jpg").write_bytes(jpg.tobytes()[: len(jpg) // 2])  # truncated JPEG
    (d / "capsule_00011.png").unlink()  # a gap: frame 11 missing (frames go on at 12)
    shutil.copy(DEMO / "frames" / "000012.png", d / "capsule_00012.png")
    (d / "notes.txt").write_text("exam notes")  # not an image
    return {"capsule_00004.png": "empty file", "capsule_00005.png": "not a decodable image",
            "capsule_00006.png": "not a decodable image", "capsule_00007.png": "is not the camera's",
            "capsule_00008.png": "grayscale", "capsule_00009.png": "16-bit", "capsule_00010.jpg": "truncated JPEG",
            "notes.txt": "not an image file", "exam": "numbering gap: frame 11 missing"}


def test_bad_files_are_listed_and_the_run_completes(tmp_path, capsys):
    expected = _write_bad_folder(tmp_path / "exam")
    rc = cli_main(["batch", str(tmp_path / "exam"), "--out", str(tmp_path / "out"), "--jobs", "1",
                   "--chunk-frames", "5", "--calib", str(_calib_json(tmp_path))])
    assert rc == 3  # finished, with problems
    probs = _rows(tmp_path / "out" / "problems.csv")
    for name, reason in expected.items():
        hits = [p for p in probs if Path(p["file"]).name == name and reason in p["reason"]]
        assert hits, f"{name}: no problem mentioning {reason!r} in {probs}"
    frames = {r["file"]: r for r in _rows(tmp_path / "out" / "exam" / "frames.csv")}
    assert frames["capsule_00004.png"]["status"] == "unreadable"
    assert frames["capsule_00007.png"]["status"] == "bad_size"
    assert frames["capsule_00008.png"]["status"] == "ok"  # converted, processed, and reported as a warning
    steps = {int(r["frame"]): r["status"] for r in _rows(tmp_path / "out" / "exam" / "motion.csv")}
    assert steps[4] == steps[5] == "bad_frame" and 12 in steps and 11 not in steps
    assert "problem(s)" in capsys.readouterr().out


def test_a_grayscale_exam_is_one_warning(tmp_path, capsys):
    d = tmp_path / "gray"
    _plain_folder(d, 6)
    for f in d.glob("*.png"):
        cv2.imwrite(str(f), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    assert cli_main(["batch", str(d), "--out", str(tmp_path / "out"), "--jobs", "1", "--chunk-frames", "3",
                     "--calib", str(_calib_json(tmp_path))]) == 3
    probs = _rows(tmp_path / "out" / "problems.csv")
    assert len(probs) == 1 and probs[0]["reason"] == "grayscale frame: read as RGB (6 frames, 0 to 5)", probs
    assert "1 problem(s)" in capsys.readouterr().out


def test_unusable_input_is_one_clear_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert cli_main(["batch", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "no image files found" in err and "Traceback" not in err
    (tmp_path / "clip.mp4").write_bytes(b"\x00" * 1000)
    assert cli_main(["batch", str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "o")]) == 1
    assert "clip.mp4" in capsys.readouterr().err
    # calibration files that are not what they claim, and one whose image size is not the frames': one line each
    _plain_folder(tmp_path / "frames", 4)
    (tmp_path / "junk.yaml").write_bytes(b"garbage \x00\x01 not yaml")
    (tmp_path / "scalar.yaml").write_text("%YAML:1.0\nK: 3\n")
    cam = json.loads(_calib_json(tmp_path).read_text())
    (tmp_path / "small.json").write_text(json.dumps(dict(cam, width=100, height=100, cx=49.5, cy=49.5)))
    for calib, message in (("junk.yaml", "not a readable OpenCV calibration"), ("scalar.yaml", "3x3 matrix"),
                           ("small.json", "the camera (calibration) is 100x100")):
        code = cli_main(["batch", str(tmp_path / "frames"), "--calib", str(tmp_path / calib), "--out",
                         str(tmp_path / f"o_{calib}"), "--fps", "2"])
        err = capsys.readouterr().err
        assert code == 1 and message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        # the parser's own reason, not Python's wrapper of it nor OpenCV's source file
        assert "exception set" not in err and ".cpp" not in err, err


def test_repeated_frames_give_steps_at_rest_and_a_report(tmp_path, capsys):
    # a clip exported at a higher frame rate than it was taken repeats its frames: every step is one at rest, and
    # the per-step 1-sigma check's pairs add up to no length (its distance ratio has nothing to divide by; the
    # report used to stop on it with a TypeError)
    d = tmp_path / "exam"
    d.mkdir()
    for k in range(7):
        shutil.copy(DEMO / "frames" / "000003.png", d / f"capsule_{k:05d}.png")
    rc = cli_main(["batch", str(d), "--out", str(tmp_path / "out"), "--jobs", "1", "--calib",
                   str(_calib_json(tmp_path))])
    out, err = capsys.readouterr()
    assert rc == 0 and "Traceback" not in err, err
    steps = _rows(tmp_path / "out" / "exam" / "motion.csv")
    # at rest to rounding (1e-9 m: the fit's start and solver leave ~1e-15)
    assert len(steps) == 6 and all(r["status"] == "ok" and abs(float(r["distance_m"])) < 1e-9 for r in steps)
    c = json.loads((tmp_path / "out" / "exam" / "summary.json").read_text())["step_consistency"]
    assert c["pairs_estimated"] >= 1 and c["median_distance_ratio_pair_over_singles"] is None
    assert "distance ratio n/a" in (tmp_path / "out" / "exam" / "report.html").read_text()
    # a folder assumes a lumen that is not a cylinder (13% of each step): the check is read with that share too
    assert c["lumen_shape_sd_rel"] == pytest.approx(0.13) and c["stated_within_1sigma"] is not None
    assert "own 1-sigma: " in (tmp_path / "out" / "exam" / "report.html").read_text()  # (its ' escaped)


def test_frames_too_dark_to_classify_are_counted_apart_from_the_wall(tmp_path, capsys):
    # a capsule in the dark (or a blinded sensor) gives frames the classifier never sees: they are FL by rule, and
    # the summary, the printed line and the report say how many of the FL are those
    d = _plain_folder(tmp_path / "exam", 4)
    for k in (4, 5):
        cv2.imwrite(str(d / f"capsule_{k:05d}.png"), np.zeros((320, 320, 3), np.uint8))
    rc = cli_main(["batch", str(d), "--out", str(tmp_path / "out"), "--jobs", "1", "--calib",
                   str(_calib_json(tmp_path))])
    out = capsys.readouterr().out
    assert rc == 0
    c = json.loads((tmp_path / "out" / "exam" / "summary.json").read_text())["classes"]
    assert c["FL_dark_or_saturated"] == 2 and c["FT"] + c["FL"] == 6 and c["FL"] >= 2
    assert "2 of the FL too dark or saturated to classify" in out
    assert "2 of the FL too dark or saturated" in (tmp_path / "out" / "exam" / "report.html").read_text()
    assert [r["status"] for r in _rows(tmp_path / "out" / "exam" / "frames.csv")][4:] == ["dark", "dark"]


def _write_video(path: Path, n: int) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 2.0, (320, 320))
    assert w.isOpened()
    for k in range(n):
        w.write(cv2.imread(str(DEMO / "frames" / f"{k:06d}.png")))
    w.release()


def test_video_chunks_seek_exactly_and_a_broken_tail_is_reported(tmp_path):
    vid = tmp_path / "exam.avi"
    _write_video(vid, 20)
    run_batch(open_exams([str(vid)], radius_m=0.015), tmp_path / "one", BatchSettings(chunk_frames=20), jobs=1)
    run_batch(open_exams([str(vid)], radius_m=0.015), tmp_path / "many", BatchSettings(chunk_frames=6), jobs=1)
    _same_outputs(tmp_path / "one" / "exam", tmp_path / "many" / "exam")
    assert len(_rows(tmp_path / "one" / "exam" / "frames.csv")) == 20
    # cut the file: every frame that still decodes is processed; fewer frames than the container's count is the
    # end of the exam, not a problem (a container's count is an estimate: a WMV saying 19 frames may hold 18)
    data = vid.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rep = run_batch(open_exams([str(cut)], radius_m=0.015), tmp_path / "cut_out", BatchSettings(chunk_frames=6),
                    jobs=1)
    n = rep.exams[0]["frames"]
    assert 5 <= n < 20 and rep.exams[0]["video_ended_at"] == n and rep.exams[0]["frames_expected"] == 20
    assert rep.n_problems == 0 and len(_rows(tmp_path / "cut_out" / "problems.csv")) == 0
    p = subprocess.run([sys.executable, "-m", "bodyslam.cli", "batch", str(cut), "--out", str(tmp_path / "cli"),
                        "--radius-m", "0.015", "--jobs", "1"], capture_output=True, text=True)
    assert p.returncode == 0 and "container said 20" in p.stdout, p.stdout + p.stderr
    # the frames read, not the container's count, in what the run says it is doing (its stage lines, on stderr with
    # the progress); and the field-of-view sample's frames past the end are not each a warning (they were, one line
    # per sampled frame past it)
    assert f"dead reckoning over {n} frames" in p.stderr and "dead reckoning over 20 frames" not in p.stderr, p.stderr
    assert "skipped for field-of-view detection" not in p.stderr, p.stderr


def test_a_webm_or_transport_stream_is_a_video(tmp_path):
    # a user's WebM was "not a frame folder, a video (...) or a manifest"; the name's case does not matter either
    vid = tmp_path / "clip.avi"
    _write_video(vid, 4)
    for name in ("clip.webm", "CLIP.TS"):
        (tmp_path / name).write_bytes(vid.read_bytes())  # FFmpeg probes the content, the name says "a video"
        exam = open_exams([str(tmp_path / name)], radius_m=0.015)[0]
        assert exam.kind == "video" and exam.n_frames == 4


def _calib_json(tmp_path: Path) -> Path:
    meta = json.loads((DEMO / "meta.json").read_text())
    c = meta["camera"]
    p = tmp_path / "calib.json"
    p.write_text(json.dumps({"K": [[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]], "D": c["k"],
                             "width": 320, "height": 320, "fov_deg": c["fov_deg"]}))
    return p


def test_calibration_files_json_and_opencv_yaml(tmp_path):
    cam = read_calibration(_calib_json(tmp_path))
    assert cam["model"] == "opencv_fisheye" and cam["fov_deg"] == pytest.approx(156.0)
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    fs.write("K", K)
    fs.write("D", np.zeros((4, 1)))
    fs.write("image_width", 320)
    fs.write("image_height", 320)
    fs.release()
    cam2 = read_calibration(tmp_path / "calib.yaml")
    # no fov_deg in the file: the largest circle about the principal point (159.5 px) of an equidistant lens
    # with f = 117.53 px is 2 * 159.5 / 117.53 rad = 155.5 deg
    assert cam2["fov_deg"] == pytest.approx(np.degrees(2 * 159.5 / cam["fx"]), abs=0.05)
    (tmp_path / "bad.json").write_text(json.dumps({"K": [1, 2]}))
    with pytest.raises(InputError, match="bad.json"):
        read_calibration(tmp_path / "bad.json")


def test_manifest_lists_exams_with_their_options(tmp_path):
    _plain_folder(tmp_path / "a", 6)
    _plain_folder(tmp_path / "b", 6, start=10)
    (tmp_path / "m.csv").write_text("input,name,fps,radius_m,marks\na,first,4,0.015,2;3\nb,,,,\n")
    exams = open_exams([str(tmp_path / "m.csv")])
    assert [e.name for e in exams] == ["first", "b"]
    assert exams[0].frame_rate_hz == 4.0 and exams[0].marks == [(2, ""), (3, "")]
    assert any("frame rate" in a for a in exams[1].assumed) and any("radius" in a for a in exams[1].assumed)
    assert [i for i, _ in exams[1].frames] == list(range(10, 16))
    # a plain folder says nothing of the lumen: its departure from a cylinder is assumed (the realistic testbed's)
    assert all(e.shape_sd_rel == DEFAULT_SHAPE_SD_REL > 0 and any("lumen shape" in a for a in e.assumed) for e in exams)


def test_list_frames_orders_by_number_and_reports_gaps(tmp_path):
    for name in ("img_10.png", "img_9.png", "img_12.png", "Thumbs.db"):
        (tmp_path / name).write_bytes(b"x")
    frames, probs = list_frames(tmp_path)
    assert frames == [(9, "img_9.png"), (10, "img_10.png"), (12, "img_12.png")]
    assert any("frame 11 missing" in p[3] for p in probs) and any("Thumbs.db" in p[0] for p in probs)


def test_dask_local_cluster_gives_the_same_results(tmp_path):
    distributed = pytest.importorskip("distributed")
    src = _plain_folder(tmp_path / "exam", 16)
    run_batch(open_exams([str(src)], radius_m=0.015), tmp_path / "local", FAST, jobs=1)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        rep = run_batch(open_exams([str(src)], radius_m=0.015), tmp_path / "dask", FAST,
                        scheduler=cluster.scheduler_address)
    assert rep.chunks_computed == 2
    _same_outputs(tmp_path / "local" / "exam", tmp_path / "dask" / "exam")


def test_a_broken_exam_in_a_study_is_listed_and_the_others_finish(tmp_path, capsys):
    _plain_folder(tmp_path / "good", 6)
    (tmp_path / "broken.mp4").write_bytes(b"")  # zero bytes: cannot be opened
    (tmp_path / "m.csv").write_text("input,name\ngood,good\nbroken.mp4,broken\n")
    code = cli_main(["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o"), "--jobs", "1"])
    out = capsys.readouterr().out
    assert code == 3 and "not processed" in out and "broken.mp4" in out
    assert (tmp_path / "o" / "good" / "trajectory.tum").is_file() and not (tmp_path / "o" / "broken").exists()
    problems = (tmp_path / "o" / "problems.csv").read_text().splitlines()
    assert any("broken.mp4" in ln and "error" in ln for ln in problems[1:])
    # a study whose every exam is broken has nothing to do: one line, exit 1
    (tmp_path / "m2.csv").write_text("input\nbroken.mp4\n")
    assert cli_main(["batch", str(tmp_path / "m2.csv"), "--out", str(tmp_path / "o2")]) == 1
    assert "broken.mp4" in capsys.readouterr().err


def test_guided_chunks_shrink_toward_the_end_and_a_resume_keeps_its_chunks(tmp_path):
    """Guided chunks cover the exam once, overlapping by one frame, within 20-500 frames and shrinking toward the
    study's end (an exam followed by others keeps bigger chunks at its own end); the plan (batch.json) records the
    workers they were sized for, and resuming with another --jobs keeps the chunks the run has."""
    from bodyslam.exam.batch import CHUNK_FRAMES_RANGE, guided_chunk_bounds

    for n, w in ((55_000, 2), (10_000, 16), (2000, 16), (600, 2), (40, 2), (21, 4)):
        b = guided_chunk_bounds(n, w)
        assert b[0][0] == 0 and b[-1][1] == n - 1 and all(x[1] == y[0] for x, y in zip(b, b[1:]))
        sizes = [y - x for x, y in b]
        assert all(CHUNK_FRAMES_RANGE[0] <= z <= CHUNK_FRAMES_RANGE[1] for z in sizes[:-1]) or len(b) == 1
        assert sizes[:-1] == sorted(sizes[:-1], reverse=True)  # never bigger than the chunk before
        assert len(b) >= 2 * w or min(sizes[:-1], default=20) <= 2 * CHUNK_FRAMES_RANGE[0]  # workers fed to the end
    # a third of 9,999 steps per worker of 16, then of the rest
    assert [y - x for x, y in guided_chunk_bounds(10_000, 16)][:2] == [208, 203]
    first, last = guided_chunk_bounds(1000, 2, after=100_000)[-1]  # exams follow: no shrinking at this one's end
    assert last - first > 300
    out = tmp_path / "run"
    rep = run_batch(open_exams([str(DEMO)]), out, BatchSettings(), jobs=2)
    plan = json.loads((out / "batch.json").read_text())["plan"]
    assert plan["settings"]["chunk_workers"] == 2 and plan["settings"]["chunk_frames"] is None
    assert rep.chunks_computed == 1  # 39 steps: one chunk (a rest under 20 frames joins it)
    again = run_batch(open_exams([str(DEMO)]), out, BatchSettings(), jobs=1)
    assert again.chunks_reused == 1 and again.chunks_computed == 0
    # equal chunks of a size the guided rule never gives (7) are kept too: the resume follows the run in OUT
    out7 = tmp_path / "run7"
    run_batch(open_exams([str(DEMO)]), out7, BatchSettings(chunk_frames=7), jobs=2)
    resumed = run_batch(open_exams([str(DEMO)]), out7, BatchSettings(), jobs=1)
    assert resumed.chunks_computed == 0 and resumed.chunks_reused == 6
    _same_outputs(out / "demo_seed0", out7 / "demo_seed0")


def test_the_reports_duration_reads_as_a_person_would():
    from bodyslam.exam.batch import duration_text

    assert duration_text(1.5) == "1.5 s"  # a short clip is not "0.0 min"
    assert duration_text(250.0) == "4.2 min"
    assert duration_text(27480.0) == "7 h 38 min"  # a whole exam of 55,000 frames at 2 frames/s
    assert duration_text(float("nan")) == "nan s"


def test_dead_reckoned_steps_without_an_estimate_take_the_path_travelled_length():
    """Without RF, batch dead-reckons causally (a lost step at the steps so far at their 90th percentile) while the
    path travelled fills it from both sides: the trajectory's missing steps are stretched along their direction to
    the path's lengths, so its length is the path travelled and marks' positions agree with their path; estimated
    steps and directions stay as they were."""
    from bodyslam.exam.batch import _with_path_lengths

    rng = np.random.default_rng(3)
    dp = rng.normal(0.0, 0.003, (12, 3))
    pos = np.vstack([np.zeros(3), np.cumsum(dp, axis=0)]) + [0.1, 0.2, 0.3]
    length = np.linalg.norm(dp, axis=1)
    length[[4, 5, 9]] = np.nan  # steps without an estimate
    path = np.r_[0.0, np.cumsum(np.where(np.isfinite(length), length, [0.011] * 12))]
    out = _with_path_lengths(pos, path, length)
    step = np.diff(out, axis=0)
    assert np.linalg.norm(step, axis=1) == pytest.approx(np.diff(path), rel=1e-12)
    assert out[0] == pytest.approx(pos[0])
    ok = np.isfinite(length)
    assert step[ok] == pytest.approx(dp[ok], abs=1e-15)
    unit = lambda v: v / np.linalg.norm(v, axis=1, keepdims=True)  # noqa: E731
    assert unit(step[~ok]) == pytest.approx(unit(dp[~ok]))
    assert len(_with_path_lengths(pos[:1], path[:1], length[:0])) == 1  # a one-frame exam: nothing to stretch


def test_checks_in_background_run_in_order_and_raise_where_waited():
    """The k-step checks run on a thread while the coordinator finalizes: each is waited for by index, in order of
    the calls, and an error in one is raised to the waiter of that one (not lost on the thread, not raised for the
    others)."""
    import time as _time

    from bodyslam.exam.batch import _in_background

    seen = []

    def slow(tag):
        _time.sleep(0.05)
        seen.append(tag)

    def broken():
        raise ValueError("check 1 failed")

    for thread in (True, False):
        seen.clear()
        wait = _in_background([lambda: slow("a"), broken, lambda: slow("c")], thread=thread)
        wait(0)
        assert seen[:1] == ["a"]
        with pytest.raises(ValueError, match="check 1 failed"):
            wait(1)
        wait(2)
        assert seen == ["a", "c"]


def test_rf_named_by_meta_json_but_missing_is_said(tmp_path):
    """A sequence whose meta.json names its rf.csv and sensors.csv, one of them missing: dead reckoning, and the
    missing file is a warning in problems.csv (it was passed over in silence)."""
    seq = tmp_path / "seq"
    shutil.copytree(DEMO, seq)
    (seq / "sensors.csv").unlink()
    exam = open_exams([str(seq)])[0]
    assert exam.rf is None
    assert [p[2] for p in exam.problems] == ["warning"]
    assert "sensors.csv named by meta.json not found" in exam.problems[0][3]


def test_an_exam_whose_fusion_fails_is_dead_reckoned_as_one_without_rf(tmp_path):
    """With RF the serial end skips dead reckoning while the fusion runs; where the fusion then gives nothing (here
    an rf.csv with readings in only two frames: too few fixes to align), the exam's trajectory and 1-sigmas are the
    dead reckoning an exam without RF gets, byte for byte, and the reason is in problems.csv."""
    with_rf, without = tmp_path / "with_rf", tmp_path / "without"
    shutil.copytree(DEMO, with_rf)
    lines = (DEMO / "rf.csv").read_text().splitlines()
    (with_rf / "rf.csv").write_text("\n".join([lines[0], *(x for x in lines[1:] if float(x.split(",")[0]) < 0.6)])
                                    + "\n")
    shutil.copytree(DEMO, without)
    meta = json.loads((without / "meta.json").read_text())
    for f in ("rf.csv", "sensors.csv"):
        (without / f).unlink()
    meta.pop("rf", None)
    (without / "meta.json").write_text(json.dumps(meta))
    ea, eb = open_exams([str(with_rf)])[0], open_exams([str(without)])[0]
    assert ea.rf is not None and eb.rf is None
    ra = run_batch([ea], tmp_path / "a", FAST, jobs=1)
    rb = run_batch([eb], tmp_path / "b", FAST, jobs=1)
    assert ra.exams[0]["trajectory"] == rb.exams[0]["trajectory"] == "dead reckoning"
    assert "RF not used" in (tmp_path / "a" / "problems.csv").read_text()
    for name in ("trajectory.tum", "uncertainty.csv", "motion.csv"):
        a, b = (tmp_path / "a" / "with_rf" / name), (tmp_path / "b" / "without" / name)
        assert a.read_bytes() == b.read_bytes(), name
    tum = np.loadtxt(tmp_path / "a" / "with_rf" / "trajectory.tum")
    assert np.linalg.norm(tum[-1, 1:4] - tum[0, 1:4]) > 0.01  # a trajectory that moved, not zeros


def test_the_summary_counts_the_steps_fitted_beside_the_wall(tmp_path, monkeypatch):
    """Steps whose tube fit put the camera beside its own cylinder's wall (StepMotion.beside_wall) are counted in
    summary.json (``steps_beside_wall``) as motion.csv marks them, and the report says so. The demo's ideal tube
    has none, so every third pair is marked here as the fit would."""
    from dataclasses import replace

    from bodyslam.vision.odometry import VisualOdometry

    plain = VisualOdometry.estimate_pair
    calls = iter(range(10**6))

    def marked(self, f1, f2, *a, **kw):
        s = plain(self, f1, f2, *a, **kw)
        return replace(s, beside_wall=True) if s.ok and next(calls) % 3 == 0 else s

    monkeypatch.setattr(VisualOdometry, "estimate_pair", marked)
    run_batch(open_exams([str(_plain_folder(tmp_path / "exam", 10))]), tmp_path / "out", FAST, jobs=1)
    d = tmp_path / "out" / "exam"
    summary = json.loads((d / "summary.json").read_text())
    flagged = [r for r in _rows(d / "motion.csv") if r["beside_wall"] == "1"]
    assert summary["steps_beside_wall"] == len(flagged) > 0
    assert all(r["status"] in ("ok", "wall") for r in flagged)
    assert f"{len(flagged)} of the estimated steps fitted beside the wall" in (d / "report.html").read_text()
    # their share of the path (lengths the speed model gave them), as uncertainty.csv's path column holds it
    wall = np.array([r["beside_wall"] == "1" for r in _rows(d / "motion.csv")])
    path = np.array([float(r["path_m"]) for r in _rows(d / "uncertainty.csv")])
    share = float(np.diff(path)[wall].sum() / path[-1])
    assert 0 < summary["path_beside_wall_share"] == pytest.approx(share)
    assert f"{100 * share:.0f}% in fits beside the wall" in (d / "report.html").read_text()


def test_the_summary_says_how_much_of_the_path_the_missing_steps_hold(tmp_path, monkeypatch):
    """summary.json's ``path_without_estimate_share`` is the share of the path travelled in steps without an
    estimate (their lengths are the missing-step model's), as uncertainty.csv's path column holds them, and the
    report says it beside the path. Every fourth pair loses its matches here, as in turbid fluid."""
    from dataclasses import replace

    from bodyslam.steps import StepMotion, StepStatus
    from bodyslam.vision.odometry import VisualOdometry

    plain = VisualOdometry.estimate_pair
    calls = iter(range(10**6))

    def lossy(self, f1, f2, *a, **kw):
        s = plain(self, f1, f2, *a, **kw)
        return StepMotion(n_matches=5, status=StepStatus.LOST) if next(calls) % 4 == 1 else s

    monkeypatch.setattr(VisualOdometry, "estimate_pair", lossy)
    settings = replace(FAST, motion=replace(FAST.motion, bridge_gaps=0))  # the lost steps stay lost
    run_batch(open_exams([str(_plain_folder(tmp_path / "exam", 12))]), tmp_path / "out", settings, jobs=1)
    d = tmp_path / "out" / "exam"
    summary = json.loads((d / "summary.json").read_text())
    rows = _rows(d / "motion.csv")
    missing = np.array([r["status"] not in ("ok", "wall", "bridged") for r in rows])
    assert missing.sum() >= 2
    path = np.array([float(r["path_m"]) for r in _rows(d / "uncertainty.csv")])
    expected = float(np.diff(path)[missing].sum() / path[-1])
    assert 0 < summary["path_without_estimate_share"] == pytest.approx(expected)
    page = (d / "report.html").read_text()
    assert f"{100 * expected:.0f}% of it in steps without an estimate" in page
    # the loss curve's scale the path model chose for this exam, in lumen radii, and on the page
    from bodyslam.steps import LOSS_SCALE_GRID, LOST_STEP_FLOOR_R

    half = summary["path_loss_half_length_r"]
    assert half in [round(LOST_STEP_FLOOR_R * g, 3) for g in LOSS_SCALE_GRID]
    assert f"half of the steps are lost at {half:g} lumen radii" in page


def test_the_lumen_scale_rescales_every_step_with_a_pose(tmp_path, monkeypatch):
    """The exam's lumen scale (bodyslam.vision.lumen_scale), the median of the sampled steps' ring ratios, rescales
    the translation of every step with a pose in motion.csv and leaves its rotation; summary.json says what was
    applied. The ratio is fixed here at 0.9 so the check is exact, and the least sample lowered to fit 12 frames."""
    from dataclasses import replace

    from bodyslam.vision import lumen_scale

    monkeypatch.setattr(lumen_scale, "ring_distance_ratio", lambda *a, **k: 0.9)
    monkeypatch.setattr(lumen_scale, "RING_MIN_SAMPLES", 2)
    monkeypatch.setattr(lumen_scale, "RING_SAMPLE_MIN_STEPS", 2)
    folder = _plain_folder(tmp_path / "exam", 12)
    # the chain off too, so that the factor is all that differs (bodyslam.vision.scale_chain: tested there)
    run_batch(open_exams([str(folder)]), tmp_path / "on", replace(FAST, motion=replace(FAST.motion, scale_chain=False)),
              jobs=1)
    off = replace(FAST, motion=replace(FAST.motion, lumen_scale=False))
    run_batch(open_exams([str(folder)]), tmp_path / "off", off, jobs=1)
    on_rows, off_rows = _rows(tmp_path / "on" / "exam" / "motion.csv"), _rows(tmp_path / "off" / "exam" / "motion.csv")
    sampled = [r for r in on_rows if r["ring_ratio"] != "nan"]
    every = lumen_scale.ring_every(12)
    assert every > 0 and len(sampled) >= 2 and all(int(r["frame"]) % every == 0 for r in sampled)
    assert all(r["ring_ratio"] == "nan" for r in off_rows)
    n_pose = 0
    for a, b in zip(on_rows, off_rows):
        assert a["status"] == b["status"] and a["rx_rad"] == b["rx_rad"] and a["roll_rad"] == b["roll_rad"]
        if a["status"] in ("ok", "wall", "bridged"):
            n_pose += 1
            for c in ("distance_m", "tx_m", "tz_m"):
                assert float(a[c]) == pytest.approx(0.9 * float(b[c]), rel=1e-7, abs=1e-12)
        else:
            assert a["distance_m"] == b["distance_m"]
    assert n_pose > 5
    sc = json.loads((tmp_path / "on" / "exam" / "summary.json").read_text())["lumen_scale"]
    assert sc["factor"] == pytest.approx(0.9) and sc["samples"] == len(sampled) and sc["applied"]
    assert sc["steps_tried"] == len(sampled)  # every fit gave its ratio here
    assert sc["effective_radius_m"] == pytest.approx(0.9 * json.loads(
        (tmp_path / "on" / "exam" / "summary.json").read_text())["radius_m"])
    assert json.loads((tmp_path / "off" / "exam" / "summary.json").read_text())["lumen_scale"] is None


def test_a_frame_range_is_a_stretch_of_the_recording_with_its_own_numbers_and_times(tmp_path):
    """The small bowel between two landmark frames, say: only those frames are read, they keep their numbers and
    times, and every step inside is the one the whole recording gives (each step depends on its two frames only;
    the demo's radius is known, so no exam-wide scale touches them)."""
    run_batch(open_exams([str(DEMO)]), tmp_path / "all", FAST, jobs=1)
    rep = run_batch(open_exams([str(DEMO)], frame_range=(5, 30), marks=[(12, ""), (3, "")], landmarks=[8]),
                    tmp_path / "cut", FAST, jobs=1)
    whole = {r["frame"]: r for r in _rows(tmp_path / "all" / "demo_seed0" / "motion.csv")}
    d = tmp_path / "cut" / "demo_seed0"
    steps = _rows(d / "motion.csv")
    assert [int(r["frame"]) for r in steps] == list(range(6, 31))
    assert all(r == whole[r["frame"]] for r in steps)
    frames = _rows(d / "frames.csv")
    assert [int(r["frame"]) for r in frames] == list(range(5, 31)) and float(frames[0]["t"]) == 2.5
    s = rep.exams[0]
    assert s["frames"] == s["frames_expected"] == 26 and s["frame_range"] == [5, 30]
    assert [int(r["frame"]) for r in _rows(d / "marks.csv")] == [12]
    problems = _rows(tmp_path / "cut" / "problems.csv")
    assert [(p["frame"], p["reason"]) for p in problems] == [("3", "marked frame not in the exam: outside its "
                                                                    "frame range 5-30")]
    again = run_batch(open_exams([str(DEMO)], frame_range=(5, 30), marks=[(12, ""), (3, "")], landmarks=[8]),
                      tmp_path / "cut", FAST, jobs=1)  # the same command resumes its own run
    assert again.chunks_computed == 0 and again.chunks_reused > 0
    # landmarks alone: one outside the stretch is an error, one inside a warning that nothing is measured from it
    # (neither was mentioned: the landmarks were read only where there were marks)
    run_batch(open_exams([str(DEMO)], frame_range=(5, 30), landmarks=[8, 35]), tmp_path / "lm", FAST, jobs=1)
    assert [(p["frame"], p["severity"]) for p in _rows(tmp_path / "lm" / "problems.csv")] == [("35", "error"),
                                                                                              ("8", "warning")]
    # a folder's gaps outside the stretch are not its problems; to the end with "FIRST-"
    folder = _plain_folder(tmp_path / "plain", 12)
    (folder / "capsule_00003.png").unlink()
    assert len(open_exams([str(folder)])[0].problems) == 1
    e = open_exams([str(folder)], frame_range=(4, None))[0]
    assert [f[0] for f in e.frames] == list(range(4, 12)) and e.problems == []
    assert e.describe() != open_exams([str(folder)], frame_range=(5, None))[0].describe()  # no resuming across


def test_a_frame_range_of_a_video_seeks_to_its_first_frame(tmp_path):
    vid = tmp_path / "exam.avi"
    _write_video(vid, 20)
    run_batch(open_exams([str(vid)], radius_m=0.015), tmp_path / "all", BatchSettings(chunk_frames=20), jobs=1)
    rep = run_batch(open_exams([str(vid)], radius_m=0.015, frame_range=(7, 15)), tmp_path / "cut",
                    BatchSettings(chunk_frames=4), jobs=1)
    whole = _rows(tmp_path / "all" / "exam" / "frames.csv")
    frames = _rows(tmp_path / "cut" / "exam" / "frames.csv")
    assert [int(r["frame"]) for r in frames] == list(range(7, 16))
    assert [r["t"] for r in frames] == [r["t"] for r in whole[7:16]]  # the container's times, as read from 0
    all_steps = {r["frame"]: r for r in _rows(tmp_path / "all" / "exam" / "motion.csv")}
    assert all(r == all_steps[r["frame"]] for r in _rows(tmp_path / "cut" / "exam" / "motion.csv"))
    assert rep.exams[0]["frame_range"] == [7, 15]
    # past the end of the video, the range's end is the video's end (a container's count is an estimate)
    assert open_exams([str(vid)], frame_range=(10, 500))[0].n_positions == 10


@pytest.mark.parametrize("text, message", [("12", "give FIRST-LAST"), ("30-12", "LAST must be after FIRST"),
                                           ("a-b", "give FIRST-LAST"), ("5-5", "LAST must be after FIRST")])
def test_a_bad_frame_range_is_refused_by_name(tmp_path, capsys, text, message):
    code = cli_main(["batch", str(DEMO), "--frame-range", text, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 1 and message in err and repr(text) in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_a_frame_range_outside_the_recording_is_refused_by_name(tmp_path, capsys):
    vid = tmp_path / "exam.avi"
    _write_video(vid, 6)
    for src, text, message in ((DEMO, "50-60", "holds 0 frame(s) (the folder's frames are numbered 0-39)"),
                               (DEMO, "39-", "holds 1 frame(s)"),
                               (vid, "5-9", "starts at or past the video's last frame (6 frames by its container")):
        code = cli_main(["batch", str(src), "--frame-range", text, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert code == 1 and message in err and len(err.strip().splitlines()) == 1, err
    # in a manifest: the row is named
    (tmp_path / "m.csv").write_text(f"input,frame_range\n{DEMO},10-\n{DEMO},x\n")
    with pytest.raises(InputError, match=r"m.csv:line 3: frame range 'x'"):
        open_exams([str(tmp_path / "m.csv")])
    (tmp_path / "m2.csv").write_text(f"input,frame_range\n{DEMO},10-\n")
    assert open_exams([str(tmp_path / "m2.csv")])[0].frame_range == (10, None)


def test_frames_exported_beside_a_panel_get_a_lens_centred_on_their_field(tmp_path, capsys):
    # an export that puts the image at the left of a wider frame, a panel of text at its right: the assumed lens is
    # centred on the detected field (the frame's centre put the camera beside the wall of its own fits), and the
    # steps come out as the plain frames' do
    plain = _plain_folder(tmp_path / "plain", 6)
    wide = tmp_path / "wide"
    wide.mkdir()
    for k in range(6):
        canvas = np.zeros((400, 520, 3), np.uint8)
        canvas[30:350, 10:330] = cv2.imread(str(DEMO / "frames" / f"{k:06d}.png"))
        cv2.putText(canvas, f"00:00:{k:02d}", (360, 200), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
        cv2.imwrite(str(wide / f"capsule_{k:05d}.png"), canvas)
    for d in (plain, wide):
        assert cli_main(["batch", str(d), "--out", str(tmp_path / f"out_{d.name}"), "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert "centred at (169.5, 189.5)" in out and "in 520x400 frames" in out
    cam = json.loads((tmp_path / "out_wide" / "wide" / "summary.json").read_text())["camera"]
    assert (cam["cx"], cam["cy"]) == (169.5, 189.5)  # the field's centre, not the frame's (259.5, 199.5)
    a, b = (_rows(tmp_path / f"out_{d}" / d / "motion.csv") for d in ("plain", "wide"))
    da, db = (np.array([float(r["distance_m"]) for r in rows]) for rows in (a, b))
    assert [r["beside_wall"] for r in b].count("1") == 0
    both = np.isfinite(da) & np.isfinite(db)  # (the demo's thesis motion: a hard pair may fail either way)
    assert both.sum() >= 3 and [r["status"] for r in b].count("ok") == [r["status"] for r in a].count("ok")
    # the field is the disc less the detector's 1-px rim (318 of 320 px): ~1% on the lens, a few % on a distance
    assert np.allclose(db[both], da[both], rtol=0.06), (da, db)


def test_the_report_says_whether_the_radius_is_a_prior_or_known():
    """A radius with a 1-sigma is a prior; one without (--radius-m, a testbed tube of one radius) is not called one."""
    from bodyslam.exam.batch import radius_text

    assert radius_text(0.0125, 0.0025) == "1.25 +- 0.25 cm (the prior, 1-sigma)"
    assert radius_text(0.015, 0.0) == "1.50 cm (known exactly: the steps' scale)"


def test_a_clip_takes_the_lumen_radius_its_exam_measured(tmp_path):
    """``--radius-from``: the lumen radius an earlier batch run measured for its exam (its lumen scale's effective
    radius) and its 1-sigma, from the exam's summary.json, the study's (one exam) or their directory; refused with the
    file and the reason where there is none to take, and beside --radius-m. A summary from before the 1-sigma was
    stated gives the radius alone, taken as known."""
    from bodyslam.exam.batch import radius_from_summary

    scale = {"factor": 0.736, "samples": 34, "applied": True, "effective_radius_m": 0.0092,
             "effective_radius_sd_m": 0.0008}
    exam = tmp_path / "out" / "exam"
    exam.mkdir(parents=True)
    (exam / "summary.json").write_text(json.dumps({"exam": "exam", "lumen_scale": scale}))
    (tmp_path / "out" / "summary.json").write_text(json.dumps({"exams": [{"exam": "exam", "lumen_scale": scale}]}))
    for p in (exam / "summary.json", exam, tmp_path / "out" / "summary.json", tmp_path / "out"):
        assert radius_from_summary(p) == (0.0092, 0.0008)
    (tmp_path / "two.json").write_text(json.dumps({"exams": [{"lumen_scale": scale}, {"lumen_scale": scale}]}))
    (tmp_path / "unapplied.json").write_text(json.dumps({"lumen_scale": dict(scale, applied=False, samples=5)}))
    (tmp_path / "unmeasured.json").write_text(json.dumps({"lumen_scale": None}))
    (tmp_path / "other.json").write_text(json.dumps({"format": "bodyslam-sequence/1"}))
    (tmp_path / "broken.json").write_text(json.dumps({"lumen_scale": dict(scale, effective_radius_m=-1)}))
    (tmp_path / "broken_sd.json").write_text(json.dumps({"lumen_scale": dict(scale, effective_radius_sd_m=0.01)}))
    old = {k: v for k, v in scale.items() if k != "effective_radius_sd_m"}
    (tmp_path / "old.json").write_text(json.dumps({"lumen_scale": old}))
    assert radius_from_summary(tmp_path / "old.json") == (0.0092, None)
    for name, why in (("two.json", "a study of 2 exams"), ("unapplied.json", "not applied: 5 ring"),
                      ("unmeasured.json", "was not measured"), ("other.json", "not a bodyslam batch summary"),
                      ("broken.json", "not a positive number"), ("broken_sd.json", "not a 1-sigma"),
                      ("missing.json", "file not found")):
        with pytest.raises(InputError, match=why):
            radius_from_summary(tmp_path / name)
    # through the CLI: the demo clip runs at that radius with its 1-sigma (8.7%: below the 10% at which a clip would
    # measure its own scale again, so its steps keep it); an old summary's radius is taken as known
    assert cli_main(["batch", str(DEMO / "frames"), "--out", str(tmp_path / "clip"), "--jobs", "1",
                     "--radius-from", str(exam)]) == 0
    summary = json.loads((tmp_path / "clip" / "summary.json").read_text())["exams"][0]
    assert (summary["radius_m"], summary["radius_sd_m"]) == (0.0092, 0.0008)
    assert summary["lumen_scale"] is None
    assert cli_main(["batch", str(DEMO / "frames"), "--out", str(tmp_path / "clip_old"), "--jobs", "1",
                     "--radius-from", str(tmp_path / "old.json")]) == 0
    old_summary = json.loads((tmp_path / "clip_old" / "summary.json").read_text())["exams"][0]
    assert (old_summary["radius_m"], old_summary["radius_sd_m"]) == (0.0092, 0.0)
    # the radius's 1-sigma widens the path's
    assert summary["sd_path_travelled_m"] > old_summary["sd_path_travelled_m"]
    # bodyslam motion (and track, localize) take it too: the same distances as with --radius-m, each step's 1-sigma
    # with the radius's share in it
    from bodyslam.io import read_motion_csv

    assert cli_main(["motion", str(DEMO), "--out", str(tmp_path / "from.csv"), "--mode", "fast", "--jobs", "1",
                     "--radius-from", str(exam)]) == 0
    assert cli_main(["motion", str(DEMO), "--out", str(tmp_path / "known.csv"), "--mode", "fast", "--jobs", "1",
                     "--radius-m", "0.0092"]) == 0
    a, b = read_motion_csv(tmp_path / "from.csv"), read_motion_csv(tmp_path / "known.csv")
    fitted = [k for k in a if a[k]["distance_m"] > 1e-4 and a[k]["status"] == "ok"]
    assert fitted and all(a[k]["distance_m"] == b[k]["distance_m"] for k in a)
    for k in fitted:  # the fit's and the shape's shares are the same in both: the difference is the radius's
        share = math.sqrt(a[k]["sigma_distance_m"] ** 2 - b[k]["sigma_distance_m"] ** 2)
        assert share == pytest.approx(0.0008 / 0.0092 * a[k]["distance_m"], rel=1e-3), k  # (9 digits in the CSV)
    assert cli_main(["motion", str(DEMO), "--out", str(tmp_path / "both.csv"), "--radius-from", str(exam),
                     "--radius-m", "0.01"]) == 1
    assert cli_main(["localize", str(DEMO), "--out", str(tmp_path / "loc"), "--motion", str(tmp_path / "from.csv"),
                     "--radius-from", str(tmp_path / "broken_sd.json")]) == 1
    assert not (tmp_path / "both.csv").exists() and not (tmp_path / "loc").exists()
    assert cli_main(["batch", str(DEMO / "frames"), "--out", str(tmp_path / "both"), "--radius-from", str(exam),
                     "--radius-m", "0.01"]) == 1
    assert cli_main(["batch", str(DEMO / "frames"), "--out", str(tmp_path / "none"),
                     "--radius-from", str(tmp_path / "unapplied.json")]) == 1
    assert not (tmp_path / "both").exists() and not (tmp_path / "none").exists()  # refused before any work

"""The bodyslam command as a whole: a light start, a description and an example per subcommand, one exit-code
rule (0 done, 3 done with problems listed, 1 unusable input, 130 interrupted)."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import sys
from pathlib import Path


from bodyslam.cli import COMMANDS, _parser
from bodyslam.cliutil import run_cli

DEMO = Path(__file__).resolve().parents[2] / "data_samples" / "demo_seed0"


def run(*args):
    return subprocess.run([sys.executable, "-m", "bodyslam.cli", *args], capture_output=True, text=True)


def test_help_imports_neither_opencv_nor_scipy():
    """``bodyslam --help`` must start fast: the parser module may not pull in the heavy libraries (the
    choices come from bodyslam.choices). Checked by what is imported, not by a timing."""
    code = "import sys, bodyslam.cli; bodyslam.cli._parser(); print(sorted(m for m in ('cv2', 'scipy', 'sklearn') if m in sys.modules))"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.strip() == "[]", p.stdout + p.stderr


def test_every_subcommand_has_a_description_and_an_example():
    sub = next(a for a in _parser()._actions if a.dest == "cmd")
    assert set(sub.choices) == set(COMMANDS)
    for name, parser in sub.choices.items():
        assert parser.description and parser.epilog.startswith("example: bodyslam " + name), name


def test_exit_codes_done_problems_unusable(tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(DEMO, seq, ignore=shutil.ignore_patterns("depth"))
    # done: 0
    assert run("check", str(seq)).returncode == 0
    # done, with problems listed: a corrupt frame (check, motion), a malformed RF line (localize, batch)
    (seq / "frames" / "000020.png").write_bytes(b"garbage")
    p = run("check", str(seq))
    assert p.returncode == 3 and "000020.png" in p.stdout
    p = run("motion", str(seq), "--out", str(tmp_path / "m.csv"), "--mode", "fast", "--jobs", "1")
    assert p.returncode == 3 and "000020.png" in p.stdout and (tmp_path / "m.csv").is_file()
    # the field of view used is written beside the output: on the ideal testbed the image circle (detection agrees)
    from bodyslam.io import read_image
    from bodyslam.meta import read_meta

    assert np.array_equal(read_image(tmp_path / "m_mask.png", unchanged=True) > 0,
                          read_meta(seq).camera_model().fov_mask())
    shutil.copy(DEMO / "frames" / "000020.png", seq / "frames" / "000020.png")
    with (seq / "rf.csv").open("a") as f:
        f.write("oops,S1,-60\n")
    p = run("localize", str(seq), "--out", str(tmp_path / "loc"), "--mode", "fast", "--jobs", "1")
    assert p.returncode == 3 and "rf.csv" in p.stdout, p.stdout + p.stderr
    assert (tmp_path / "loc" / "trajectory.tum").is_file() and (tmp_path / "loc" / "mask.png").is_file()
    p = run("batch", str(seq), "--out", str(tmp_path / "b"), "--jobs", "1")
    assert p.returncode == 3, p.stdout + p.stderr
    assert (tmp_path / "b" / seq.name / "mask.png").is_file()
    # unusable input: 1, one line, and a failed run leaves no output directory behind
    p = run("localize", str(seq), "--out", str(tmp_path / "loc3"), "--motion", str(tmp_path / "loc" / "motion.csv"),
            "--radius-m", "-0.01")
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1 and "lumen radius in metres" in p.stderr
    assert not (tmp_path / "loc3").exists()
    # a radius in centimetres (every step 80x too long, without a word) is named with the metres it meant
    p = run("localize", str(seq), "--out", str(tmp_path / "loc3"), "--motion", str(tmp_path / "loc" / "motion.csv"),
            "--radius-m", "1.25")
    assert p.returncode == 1 and "1.25 centimetres is 0.0125" in p.stderr, p.stderr
    assert not (tmp_path / "loc3").exists()
    (seq / "rf.csv").write_text("t,sensor,rss_dbm\n")
    p = run("localize", str(seq), "--out", str(tmp_path / "loc2"), "--motion", str(tmp_path / "loc" / "motion.csv"))
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1 and "RF" in p.stderr
    assert not (tmp_path / "loc2").exists()


def test_classify_takes_the_frame_size_from_a_frame_that_decodes(tmp_path):
    """A plain folder whose first frame is corrupt: the camera's size comes from the first frame that decodes, so
    the others are classified and the corrupt one is listed (exit 3); it used to stop the whole folder with exit 1.
    A folder where nothing decodes is unusable input, and says that ``--meta`` gives the camera."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(4):
        shutil.copy(DEMO / "frames" / f"{k:06d}.png", frames / f"{k:06d}.png")
    (frames / "000000.png").write_bytes(b"garbage")
    p = run("classify", str(frames), "--out", str(tmp_path / "c.csv"), "--jobs", "1")
    assert p.returncode == 3 and "000000.png" in p.stdout, p.stdout + p.stderr
    rows = (tmp_path / "c.csv").read_text().splitlines()[1:]
    assert [r.split(",")[3] for r in rows] == ["unreadable", "ok", "ok", "ok"], rows
    assert all(r.split(",")[1] in ("FT", "FL") for r in rows[1:])
    for k in range(1, 4):
        (frames / f"{k:06d}.png").write_bytes(b"garbage")
    p = run("classify", str(frames), "--out", str(tmp_path / "c2.csv"))
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1 and "--meta" in p.stderr, p.stderr
    assert not (tmp_path / "c2.csv").exists()


def test_a_file_that_is_not_a_video_is_one_line_without_ffmpegs_own(tmp_path):
    """OpenCV's FFmpeg reader printed its own log line ("moov atom not found") above the command's error; the
    command names the file itself, so stderr is that one line (``-v`` or OPENCV_FFMPEG_LOGLEVEL keeps FFmpeg's)."""
    (tmp_path / "clip.mp4").write_text("not a video")
    p = run("batch", str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "o"))
    assert p.returncode == 1 and p.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'clip.mp4'}: cannot open the video (unsupported codec or not a video)"], p.stderr


def test_a_worker_count_below_one_is_refused_by_name(tmp_path):
    """``--jobs 0`` (or less) is an argument error that says what to give, on every command that takes it; it was
    read as "one per core". Nothing is written."""
    from testbed.cli import main as testbed_main

    for cmd in (["motion", str(DEMO), "--out", str(tmp_path / "m.csv")],
                ["batch", str(DEMO), "--out", str(tmp_path / "b")],
                ["classify", str(DEMO), "--out", str(tmp_path / "c.csv")]):
        p = run(*cmd, "--jobs", "0")
        assert p.returncode == 2 and "argument --jobs: give at least 1 worker process, got 0" in p.stderr, cmd
    try:
        testbed_main(["simulate", "demo", "--seed", "0", "--out", str(tmp_path / "s"), "--jobs", "-2"])
    except SystemExit as exc:
        assert exc.code == 2
    else:
        raise AssertionError("testbed simulate --jobs -2 was accepted")
    assert not any(tmp_path.iterdir())


def test_interrupt_exits_130():
    def body(argv):
        raise KeyboardInterrupt

    assert run_cli(body, []) == 130


def test_uncertainty_csv_has_one_schema(tmp_path):
    """localize and batch (with and without RF) write uncertainty.csv with the same columns."""
    from bodyslam.fusion.localize import UNCERTAINTY_COLUMNS

    p = run("localize", str(DEMO), "--out", str(tmp_path / "loc"), "--mode", "fast", "--jobs", "1")
    assert p.returncode == 0, p.stderr
    # the demo's two rotation-only steps: part of the printed path is the missing-step model's
    assert "% of it in steps without an estimate" in p.stdout, p.stdout
    # the opt-in per-sensor RSS bias states: another trajectory from the same steps, the same files
    p = run("localize", str(DEMO), "--out", str(tmp_path / "loc_b"), "--motion", str(tmp_path / "loc" / "motion.csv"),
            "--rss-bias-states")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "loc_b" / "trajectory.tum").read_text() != (tmp_path / "loc" / "trajectory.tum").read_text()
    # each sensor's bias estimate, written and pointed at (without the states: no such file)
    assert len((tmp_path / "loc_b" / "rss_bias.csv").read_text().splitlines()) == 33 and "rss_bias.csv" in p.stdout
    assert not (tmp_path / "loc" / "rss_bias.csv").exists()
    for cmd in ("localize", "batch"):  # states of the raw-RSS filter: refused with fix fusion, not ignored
        p = run(cmd, str(DEMO), "--out", str(tmp_path / f"{cmd}_fix"), "--fusion", "fix", "--rss-bias-states")
        assert p.returncode == 1 and "--fusion rss" in p.stderr and not (tmp_path / f"{cmd}_fix").exists()
    p = run("batch", str(DEMO), "--out", str(tmp_path / "b"), "--jobs", "1", "--rss-bias-states")
    assert p.returncode == 0, p.stderr
    summary = json.loads((tmp_path / "b" / "demo_seed0" / "summary.json").read_text())
    assert "bias states" in summary["trajectory"], summary["trajectory"]
    # the count of fits beside the wall is printed where there are any (the ideal demo tube has none: no noise)
    assert ("fitted beside the wall" in p.stdout) == (summary["steps_beside_wall"] > 0), p.stdout
    # and how much of the path lies in steps without an estimate (the demo's two rotation-only steps: some)
    assert summary["path_without_estimate_share"] > 0
    assert f"({100 * summary['path_without_estimate_share']:.0f}% of it in steps without an estimate" in p.stdout
    assert "steps estimated" in p.stdout
    assert (tmp_path / "b" / "demo_seed0" / "rss_bias.csv").is_file()
    p = run("batch", str(DEMO / "frames"), "--out", str(tmp_path / "b2"), "--jobs", "1")
    assert p.returncode == 0, p.stderr
    for f in (tmp_path / "loc" / "uncertainty.csv", tmp_path / "b" / "demo_seed0" / "uncertainty.csv",
              tmp_path / "b2" / "frames" / "uncertainty.csv"):
        assert f.read_text().splitlines()[0].split(",") == UNCERTAINTY_COLUMNS, f


def test_failed_localizers_leave_no_output_directory(tmp_path):
    """magnetic-localize and hybrid-localize on a recording they cannot read: exit 1, one line, and nothing that
    looks like a result (they used to create their output directory first)."""
    (tmp_path / "rec").mkdir()
    for cmd in ("magnetic-localize", "hybrid-localize"):
        p = run(cmd, str(tmp_path / "rec"), "--out", str(tmp_path / cmd))
        assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1 and "meta.json" in p.stderr
        assert not (tmp_path / cmd).exists()


def test_progress_rates_only_the_work_of_this_run(monkeypatch):
    """A resumed batch starts with most frames reused from the checkpoints: the rate counts from the first call,
    so reused frames are counted, not rated (it printed 56,195 frames/s for 55,000 reused frames)."""
    import io

    from bodyslam import cliutil

    clock = iter([10.0, 20.0])
    monkeypatch.setattr(cliutil.time, "monotonic", lambda: next(clock))
    out = io.StringIO()
    bar = cliutil.Progress("batch", stream=out)
    bar(9000, 10000)  # at 10 s: 9,000 reused, no rate yet
    bar(10000, 10000)  # at 20 s: 1,000 computed
    assert out.getvalue().splitlines() == ["batch: 9000/10000", "batch: 10000/10000 (100.0/s)"]


def test_segment_shows_the_regions_a_normalised_classifier_reads(tmp_path):
    """``bodyslam segment --photometric channel_p90``: a frame and the same frame 40% darker with a colour cast give
    the same regions (what the shipped classifier segments); without it the darker frame's regions are painted in
    its own, darker colours. A bad mode is refused by name."""
    from bodyslam.io import read_image, write_image

    img = read_image(DEMO / "frames" / "000010.png")
    dark = np.clip(img.astype(float) * [0.6, 0.55, 0.5], 0, 255).astype(np.uint8)
    write_image(tmp_path / "a.png", img)
    write_image(tmp_path / "b.png", dark)
    out = {}
    for name in ("a", "b"):
        for mode in ("none", "channel_p90"):
            p = run("segment", str(tmp_path / f"{name}.png"), "--meta", str(DEMO), "--photometric", mode,
                    "--out", str(tmp_path / f"{name}_{mode}.png"))
            assert p.returncode == 0, p.stderr
            out[name, mode] = read_image(tmp_path / f"{name}_{mode}.png").astype(int)
    # the same regions, painted in the same normalised colours, to the rounding of the 8-bit levels
    assert np.abs(out["a", "channel_p90"] - out["b", "channel_p90"]).mean() < 1.0
    assert np.abs(out["a", "none"] - out["b", "none"]).mean() > 10.0
    p = run("segment", str(tmp_path / "a.png"), "--meta", str(DEMO), "--photometric", "histogram",
            "--out", str(tmp_path / "x.png"))
    assert p.returncode == 2 and "--photometric" in p.stderr and not (tmp_path / "x.png").exists()


def test_train_classifier_on_labels_it_can_read_and_none_it_cannot(tmp_path):
    # labels.csv was split by hand: a short row ended in an IndexError traceback, and any label was learnt
    seq = tmp_path / "seq"
    shutil.copytree(DEMO, seq, ignore=shutil.ignore_patterns("depth"))
    rows = (DEMO / "labels.csv").read_text().splitlines()
    flipped = [r.replace(",FT,", ",FL,") if i % 3 == 0 else r for i, r in enumerate(rows[1:])]  # both classes
    (seq / "labels.csv").write_text("\n".join(rows[:1] + flipped) + "\n")
    p = run("train-classifier", str(seq), "--out", str(tmp_path / "m.npz"), "--jobs", "1")
    assert p.returncode == 0 and "FL)" in p.stdout and (tmp_path / "m.npz").is_file(), p.stdout + p.stderr
    (seq / "labels.csv").write_text("\n".join(rows[:1] + flipped[:3] + ["3,1.0", flipped[4].replace("FT", "ft")]))
    p = run("train-classifier", str(seq), "--out", str(tmp_path / "m2.npz"), "--jobs", "1")
    assert p.returncode == 1 and p.stderr.strip().splitlines() == [
        f"error: {seq / 'labels.csv'}:6: label must be FT or FL (or empty), got 'ft'"], p.stderr
    assert not (tmp_path / "m2.npz").exists()
    # one FL frame cannot be cross-validated: sklearn's fits failed with a page of warnings and a model came out
    (seq / "labels.csv").write_text("\n".join(rows[:1] + flipped[:3]) + "\n")
    p = run("train-classifier", str(seq), "--out", str(tmp_path / "m3.npz"), "--jobs", "1")
    assert p.returncode == 1 and "at least 2 frames of each class" in p.stderr and "Warning" not in p.stderr, p.stderr

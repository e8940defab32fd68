"""Frame sources (bodyslam.frames): video time stamps."""

import cv2
import numpy as np

from bodyslam import frames
from bodyslam.frames import FrameSource, collapse_format_notes


def test_video_frames_are_timed_by_their_presentation_times(tmp_path, monkeypatch):
    # a real file: presentation times k / fps, also after a seek (a worker's chunk)
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 4.0, (64, 64))
    for k in range(6):
        w.write(np.full((64, 64, 3), 40 * k, np.uint8))
    w.release()
    src = FrameSource("video", str(path), 4.0, n_frames=6)
    assert [f.t_s for f in src.read()] == [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]
    assert [f.t_s for f in src.read(3, 4)] == [0.75, 1.0]

    # variable frame rate (no muxer in the stack writes one: a capture that reports uneven presentation times)
    class Capture:
        pts_ms = [0.0, 200.0, 450.0, 1200.0]

        def __init__(self, _):
            self.k = -1

        def read(self):
            self.k += 1
            return (self.k < len(self.pts_ms)), np.zeros((8, 8, 3), np.uint8)

        def get(self, prop):
            assert prop == cv2.CAP_PROP_POS_MSEC
            return self.pts_ms[self.k]

        def set(self, *_):
            pass

        def release(self):
            pass

    monkeypatch.setattr(frames.cv2, "VideoCapture", Capture)
    got = list(FrameSource("video", "vfr.mkv", 5.0, n_frames=4).read())
    assert [f.t_s for f in got] == [0.0, 0.2, 0.45, 1.2]
    # a backend without presentation times (0 after the first frame): index / frame rate
    Capture.pts_ms = [0.0, 0.0, 0.0]
    assert [f.t_s for f in FrameSource("video", "x.avi", 5.0, n_frames=3).read()] == [0.0, 0.2, 0.4]


def test_how_an_exam_was_stored_is_one_problem_not_one_per_frame():
    # a grayscale or 16-bit exam gave one warning per frame (50,000 lines for a whole exam); now the first frame's
    # row says how many frames have it, other problems keep their rows and their order
    rows = [["a/000000.png", 0, "warning", "grayscale frame: read as RGB"],
            ["a/000001.png", 1, "error", "empty file (0 bytes)"],
            ["a/000002.png", 2, "warning", "grayscale frame: read as RGB"],
            ["a/000007.png", 7, "warning", "grayscale frame: read as RGB"],
            ["a/000008.png", 8, "warning", "16-bit frame: scaled to 8 bits"]]
    out = collapse_format_notes(rows)
    assert out == [["a/000000.png", 0, "warning", "grayscale frame: read as RGB (3 frames, 0 to 7)"],
                   ["a/000001.png", 1, "error", "empty file (0 bytes)"],
                   ["a/000008.png", 8, "warning", "16-bit frame: scaled to 8 bits"]]
    assert rows[0][3] == "grayscale frame: read as RGB"  # the caller's rows are not changed

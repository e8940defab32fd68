"""Frame sources (bodyslam.frames): video time stamps."""

import cv2
import numpy as np

from bodyslam import frames
from bodyslam.frames import FrameSource


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

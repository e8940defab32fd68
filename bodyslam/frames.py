"""Where frames come from: a sequence directory, a folder of images or a video, as one :class:`FrameSource`.

A source is a small, picklable description (it is sent to worker processes and Dask workers); reading opens the
files there. :meth:`FrameSource.read` yields :class:`Frame` records for a range of *positions* (0 .. n-1, the
order of the exam): the frame number (``index``: a sequence's ``k``, the last number in an image file's name,
a video's frame number), its time stamp (folders: ``index / frame_rate``; videos: the container's presentation
time of the frame, so a variable-frame-rate file is timed right -- ``index / frame_rate`` only where the container
gives none), the RGB image or ``None`` and notes
``(severity, reason)`` saying what was wrong. Nothing raises for one bad frame: a corrupt file is a frame with
no image and an ``error`` note, and the caller decides (a step across it has status ``bad_frame``).

Folder listing: image files in the order of the last number in their names; that number is the frame index.
Missing numbers are reported as one gap problem each; files that are not images (by extension) are skipped
and reported. A video's frames are numbered from 0; a video that ends before its container's frame count
yields a last record with ``index == -1`` (:attr:`Frame.end_of_video`): a container's frame count is an estimate
(a WMV that says 19 frames may hold 18), so that is the end of the exam, not a problem.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from bodyslam.errors import InputError
from bodyslam.io import frame_name

__all__ = ["Frame", "FrameSource", "list_frames", "decode_frame", "collapse_format_notes", "IMAGE_EXTS", "VIDEO_EXTS",
           "SIDECARS", "FORMAT_NOTES"]

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
# the containers OpenCV's FFmpeg reads (it probes the content; the name only says a file is meant as a video)
VIDEO_EXTS = (".mp4", ".avi", ".wmv", ".mov", ".mkv", ".mpg", ".mpeg", ".m4v", ".asf", ".webm", ".ogv", ".flv",
              ".3gp", ".ts", ".m2ts", ".mts")
SIDECARS = {"meta.json", "rf.csv", "sensors.csv", "labels.csv", "groundtruth.tum", "motion_truth.csv",
            "centerline.csv", "truth.json", "calibration.json", "mask.png"}


@dataclass
class Frame:
    pos: int  # position in the source, 0 .. n-1
    index: int  # frame number (-1: the video ended here)
    t_s: float
    path: str  # the file read (the video file for videos)
    image: np.ndarray | None  # RGB uint8 (h, w, 3), None when unusable
    notes: list[tuple[str, str]] = field(default_factory=list)  # (severity, reason)
    path_is_video: bool = False

    @property
    def end_of_video(self) -> bool:
        return self.index < 0

    @property
    def label(self) -> str:
        """The file name of a folder frame, ``#index`` of a video frame."""
        return os.path.basename(self.path) if not self.path_is_video else f"#{self.index}"


@dataclass
class FrameSource:
    """Frames of one exam. ``kind``: ``folder`` (image files, a sequence directory's frames among them) or
    ``video``. ``frames``: ``(index, file name)`` per position for folders; ``n_frames`` for videos, from frame
    number ``start`` on."""

    kind: str
    source: str  # frames folder or video file
    frame_rate_hz: float
    frames: list[tuple[int, str]] = field(default_factory=list, repr=False)
    n_frames: int = 0
    offset: int = 0  # position of frames[0] (a subset sent to a worker)
    start: int = 0  # videos: the frame number at position 0 (an exam that is a stretch of the video)

    @classmethod
    def sequence(cls, frames_dir: str | os.PathLike, n_frames: int, frame_rate_hz: float) -> "FrameSource":
        """A sequence directory's frames ``000000.png .. `` (``n_frames`` of them, numbered from 0)."""
        return cls("folder", str(frames_dir), frame_rate_hz, [(k, frame_name(k)) for k in range(n_frames)])

    @classmethod
    def folder(cls, folder: str | os.PathLike, frame_rate_hz: float) -> tuple["FrameSource", list[list]]:
        """A folder of image files (:func:`list_frames`) and the problems found listing it."""
        frames, problems = list_frames(folder)
        return cls("folder", str(folder), frame_rate_hz, frames), problems

    def __len__(self) -> int:
        return self.offset + len(self.frames) if self.kind == "folder" else self.n_frames

    def subset(self, first: int, last: int) -> "FrameSource":
        """The same source restricted to positions ``first .. last`` (for a worker's task: small to send)."""
        if self.kind == "folder":
            return FrameSource("folder", self.source, self.frame_rate_hz,
                               self.frames[first - self.offset:last + 1 - self.offset], offset=first)
        return self

    def read(self, first: int = 0, last: int | None = None) -> Iterator[Frame]:
        """Frames at positions ``first .. last`` (inclusive; default: to the end), streamed."""
        last = len(self) - 1 if last is None else last
        if self.kind == "folder":
            for pos in range(first, last + 1):
                idx, name = self.frames[pos - self.offset]
                path = os.path.join(self.source, name)
                try:
                    with open(path, "rb") as f:
                        data = f.read()
                except OSError as exc:
                    yield Frame(pos, idx, idx / self.frame_rate_hz, path, None,
                                [("error", f"cannot read ({exc.strerror or exc})")])
                    continue
                img, notes = decode_frame(data, name)
                yield Frame(pos, idx, idx / self.frame_rate_hz, path, img, notes)
            return
        cap = cv2.VideoCapture(self.source)
        s0 = self.start
        try:
            if s0 + first > 0:
                cap.set(cv2.CAP_PROP_POS_FRAMES, s0 + first)
            for pos in range(first, last + 1):
                ok, bgr = cap.read()
                if not ok:
                    yield Frame(pos, -1, (s0 + pos) / self.frame_rate_hz, self.source, None,
                                [("info", f"the video ends at frame {s0 + pos} (its container says "
                                          f"{s0 + self.n_frames} frames: an estimate)")], path_is_video=True)
                    return
                yield Frame(pos, s0 + pos, _presentation_time_s(cap, s0 + pos, self.frame_rate_hz), self.source,
                            cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), [], path_is_video=True)
        finally:
            cap.release()

    def read_one(self, pos: int) -> Frame:
        return next(iter(self.read(pos, pos)))

    def first_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the first readable frame among the first 50, or None."""
        for pos in range(min(50, len(self))):
            fr = self.read_one(pos)
            if fr.image is not None:
                return fr.image.shape[1], fr.image.shape[0]
            if fr.end_of_video:
                break
        return None


def _presentation_time_s(cap, pos: int, frame_rate_hz: float) -> float:
    """The time stamp (s) of the frame ``cap`` has just read: its presentation time in the container (OpenCV's
    ``CAP_PROP_POS_MSEC`` after a read), or ``pos / frame_rate_hz`` where the backend gives none (negative, not a
    number, or 0 after the first frame)."""
    ms = cap.get(cv2.CAP_PROP_POS_MSEC)
    if math.isfinite(ms) and ms >= 0 and (ms > 0 or pos == 0):
        return ms / 1000.0
    return pos / frame_rate_hz


def decode_frame(data: bytes, name: str) -> tuple[np.ndarray | None, list[tuple[str, str]]]:
    """A frame file's bytes -> RGB uint8, with ``(severity, reason)`` notes; ``None`` when unusable."""
    if len(data) == 0:
        return None, [("error", "empty file (0 bytes)")]
    ext = os.path.splitext(name)[1].lower()
    if ext in (".jpg", ".jpeg") and data[:2] == b"\xff\xd8" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        # libjpeg decodes a cut file into a grey-filled frame with only a warning: refuse it here
        return None, [("error", "truncated JPEG (no end-of-image marker)")]
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None, [("error", "not a decodable image (corrupt, truncated or not an image)")]
    notes = []
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
        notes.append(("warning", "16-bit frame: scaled to 8 bits"))
    elif img.dtype != np.uint8:
        return None, [("error", f"unsupported pixel type {img.dtype}")]
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        img = cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
        notes.append(("warning", "grayscale frame: read as RGB"))
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img, notes


# decode notes that describe how an exam was stored rather than a fault of one frame: listed once per exam, at the
# first frame that has one, with how many frames have it (a 50,000-frame grayscale exam gave 50,000 lines)
FORMAT_NOTES = ("16-bit frame: scaled to 8 bits", "grayscale frame: read as RGB")


def collapse_format_notes(problems: list[list]) -> list[list]:
    """Problem rows ``[file, frame, severity, reason]`` with each of :data:`FORMAT_NOTES` kept at its first row only,
    its reason saying how many frames have it and from which to which; every other row unchanged, in order."""
    seen: dict[str, list] = {}
    out = []
    for row in problems:
        reason = row[3] if len(row) > 3 else None
        if reason not in FORMAT_NOTES:
            out.append(row)
            continue
        if reason not in seen:
            seen[reason] = [list(row), 0, row[1], row[1]]
            out.append(seen[reason][0])
        entry = seen[reason]
        entry[1] += 1
        entry[3] = row[1]
    for reason, (row, count, first, last) in seen.items():
        if count > 1:
            row[3] = f"{reason} ({count} frames, {first} to {last})"
    return out


_NUM = re.compile(r"(\d+)")


def list_frames(folder: str | os.PathLike) -> tuple[list[tuple[int, str]], list[list]]:
    """Image files of a folder in frame order, and the problems found (non-image files, numbering gaps).

    Returns ``([(index, name)], [[file, frame, severity, reason]])``. The index is the last number in the file
    name; when names carry no numbers, the sorted position.

    Raises
    ------
    InputError
        The folder cannot be listed.
    """
    folder = Path(folder)
    problems: list[list] = []
    imgs, numbered = [], True
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError as exc:
        raise InputError(f"{folder}: cannot list the folder ({exc.strerror or exc})") from None
    for entry in entries:
        if entry.name.startswith(".") or not entry.is_file() or entry.name in SIDECARS:
            continue
        ext = os.path.splitext(entry.name)[1].lower()
        if ext not in IMAGE_EXTS:
            problems.append([str(folder / entry.name), "", "warning", "not an image file (by extension): skipped"])
            continue
        nums = _NUM.findall(os.path.splitext(entry.name)[0])
        numbered &= bool(nums)
        imgs.append((int(nums[-1]) if nums else -1, entry.name))
    if not numbered:
        imgs = [(i, name) for i, (_, name) in enumerate(sorted(imgs, key=lambda x: x[1]))]
    imgs.sort()
    frames: list[tuple[int, str]] = []
    for idx, name in imgs:
        if frames and idx == frames[-1][0]:
            problems.append([str(folder / name), idx, "warning",
                             f"frame number {idx} also used by {frames[-1][1]}: skipped"])
            continue
        if frames and idx > frames[-1][0] + 1:
            a, b = frames[-1][0] + 1, idx - 1
            problems.append([str(folder), a, "warning",
                             f"numbering gap: frame{'s' if b > a else ''} {a}{f'-{b}' if b > a else ''} missing "
                             f"(the step from {frames[-1][0]} to {idx} spans {idx - frames[-1][0]} frame intervals)"])
        frames.append((idx, name))
    return frames, problems

"""Whole exams: frame folders, videos and manifests, processed in resumable chunks on both cores or a Dask
cluster (``bodyslam batch``).

An *exam* is one capsule recording: a folder of frames (a sequence directory with ``meta.json``, or a plain
folder of image files), or a video file. For each exam the run writes, under ``OUT/<exam>/``:

- ``frames.csv``: ``frame,file,t,class,status`` per frame (FT/FL from the kernel SVM; status ``ok``, ``dark``,
  ``saturated``, ``unreadable``, ``bad_size``);
- ``motion.csv``: per-step motion (SPEC.md columns and the full step, as ``bodyslam motion`` writes it); ``frame``
  is the step's later frame;
- ``trajectory.tum``: fused and smoothed (RF given: :func:`bodyslam.fusion.body_slam.fuse` + RTS) or dead reckoning (the
  first camera frame is the world frame), and ``uncertainty.csv`` (:data:`bodyslam.fusion.localize.UNCERTAINTY_COLUMNS`);
- ``marks.csv`` for marked frames (``--mark``): position, 1-sigma, path travelled from the first frame and from
  each landmark frame, with 1-sigma; with two landmarks or more, the fraction of the way from the first to the
  last by the path (with 1-sigma) and by the time;
- ``summary.json``, ``trajectory.png``, ``path.png`` and ``report.html`` (:func:`_report`). ``OUT/problems.csv`` lists every problem of every exam
  (``exam,file,frame,severity,reason``); ``OUT/summary.json`` gathers the exams.

Frames and time
---------------
Frames of a folder are its image files in the order of the last number in their names (``000123.png``,
``img_0042.jpg``); that number is the frame index and ``t = index / frame_rate``. Missing numbers are reported as
a gap (one problem per gap) and the step across the gap is estimated between the frames on either side. Files
that are not images (by extension) are reported and skipped. A video's frames are numbered from 0; its frame
rate is the container's unless given. An exam can be a stretch of its recording (``frame_range``, ``--frame-range
FIRST-LAST``: the small bowel between two landmark frames, say): only those frames are read, and they keep their
numbers and times (a folder's listing problems outside the stretch are not reported; a video is read from its frame
FIRST on).

Chunks, checkpoints, resuming
-----------------------------
An exam's frames are cut into chunks (by default guided, :func:`guided_chunk_bounds`: big ones first, smaller ones
toward the study's end, so every worker stays busy to it; ``chunk_frames``: equal ones) that overlap by one frame
(chunk ``i`` computes the steps into its frames, so every step belongs to exactly one chunk). A chunk's result is a
small JSON file in ``OUT/<exam>/chunks/``, written atomically; its computation depends only on its own frames, so
results do not depend on the order, the number of workers or where they ran. ``OUT/batch.json`` holds the plan
(inputs, a fingerprint of the files, settings, chunking). Running the same command again resumes: finished chunks are
reused, the rest computed, and the outputs (always rebuilt from the chunk files) are identical to an uninterrupted
run's. A plan that differs from the one in ``OUT`` (other inputs or settings) is refused unless ``force`` (which
clears ``OUT`` first); a non-empty ``OUT`` without a plan is never written into without it.

Memory
------
Workers hold one chunk's frames at a time; the coordinator streams chunk files into the outputs and keeps a few
numbers per frame (pose, covariance and path length for the marks and plots: ~200 bytes per frame). With RF,
fusion and smoothing keep the whole exam's steps and filter passes in memory (~2 kB per frame), on a worker of the
run's pool (:func:`_fuse_task`; in this process with one job or a Dask cluster) while the coordinator writes the
frame and step tables; at most two exams' at once (the next exam's fusion starts while one is finalized).

Gaps, dead reckoning and path length
------------------------------------
An exam's short gaps are bridged as ``bodyslam motion`` bridges them, so both write the same ``motion.csv``: a
gap that lies wholly inside a chunk by that chunk's worker, right after its steps
(:func:`bodyslam.vision.odometry.bridge_inside`: part of the chunk's checkpoint, counted in its progress), the
others (gaps across a seam) once all its chunks are in (:func:`bodyslam.vision.odometry.bridge_gaps`); all of
them are then a checkpoint too, ``bridges.json``. The k-step check of the per-step 1-sigma (``consistency.json``)
then runs on the workers while the coordinator finalizes the exam (the serial end is what limits many workers).
Without RF, steps are accumulated with the fusion's process model (:class:`bodyslam.fusion.body_slam.DeadReckoner`:
a step without an estimate repeats the last estimated one -- a step lost to motion stretched to the estimated steps
so far at their 90th percentile -- with a 1-sigma as large as that step); once the exam is read, those steps are
stretched along their direction to the lengths the path travelled gives them (below), so the trajectory's length is
the path travelled. The path travelled -- the "how far along the gut" figure -- is
:func:`bodyslam.vision.tracking.path_travelled`'s: estimated step lengths, and for a step without an estimate a
length from the speed around it (:func:`bodyslam.vision.tracking.missing_step_lengths`: a model of the capsule's
speed, which a step lost to motion says was beyond the matcher's reach; symmetric in time, so the path does not
depend on the frame order), with the steps' variances summed (a run of missing steps' 1-sigmas added: one speed).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import logging
import math
import os
import re
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from bodyslam.camera import FisheyeCamera, camera_from_dict
from bodyslam.errors import ConfigError, InputError
from bodyslam.frames import SIDECARS, VIDEO_EXTS, FrameSource, collapse_format_notes, list_frames
from bodyslam.io import (MOTION_COLUMNS, atomic_path, csv_rows, motion_row, motion_values, read_json, step_from_row,
                         write_csv, write_image, write_json)
from bodyslam.parallel import available_cores, shared_pool, submit
from bodyslam.vision.odometry import MotionSettings, chunk_bounds, write_mask

log = logging.getLogger(__name__)

__all__ = ["BatchSettings", "Exam", "open_exams", "read_calibration", "run_batch", "BatchReport", "radius_from_summary",
           "parse_frame_list", "read_marks", "process_chunk"]

FRAME_COLUMNS = ["frame", "file", "t", "class", "status"]
PROBLEM_COLUMNS = ["exam", "file", "frame", "severity", "reason"]
PLAN_VERSION = 2
DEFAULT_FOV_DEG = 156.0  # PillCam SB
DEFAULT_RADIUS_M = 0.0125  # small intestine, 2.5 cm lumen diameter (the thesis's testbed: 1.5 cm radius)
# its 1-sigma when assumed: small bowel lumen radius ~0.8-1.6 cm is the assumption +-1.5 sigma (stated choice); the
# fusion carries it as a visual scale state and each step's 1-sigma includes it
DEFAULT_RADIUS_SD_M = 0.0025
# the lumen's departure from the cylinder the tube estimator fits, as a relative 1-sigma of each step's distance,
# when meta.json does not say: the realistic testbed's (chosen on its tuning seeds 503-509: 69% of the radius-free
# step errors inside the fit's 1-sigma with it, 18% without)
DEFAULT_SHAPE_SD_REL = 0.13
DEFAULT_FPS = 2.0
MAX_FRAME_RANGE = 10_000_000  # a frame range (``--mark 100-200``) longer than any exam is a typing error
_SIGMA_D = MOTION_COLUMNS.index("sigma_distance_m")
_DISTANCE, _TX = MOTION_COLUMNS.index("distance_m"), MOTION_COLUMNS.index("tx_m")
_LINK, _CHAIN = MOTION_COLUMNS.index("scale_link"), MOTION_COLUMNS.index("chain_factor")


# -- exams ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BatchSettings:
    """The visual engine's settings (:class:`bodyslam.vision.odometry.MotionSettings`, fast matcher by default) and the
    batch's own: frames per checkpointed chunk and the fusion mode with RF."""

    motion: MotionSettings = MotionSettings(match_mode="fast")
    chunk_frames: int | None = None  # equal chunks of this many frames; None: guided chunks (chunk_workers)
    # guided chunks for this many workers (guided_chunk_bounds); None with chunk_frames None: the run's own workers
    chunk_workers: int | None = None
    fusion: str = "rss"
    rss_bias_states: bool = False  # per-sensor RSS bias states in the fusion (bodyslam.fusion.localize.localize)


# guided chunks (guided_chunk_bounds): each takes this share of the study's remaining frames per worker, so the
# chunks shrink toward the end and every worker stays busy to it. Chosen among 1/2, 1/3 and 1/4 by simulating the
# 10,000-frame `exam`'s measured chunk costs with noise on 2-32 workers (docs/RESULTS.md, session 50): the last
# worker's finish over the ideal, 2 / 8 / 16 / 32 workers, was 2.0 / 6.7 / 9.0 / 11.3% with equal chunks (at least
# 4 a worker, the rule before) and 0.0 / 1.9 / 2.3 / 6.6% with these
GUIDED_SHARE = 1 / 3
CHUNK_FRAMES_RANGE = (20, 500)  # fewer frames is mostly start-up; more loses more work to an interruption


def guided_chunk_bounds(n: int, workers: int, after: int = 0) -> list[tuple[int, int]]:
    """Position ranges ``(a, b)`` of an exam of ``n`` frames cut into chunks overlapping by one frame (as
    :func:`~bodyslam.vision.odometry.chunk_bounds`), each of :data:`GUIDED_SHARE` of the study's frames left
    (this exam's from ``a`` on plus ``after``, the frames of the exams after it) per worker, within
    :data:`CHUNK_FRAMES_RANGE`; a rest shorter than the range's floor joins the last chunk. Guided scheduling: big
    chunks first, small ones last, so ``workers`` workers finish together. Results do not depend on it (tested)."""
    lo, hi = CHUNK_FRAMES_RANGE
    if n <= 1:
        return [(0, max(n - 1, 0))]
    bounds, a = [], 0
    while a < n - 1:
        size = int(min(hi, max(lo, GUIDED_SHARE * (n - 1 - a + after) / max(workers, 1))))
        b = n - 1 if n - 1 - (a + size) < lo else a + size
        bounds.append((a, b))
        a = b
    return bounds


@dataclass
class Exam:
    """One exam to process. ``frames``: ``(index, file name)`` for folders; ``n_frames`` for videos."""

    name: str
    kind: str  # "folder" or "video"
    source: str  # frames folder or video file
    camera: dict
    frame_rate_hz: float
    radius_m: float
    frames: list[tuple[int, str]] = field(default_factory=list, repr=False)
    n_frames: int = 0
    mask: str | None = None  # None or "auto": detected (the image circle where it agrees); "circle"; or a PNG path
    rf: str | None = None
    sensors: str | None = None
    pathloss: dict | None = None
    marks: list[tuple[int, str]] = field(default_factory=list)
    landmarks: list[int] = field(default_factory=list)
    assumed: list[str] = field(default_factory=list)
    camera_assumed: bool = False  # no calibration, no meta.json: DEFAULT_FOV_DEG's lens, centred on the field of view
    problems: list[list] = field(default_factory=list, repr=False)  # found while listing (gaps, non-images)
    radius_sd_m: float = 0.0  # 1-sigma of radius_m: meta.json's, 0 when given, DEFAULT_RADIUS_SD_M when assumed
    shape_sd_rel: float = 0.0  # the lumen's departure from a cylinder: meta.json's, else DEFAULT_SHAPE_SD_REL
    # the stretch of the recording asked for, frame numbers (last None: to the end); None: all of it
    frame_range: tuple[int, int | None] | None = None
    video_start: int = 0  # videos: the frame number of the exam's first frame

    def frame_source(self) -> FrameSource:
        # (while the exam is being opened its frame rate is not known yet: 1 frame/s for the size probe)
        return FrameSource(self.kind, self.source, self.frame_rate_hz or 1.0, self.frames, self.n_frames,
                           start=self.video_start)

    def describe(self) -> dict:
        """What the plan fingerprints: everything that changes results."""
        h = hashlib.sha256()
        if self.kind == "folder":
            for idx, name in self.frames:
                try:
                    size = os.path.getsize(os.path.join(self.source, name))
                except OSError:
                    size = -1
                h.update(f"{idx}\t{name}\t{size}\n".encode())
        else:
            st = os.stat(self.source)
            h.update(f"{st.st_size}".encode())
        return {"name": self.name, "kind": self.kind, "source": os.path.abspath(self.source), "camera": self.camera,
                "frame_rate_hz": self.frame_rate_hz, "radius_m": self.radius_m, "radius_sd_m": self.radius_sd_m,
                "shape_sd_rel": self.shape_sd_rel,
                "n_frames": self.n_positions, "frame_range": self.frame_range, "video_start": self.video_start,
                "mask": self.mask, "rf": self.rf, "sensors": self.sensors, "files_sha256": h.hexdigest()}

    @property
    def radius_sd_rel(self) -> float:
        """The lumen radius's 1-sigma relative to it (the visual scale's)."""
        return self.radius_sd_m / self.radius_m

    @property
    def n_positions(self) -> int:
        return len(self.frames) if self.kind == "folder" else self.n_frames


def read_calibration(path: str | os.PathLike, width: int | None = None, height: int | None = None) -> dict:
    """A camera description (``camera_from_dict`` form) from a calibration file.

    Accepted: JSON in :func:`bodyslam.camera.camera_from_dict` form; JSON with ``cv2.fisheye`` results
    ``{"K": 3x3, "D": [k1..k4], "width", "height"[, "fov_deg"]}``; OpenCV FileStorage YAML/XML with ``K`` (or
    ``camera_matrix``), ``D`` (or ``distortion_coefficients``), ``image_width``, ``image_height``. Without
    ``fov_deg`` the field of view is the largest circle about the principal point inside the image.

    Raises
    ------
    InputError
        Anything wrong with the file, in one line that names it.
    """
    path = Path(path)
    try:
        return _read_calibration(path, width, height)
    except InputError as exc:
        msg = str(exc)
        raise InputError(msg if str(path) in msg else f"{path}: {msg}") from None
    except (ValueError, TypeError, OverflowError, ZeroDivisionError, cv2.error) as exc:  # numbers that make no camera
        raise InputError(f"{path}: not a usable calibration ({str(exc).strip().splitlines()[-1][:120]})") from None


def _read_calibration(path: Path, width: int | None, height: int | None) -> dict:
    if not path.is_file():
        raise InputError(f"{path}: calibration file not found")
    if path.suffix.lower() == ".json":
        d = read_json(path)
        if not isinstance(d, dict):
            raise InputError(f"{path}: calibration must be a JSON object")
        if "model" in d:
            camera_from_dict(d)  # validates, names a missing parameter
            return d
        try:
            K = np.asarray(d["K"], float).reshape(3, 3)
            D = np.asarray(d.get("D", [0, 0, 0, 0]), float).reshape(-1)
            w, h = int(d.get("width", width or 0)), int(d.get("height", height or 0))
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"{path}: calibration needs K (3x3), D (4) and width/height ({exc})") from None
        fov = d.get("fov_deg")
    else:
        try:  # OpenCV's parser raises cv2.error or SystemError on text it cannot parse
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            opened = fs.isOpened()
        except (cv2.error, SystemError) as exc:
            # a SystemError wraps the parser's cv2.error ("... returned a result with an exception set"): name that one
            cause = exc if isinstance(exc, cv2.error) else (exc.__cause__ or exc.__context__ or exc)
            why = str(cause).strip().splitlines()[-1]
            why = why.split(" error: ", 1)[-1]  # OpenCV's source path and line are not the user's business
            raise InputError(f"{path}: not a readable OpenCV calibration file (YAML/XML): {why[:120]}") from None
        if not opened:
            raise InputError(f"{path}: not a readable OpenCV calibration file (YAML/XML)")

        def node(*names):
            for n in names:
                v = fs.getNode(n)
                if not v.empty():
                    return v
            return None

        def mat(n):  # a matrix node's values, or None (a scalar or a map is not one)
            return np.asarray(n.mat(), float) if (n is not None and n.isMap() and n.mat() is not None) else None

        try:
            kn, dn = node("K", "camera_matrix"), node("D", "distortion_coefficients")
            K, D = mat(kn), mat(dn)
            if K is None or K.size != 9:
                raise InputError(f"{path}: no K / camera_matrix (3x3 matrix) in the calibration file")
            K = K.reshape(3, 3)
            D = D.reshape(-1) if D is not None else np.zeros(4)
            wn, hn = node("image_width", "width"), node("image_height", "height")
            w = int(wn.real()) if wn is not None else int(width or 0)
            h = int(hn.real()) if hn is not None else int(height or 0)
            fn = node("fov_deg")
            fov = fn.real() if fn is not None else None
        except cv2.error as exc:
            raise InputError(f"{path}: calibration file is not in the expected form ({str(exc).strip()[-80:]})") from None
        finally:
            fs.release()
    if w <= 0 or h <= 0:
        raise InputError(f"{path}: calibration gives no image size (width/height)")
    if len(D) != 4:
        raise InputError(f"{path}: D must have 4 cv2.fisheye coefficients, got {len(D)}")
    cam = {"model": "opencv_fisheye", "width": w, "height": h, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
           "cy": K[1, 2], "k": [float(x) for x in D]}
    if fov is None:
        r = min(K[0, 2], K[1, 2], w - 1 - K[0, 2], h - 1 - K[1, 2])
        probe = FisheyeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], 179.0, tuple(D))
        ray, _ = probe.unproject(np.array([[K[0, 2] + r, K[1, 2]]]))
        fov = 2 * math.degrees(math.acos(float(np.clip(ray[0, 2], -1, 1))))
    cam["fov_deg"] = float(fov)
    camera_from_dict(cam)
    return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in cam.items()}


def parse_frame_list(text: str) -> list[int]:
    """``"120,455,1000-1002"`` -> ``[120, 455, 1000, 1001, 1002]``."""
    out = []
    for part in str(text).replace(";", ",").split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                if not 0 <= int(b) - int(a) < MAX_FRAME_RANGE:
                    raise InputError(f"frame range {part!r} is empty or longer than {MAX_FRAME_RANGE} frames")
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise InputError(f"not a frame number or range: {part!r}") from None
    return out


def parse_frame_range(text: str) -> tuple[int, int | None]:
    """``"1200-48000"`` -> ``(1200, 48000)`` (frame numbers, both kept); ``"1200-"`` -> ``(1200, None)``: to the
    end."""
    m = re.fullmatch(r"\s*(\d+)\s*-\s*(\d*)\s*", str(text))
    if m is None:
        raise InputError(f"frame range {text!r}: give FIRST-LAST (frame numbers, both kept; e.g. 1200-48000) or "
                         f"FIRST- (from FIRST to the end)")
    first, last = int(m.group(1)), (int(m.group(2)) if m.group(2) else None)
    if last is not None and last <= first:
        raise InputError(f"frame range {text!r}: LAST must be after FIRST (an exam needs two frames for a step)")
    return first, last


def _range_text(r: tuple[int, int | None]) -> str:
    return f"{r[0]}-{'' if r[1] is None else r[1]}"


def read_marks(path: str | os.PathLike, exams: list[Exam]) -> None:
    """Add the marked frames of a CSV (``frame[,label][,exam]``) to the exams (all exams when no ``exam``).

    Raises
    ------
    InputError
        A malformed line or an unknown exam (file and line are named).
    """

    by_name = {e.name: e for e in exams}
    with csv_rows(path, ("frame",)) as lines:
        for lineno, row in lines:
            try:
                f = int(str(row["frame"]).strip())
            except (TypeError, ValueError):
                raise InputError(f"{path}:{lineno}: frame {row.get('frame')!r} is not a frame number") from None
            name = (row.get("exam") or "").strip()
            if name and name not in by_name:
                raise InputError(f"{path}:{lineno}: unknown exam {name!r} (exams: {', '.join(by_name)})")
            for e in ([by_name[name]] if name else exams):
                e.marks.append((f, (row.get("label") or "").strip()))


def _unique_name(name: str, taken: set[str]) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "exam"
    out, i = name, 2
    while out in taken:
        out, i = f"{name}_{i}", i + 1
    taken.add(out)
    return out


def radius_from_summary(path: str | os.PathLike) -> tuple[float, float | None]:
    """The lumen radius (m) an earlier `bodyslam batch` run measured for its exam, and its 1-sigma (m; None in a
    summary written before session 63, which states none): the ``effective_radius_m`` and ``effective_radius_sd_m``
    of its lumen scale (:func:`bodyslam.vision.lumen_scale.lumen_scale_summary`), for a clip cut from that exam, too
    short to measure its own (``--radius-from``; docs/RESULTS.md, "Short clips: ... their scale", session 61:
    18-frame clips of the realistic testbed at a real exam's pace read +45% with the radius prior, +9% with their
    exam's radius).
    ``path``: the exam's ``summary.json``, the study's (one exam), or the directory holding either.

    Raises
    ------
    InputError
        The file is missing or not such a summary, holds several exams, or its lumen scale was not applied."""
    p = Path(path)
    if p.is_dir():
        p = p / "summary.json"
    d = read_json(p)
    if isinstance(d, dict) and isinstance(d.get("exams"), list):  # the study's summary
        if len(d["exams"]) != 1:
            raise InputError(f"{p}: a study of {len(d['exams'])} exams; give the exam's own summary.json "
                             "(OUT/<exam>/summary.json)")
        d = d["exams"][0]
    if not isinstance(d, dict) or "lumen_scale" not in d:
        raise InputError(f"{p}: not a bodyslam batch summary (no lumen_scale)")
    sc = d["lumen_scale"]
    if not isinstance(sc, dict) or not sc.get("applied"):
        why = "not measured" if not isinstance(sc, dict) else f"not applied: {sc.get('samples')} ring(s) seen"
        raise InputError(f"{p}: that exam's lumen scale was {why}, so it has no radius of its own to give; "
                         "give --radius-m instead")
    r = sc.get("effective_radius_m")
    if not (isinstance(r, (int, float)) and math.isfinite(r) and r > 0):
        raise InputError(f"{p}: lumen_scale.effective_radius_m is not a positive number of metres: {r!r}")
    sd = sc.get("effective_radius_sd_m")
    if sd is not None and not (isinstance(sd, (int, float)) and math.isfinite(sd) and 0 <= sd < r):
        raise InputError(f"{p}: lumen_scale.effective_radius_sd_m is not a 1-sigma in metres below the radius: {sd!r}")
    return float(r), (None if sd is None else float(sd))


def open_exams(inputs: list[str], calib: str | None = None, fps: float | None = None,
               radius_m: float | None = None, mask: str | None = None, rf: str | None = None,
               sensors: str | None = None, marks: list[tuple[int, str]] | None = None,
               landmarks: list[int] | None = None, problems: list | None = None,
               frame_range: tuple[int, int | None] | None = None, radius_sd_m: float | None = None) -> list[Exam]:
    """Exams from command-line inputs: frame folders, sequence directories, videos, manifests (CSV/JSON).

    A manifest lists one exam per row (CSV with a header) or object (JSON list): ``input`` and optionally
    ``name, calib, fps, radius_m, mask, rf, sensors, marks, landmarks, frame_range`` (frame lists as
    ``"120;455"``, the range as ``"1200-48000"``: :func:`parse_frame_range`); relative paths are relative to the
    manifest. Command-line options are defaults for every exam. ``radius_sd_m``: the 1-sigma of ``radius_m`` (None or
    0: the radius given is taken as known; a manifest row's own radius always is).

    ``problems``: in a study (several inputs or manifest rows), an exam that cannot be opened is listed there as
    ``[source, "", "error", reason]`` and the others go on (the study then exits 3); without it, or when no exam
    of the study can be opened, the first such error is raised.

    Raises
    ------
    InputError
        An input that is none of these, or unusable as a whole (no frames, unreadable video) -- one clear line.
    """
    exams: list[Exam] = []
    taken: set[str] = set()
    failed: list[InputError] = []

    def add(make, source) -> None:
        try:
            exams.append(make())
        except InputError as exc:
            if problems is None:
                raise
            failed.append(exc)
            problems.append([str(source), "", "error", f"exam not processed: {exc}"])

    base = {"calib": calib, "fps": fps, "radius_m": radius_m, "mask": mask, "rf": rf, "sensors": sensors,
            "marks": marks or [], "landmarks": landmarks or [], "frame_range": frame_range,
            "radius_sd_m": radius_sd_m if radius_m is not None else None}
    for inp in inputs:
        p = Path(inp)
        if p.is_file() and p.suffix.lower() in (".csv", ".json") and p.name not in SIDECARS:
            for loc, row in _read_manifest(p):
                add(lambda: _manifest_exam(p, loc, row, base, taken), p)  # its message names the row
        else:
            add(lambda: _open_exam(p, p.stem if p.is_file() else p.name, taken, **base), p)
    if failed and not exams:
        raise failed[0]
    if not exams:
        raise InputError("no exams to process")
    return exams


def _manifest_exam(p: Path, loc: str, row: dict, base: dict, taken: set[str]) -> Exam:
    """The exam of one manifest row; any error names the manifest and the row (``p:loc``) on one line."""
    try:
        if "\x00" in "".join(str(v) for v in row.values()):
            raise InputError("a field holds a NUL byte")
        opts = dict(base)
        for k in ("calib", "mask", "rf", "sensors"):
            if row.get(k):
                opts[k] = str((p.parent / row[k]).resolve()) if row[k] != "auto" else "auto"
        for k in ("fps", "radius_m"):
            if row.get(k) not in (None, ""):
                try:
                    opts[k] = float(row[k])
                except ValueError:
                    raise InputError(f"{k} {row[k]!r} is not a number") from None
                if k == "radius_m":
                    opts["radius_sd_m"] = None  # the row's own radius, taken as known
        if row.get("marks"):
            opts["marks"] = [(f, "") for f in parse_frame_list(row["marks"])]
        if row.get("landmarks"):
            opts["landmarks"] = parse_frame_list(row["landmarks"])
        if row.get("frame_range"):
            opts["frame_range"] = parse_frame_range(row["frame_range"])
        src = (p.parent / row["input"]).resolve()
        return _open_exam(src, row.get("name") or src.stem, taken, **opts)
    except InputError as exc:
        msg = str(exc).replace("\n", "\\n").replace("\r", "\\r")
        raise InputError(f"{p}:{loc}: {msg}") from None


def _read_manifest(path: Path) -> list[tuple[str, dict]]:
    """``(where, row)``: ``where`` is the CSV line (or JSON item) for messages."""
    if path.suffix.lower() == ".json":
        rows = read_json(path)
        if not isinstance(rows, list) or not all(isinstance(r, dict) and isinstance(r.get("input"), str)
                                                 for r in rows):
            raise InputError(f"{path}: a JSON manifest is a list of objects with an 'input' path each")
        return [(f"item {i}", {str(k): ("" if v is None else (";".join(map(str, v)) if isinstance(v, list) else str(v)))
                               for k, v in r.items()}) for i, r in enumerate(rows, start=1)]
    with csv_rows(path, ()) as lines:
        rows = []
        for lineno, row in lines:
            if None in row:  # more fields than the header has
                raise InputError(f"{path}:{lineno}: {len(row) - 1 + len(row[None])} fields, the header has "
                                 f"{len(row) - 1}")
            rows.append((f"line {lineno}", row))
        fields = list(rows[0][1]) if rows else []
    if rows and "input" not in fields:
        raise InputError(f"{path}: not a manifest (no 'input' column; header is {fields})")
    rows = [(loc, r) for loc, r in rows if r.get("input")]
    if not rows:
        raise InputError(f"{path}: manifest lists no exams (an 'input' column, one exam per row)")
    return rows


def _open_exam(src: Path, name: str, taken: set[str], calib, fps, radius_m, mask, rf, sensors, marks,
               landmarks, frame_range=None, radius_sd_m=None) -> Exam:
    from bodyslam.meta import read_meta

    assumed: list[str] = []
    meta = None  # a sequence directory's validated meta.json (bodyslam.meta)
    if src.is_dir():
        kind = "folder"
        frames_dir = src
        if (src / "meta.json").is_file():
            meta = read_meta(src)
            frames_dir = src / meta.frames_dir
            if not frames_dir.is_dir():
                raise InputError(f"{frames_dir}: frames directory not found")
        frames, problems = list_frames(frames_dir)
        if not frames:
            raise InputError(f"{src}: no image files found (looked in {frames_dir})")
        n_meta = meta.n_frames if meta else None
        if frame_range is not None:
            frames, problems = _folder_range(src, frames, problems, frame_range)
        last_wanted = None if n_meta is None else n_meta - 1
        if last_wanted is not None and frame_range is not None and frame_range[1] is not None:
            last_wanted = min(last_wanted, frame_range[1])
        if last_wanted is not None and frames[-1][0] < last_wanted:
            a = frames[-1][0] + 1
            problems.append([str(frames_dir), a, "warning", f"frames {a}-{last_wanted} missing at the end "
                                                             f"(meta.json says {n_meta})"])
        exam = Exam(name, kind, str(frames_dir), {}, 0.0, 0.0, frames=frames, problems=problems)
    elif src.is_file() and src.suffix.lower() in VIDEO_EXTS:
        cap = cv2.VideoCapture(str(src))
        if not cap.isOpened():
            raise InputError(f"{src}: cannot open the video (unsupported codec or not a video)")
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        vfps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        ok, _ = cap.read()
        cap.release()
        if not ok:
            raise InputError(f"{src}: the video has no decodable frame")
        if n <= 0:  # container without a frame count: count by decoding
            cap = cv2.VideoCapture(str(src))
            n = 0
            while cap.grab():
                n += 1
            cap.release()
        first, last = frame_range or (0, None)
        if first >= n - 1:
            raise InputError(f"{src}: frame range {_range_text(frame_range)} starts at or past the video's last "
                             f"frame ({n} frames by its container, numbered 0-{n - 1})")
        n_in = (n if last is None else min(n, last + 1)) - first
        exam = Exam(name, "video", str(src), {}, 0.0, 0.0, n_frames=n_in, video_start=first)
        if fps is None and vfps > 0:
            fps = vfps
    elif src.exists():
        raise InputError(f"{src}: not a frame folder, a video ({', '.join(VIDEO_EXTS)}) or a manifest (.csv/.json)")
    else:
        raise InputError(f"{src}: no such file or directory")
    exam.name = _unique_name(name, taken)
    # camera: calibration file > meta.json > default (assumed)
    if calib:
        exam.camera = read_calibration(calib)
    elif meta is not None:
        exam.camera = meta.camera
    else:
        size = exam.frame_source().first_size()
        if size is None:
            raise InputError(f"{src}: no readable frame to take the image size from")
        exam.camera = {"model": "equidistant", "width": size[0], "height": size[1], "fov_deg": DEFAULT_FOV_DEG}
        exam.camera_assumed = True
        assumed.append(f"camera: equidistant fisheye {DEFAULT_FOV_DEG:g} deg at {size[0]}x{size[1]} (no calibration)")
    camera_from_dict(exam.camera)
    exam.frame_rate_hz = _given_or_assumed(src, "frame rate", fps, meta.frame_rate_hz if meta else None,
                                           DEFAULT_FPS, f"{DEFAULT_FPS:g} frames/s", assumed)
    exam.radius_m = _given_or_assumed(src, "lumen radius (m)", radius_m, meta.tube_radius_m if meta else None,
                                      DEFAULT_RADIUS_M, f"{DEFAULT_RADIUS_M * 100:g} +- {DEFAULT_RADIUS_SD_M * 100:g} "
                                      f"cm (distances scale with it)", assumed)
    if radius_m is not None:
        # given: taken as known, or with the 1-sigma given beside it (--radius-from: the measuring exam's)
        exam.radius_sd_m = float(radius_sd_m) if radius_sd_m else 0.0
    elif meta is not None and meta.tube_radius_m is not None:
        exam.radius_sd_m = meta.tube_radius_sd_m
    else:
        exam.radius_sd_m = DEFAULT_RADIUS_SD_M
    if meta is not None:
        exam.shape_sd_rel = meta.lumen_shape_sd_rel
    else:
        exam.shape_sd_rel = DEFAULT_SHAPE_SD_REL
        assumed.append(f"lumen shape {DEFAULT_SHAPE_SD_REL:.0%} of each step (1-sigma: the lumen is not a cylinder)")
    exam.mask = mask
    rf_meta = meta.rf if meta is not None else None
    if rf is None and sensors is None and src.is_dir() and rf_meta:
        cand_rf, cand_s = src / rf_meta.file, src / rf_meta.sensors
        if cand_rf.is_file() and cand_s.is_file():
            rf, sensors = str(cand_rf), str(cand_s)
        else:  # meta.json says the exam has RF: a missing file is said, not passed over in silence
            missing = [str(f) for f in (cand_rf, cand_s) if not f.is_file()]
            exam.problems.append([missing[0], "", "warning", f"RF not used (dead reckoning): {' and '.join(missing)} "
                                                             "named by meta.json not found"])
    if (rf is None) != (sensors is None):
        raise InputError(f"{src}: RF fusion needs both an rf.csv and a sensors.csv")
    exam.rf, exam.sensors = rf, sensors
    exam.pathloss = rf_meta.pathloss if (rf and rf_meta) else None
    exam.marks = list(marks)
    exam.landmarks = list(landmarks)
    exam.assumed = assumed
    exam.frame_range = frame_range
    return exam


def _folder_range(src: Path, frames: list[tuple[int, str]], problems: list[list],
                  frame_range: tuple[int, int | None]) -> tuple[list[tuple[int, str]], list[list]]:
    """A folder's frames and listing problems inside ``frame_range`` (problems without a frame number are kept)."""
    first, last = frame_range
    last = frames[-1][0] if last is None else last
    inside = [f for f in frames if first <= f[0] <= last]
    if len(inside) < 2:
        raise InputError(f"{src}: frame range {_range_text(frame_range)} holds {len(inside)} frame(s) (the folder's "
                         f"frames are numbered {frames[0][0]}-{frames[-1][0]}); an exam needs at least 2")
    return inside, [p for p in problems if not isinstance(p[1], int) or first <= p[1] <= last]


def _given_or_assumed(src, what: str, given, from_meta, default: float, default_text: str, assumed: list) -> float:
    """An option's value: given > meta.json > the default (listed in ``assumed``); a positive number."""
    v = given if given is not None else from_meta
    if v is None:
        v = default
        assumed.append(f"{what.split(' (')[0]} {default_text}")
    if not (isinstance(v, (int, float)) and math.isfinite(float(v)) and float(v) > 0):
        raise InputError(f"{src}: {what} must be a positive number, got {v}")
    return float(v)


# -- per chunk (workers) ----------------------------------------------------------------------------------------
def process_chunk(task: dict) -> dict:
    """Positions ``first..last`` of one exam through the visual engine (:mod:`bodyslam.vision.odometry`): class and
    status per frame, the motion of every step into them. Pure and deterministic (the result depends only on
    the frames and settings), so chunks can run anywhere, in any order. Returns a JSON-serialisable dict, which
    is the chunk's checkpoint file."""
    from bodyslam.vision.odometry import bridge_inside, chunk_task

    res = chunk_task(task)  # its run matched the ends of each gap inside the chunk as the gap closed
    # the gaps inside the chunk, bridged here (the rest once all chunks are in: _bridge_exam)
    gaps, shares = bridge_inside([s for *_, s in res.steps], task["first"], task["settings"], task["radius_m"],
                                 res.gap_totals)
    return {"exam": task["exam"], "chunk": task["chunk"], "first": task["first"], "last": task["last"],
            "frames": res.frames, "steps": [motion_row(idx, t, s) for _, idx, t, s in res.steps],
            "problems": res.problems, "eof": res.eof,
            # the gaps inside it, as positions (a, b), and their bridged shares by step item (as bridges.json)
            "gaps": [list(g) for g in gaps],
            "bridged": {str(i): motion_row(0, 0.0, sh) for i, sh in sorted(shares.items())},
            # the points of the first and last steps, for the seams' scale links (bodyslam.vision.scale_chain)
            "seam_in": res.seam_in.to_json() if res.seam_in is not None else None,
            "seam_out": res.seam_out.to_json() if res.seam_out is not None else None}


# -- the run ----------------------------------------------------------------------------------------------------
@dataclass
class BatchReport:
    out: Path
    exams: list[dict]
    n_problems: int
    n_errors: int
    chunks_computed: int
    chunks_reused: int


def code_fingerprint() -> str:
    """A hash of the pipeline's code (Python and C sources) and shipped models: chunks are reused only by the code
    that computed them (an upgraded toolkit with the same settings could compute different results; without this
    a resumed run would mix both)."""
    import hashlib

    root = Path(__file__).resolve().parents[1]  # the bodyslam package
    h = hashlib.sha256()
    for f in sorted([*root.rglob("*.py"), *root.rglob("*.c"), *root.rglob("models/*")]):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _prepare_out(out: Path, plan: dict, force: bool) -> None:
    plan_file = out / "batch.json"
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        old = None
        if plan_file.is_file():
            try:
                old = read_json(plan_file).get("plan")
            except (InputError, AttributeError):
                old = None
        if old == json.loads(json.dumps(plan)):
            log.info("%s: resuming (same inputs and settings)", out)
            return
        if not force:
            why = ("it holds a run with other inputs or settings, or made by another version of the toolkit"
                   if old is not None else "it is not empty and holds no batch run")
            raise InputError(f"{out}: {why}; use --force to overwrite (the same command resumes its own run)")
        for child in out.iterdir():
            if child.is_dir() and not child.is_symlink():
                shutil.rmtree(child)
            else:
                child.unlink()
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json(plan_file, {"plan": plan, "format": "bodyslam-batch/1"})
    except OSError as exc:
        raise InputError(f"{out}: cannot create the output directory ({exc.strerror or exc})") from None


def _mask_for(exam: Exam) -> np.ndarray | None:
    """The exam's field of view (None: the image circle): ``exam.mask`` None or "auto" detects it. An assumed
    lens is then centred on a detected field that is off the frame's centre or small in it
    (:func:`bodyslam.camera.equidistant_on_field`): ``exam.camera`` and its ``assumed`` line say so."""
    from bodyslam.camera import equidistant_on_field
    from bodyslam.vision.odometry import resolve_mask

    mask = resolve_mask(exam.frame_source(), camera_from_dict(exam.camera), exam.mask)
    cam = equidistant_on_field(mask, DEFAULT_FOV_DEG) if exam.camera_assumed and mask is not None else None
    if cam is not None:
        exam.camera = cam.to_dict()
        diameter = cam.fx * math.radians(cam.fov_deg)  # the image circle's, pixels
        exam.assumed = [(f"camera: equidistant fisheye {cam.fov_deg:g} deg across the detected field of view, "
                         f"centred at ({cam.cx:g}, {cam.cy:g}), {diameter:.0f} px wide, in {cam.width}x{cam.height} "
                         "frames (no calibration)") if a.startswith("camera:") else a for a in exam.assumed]
        log.info("%s: %s", exam.name, next(a for a in exam.assumed if a.startswith("camera:")))
    return mask


def _run_tasks(func, tasks: list[dict], jobs: int | None, scheduler: str | None, ordered: bool = False) -> Iterator:
    """``func(task)`` for every task: on a Dask cluster (``scheduler``) or local worker processes; as they
    finish (any order) unless ``ordered``."""
    if not tasks:
        return
    if scheduler:
        try:
            from distributed import Client, as_completed
        except ImportError:
            raise ConfigError("--scheduler needs Dask distributed (pip install 'dask[distributed]')") from None
        try:
            client = Client(scheduler, timeout=30)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        try:
            futures = client.map(func, tasks, pure=False)
            if ordered:
                for fut in futures:
                    yield fut.result()
            else:
                for fut in as_completed(futures):
                    yield fut.result()
        finally:
            client.close()
        return
    from bodyslam.parallel import imap_tasks

    yield from imap_tasks(func, tasks, jobs, ordered=ordered)


def run_batch(exams: list[Exam], out: str | os.PathLike, settings: BatchSettings = BatchSettings(),
              jobs: int | None = None, scheduler: str | None = None, force: bool = False,
              progress: Callable[[int, int], None] | None = None, problems: list | None = None,
              stage: Callable[[str], None] | None = None) -> BatchReport:
    """Process every exam into ``out`` (module docstring): resumable, streaming, parallel. ``problems``: the
    study's own (exams that could not be opened, :func:`open_exams`), listed first in ``problems.csv``; an exam
    whose field of view cannot be set up is listed there too and left out, the others go on. ``progress``: called
    with the frames done and in all as chunks finish; ``stage``: with a line per exam as each step after the
    chunks starts (on a 55,000-frame exam with RF they take ~40 s, after the progress has reached its end)."""
    out = Path(out)
    plan = {"version": PLAN_VERSION, "code": code_fingerprint(), "settings": asdict(settings),
            "exams": [e.describe() for e in exams]}
    if settings.chunk_frames is None and settings.chunk_workers is None:
        settings = replace(settings, **_chunking_for(out, plan, exams, jobs))
        plan["settings"] = asdict(settings)  # the plan records the chunking used
    if settings.chunk_frames is not None and settings.chunk_frames < 2:
        raise ConfigError(f"chunk_frames must be >= 2, got {settings.chunk_frames}")
    if settings.chunk_frames is None and not (settings.chunk_workers or 0) >= 1:
        raise ConfigError(f"chunk_workers must be >= 1, got {settings.chunk_workers}")
    _prepare_out(out, plan, force)
    t0 = time.monotonic()
    tasks, reused, total = [], 0, sum(e.n_positions for e in exams)
    ended: dict[str, int] = {}  # exam -> the position its video ended at, where it ended before its stated count
    done_frames = 0
    masks = {}
    study_problems = [["", *p] for p in (problems or [])]
    usable = []
    after = total  # the study's frames from each exam's start on (guided chunks shrink toward the study's end)
    for e in exams:
        after -= e.n_positions
        try:
            mask = _mask_for(e)
        except InputError as exc:
            if len(exams) == 1:
                raise
            study_problems.append([e.name, e.source, "", "error", f"exam not processed: {exc}"])
            continue
        usable.append(e)
        masks[e.name] = mask
        (out / e.name / "chunks").mkdir(parents=True, exist_ok=True)
        write_mask(out / e.name / "mask.png", mask, camera_from_dict(e.camera))  # the field of view used
        src = e.frame_source()
        bounds = (chunk_bounds(e.n_positions, settings.chunk_frames) if settings.chunk_frames is not None
                  else guided_chunk_bounds(e.n_positions, settings.chunk_workers, after))
        for i, (a, b) in enumerate(bounds):
            f = out / e.name / "chunks" / f"chunk_{i:06d}.json"
            old = _valid_chunk(f, i, a, b)
            if old is not None:
                reused += 1
                done_frames += b - a + (a == 0)
                _note_end(ended, e.name, old.get("eof"))
                continue
            tasks.append({"exam": e.name, "chunk": i, "first": a, "last": b, "source": src.subset(a, b),
                          "camera": e.camera, "radius_m": e.radius_m, "settings": settings.motion, "mask": mask,
                          "ring_every": _ring_every(e, settings), "bridge_inside": True})
    if not usable:
        raise InputError(f"no exam of the study could be processed: {study_problems[-1][-1]}")
    if reused:
        log.info("%d chunk(s) reused from an earlier run", reused)
    if progress:
        progress(done_frames, total)
    by_key = {(t["exam"], t["chunk"]): t for t in tasks}
    exams = usable
    # one pool of local workers for the chunks, the gap bridges and the k-step check (not for a Dask cluster)
    phases: dict[str, float] = {}  # seconds from the start at the end of each phase (summary.json)
    with contextlib.nullcontext() if scheduler else shared_pool(jobs):
        for res in _run_tasks(process_chunk, tasks, jobs, scheduler):
            phases.setdefault("first_chunk", round(time.monotonic() - t0, 3))  # workers started + one chunk
            task = by_key[(res["exam"], res["chunk"])]
            # the JSON text of a result is the checkpoint; it is read back the same way on resume
            path = out / task["exam"] / "chunks" / f"chunk_{task['chunk']:06d}.json"
            with atomic_path(path) as tmp:
                tmp.write_text(json.dumps(res), encoding="utf-8")
            done_frames += task["last"] - task["first"] + (task["first"] == 0)
            _note_end(ended, task["exam"], res.get("eof"))
            if progress:
                progress(done_frames, total)
        phases["chunks"] = round(time.monotonic() - t0, 3)
        for e in exams:
            if stage:
                stage(f"{e.name}: bridging gaps between estimated steps")
            _bridge_exam(e, out / e.name, settings, masks[e.name], jobs, scheduler)
            _lumen_scale_exam(e, out / e.name, settings)
        phases["bridges"] = round(time.monotonic() - t0, 3)
        # the k-step checks of the per-step 1-sigma run on the workers while this process finalizes each exam: they
        # add one entry to its summary, and the serial end is what limits many workers (docs/RESULTS.md, session 32)
        # an exam's fusion with RF runs on a worker while this process writes its frame and step tables, and the
        # next exam's starts while this one is finalized (at most two at once: each holds its exam's filter passes)
        fusions: dict[int, Callable[[], dict]] = {}

        def start_fusion(i: int) -> None:
            if i < len(exams) and exams[i].rf:
                task = {"exam": exams[i], "dir": str(out / exams[i].name), "settings": settings}
                fusions[i] = ((lambda task=task: _fuse_task(task)) if scheduler  # the coordinator's disk
                              else submit(_fuse_task, task, jobs))

        start_fusion(0)
        checked = _in_background([lambda e=e: _consistency_exam(e, out / e.name, settings, masks[e.name], jobs,
                                                                scheduler) for e in exams],
                                 thread=bool(scheduler) or (jobs or available_cores()) > 1)
        summaries, all_problems = [], list(study_problems)
        for i, e in enumerate(exams):
            start_fusion(i + 1)
            if stage:
                stage(f"{e.name}: {'fusing vision with RF' if e.rf else 'dead reckoning'} over "
                      f"{ended.get(e.name, e.n_positions)} frames, writing the trajectory, marks and report (the "
                      "per-step 1-sigma checked meanwhile)")
            s, probs = _finalize(e, out / e.name, settings, wait_check=lambda i=i: checked(i),
                                 fusion=fusions.pop(i, None), jobs=None if scheduler else jobs)
            summaries.append(s)
            all_problems.extend([e.name, *p] for p in probs)
    write_csv(out / "problems.csv", PROBLEM_COLUMNS, all_problems)
    n_err = sum(p[3] == "error" for p in all_problems)
    elapsed = time.monotonic() - t0
    write_json(out / "summary.json", {"exams": summaries, "n_problems": len(all_problems), "n_errors": n_err,
                                      "chunks_computed": len(tasks), "chunks_reused": reused,
                                      "seconds": round(elapsed, 3),
                                      # when each phase ended (s from the start): the first chunk's result, the
                                      # last chunk's, the gaps bridged, every exam's outputs written
                                      "phases_end_s": {**phases, "exams": round(elapsed, 3)}})
    return BatchReport(out, summaries, len(all_problems), n_err, len(tasks), reused)


def _in_background(calls: list[Callable[[], None]], thread: bool = True) -> Callable[[int], None]:
    """Run ``calls`` one after another on a thread; returns ``wait(i)``, which blocks until call ``i`` has
    finished and raises what it raised. The calls hand their work to the worker pool (or a Dask cluster) and wait
    for it, so the thread holds the interpreter little while this process goes on. ``thread`` False (one job:
    the work would run in this process, on a second core): each call runs when it is waited for."""
    done = [threading.Event() for _ in calls]
    errors: list[BaseException | None] = [None] * len(calls)
    if not thread:
        def wait_here(i: int) -> None:
            calls[i]()

        return wait_here

    def run() -> None:
        for i, call in enumerate(calls):
            try:
                call()
            except BaseException as exc:  # raised again by wait(i), in the caller's thread
                errors[i] = exc
            finally:
                done[i].set()

    threading.Thread(target=run, name="bodyslam-batch-checks", daemon=True).start()

    def wait(i: int) -> None:
        done[i].wait()
        if errors[i] is not None:
            raise errors[i]

    return wait


def _chunking_for(out: Path, plan: dict, exams: list[Exam], jobs: int | None) -> dict:
    """The automatic chunking for ``plan`` (whose chunking is not chosen yet), as ``BatchSettings`` fields: the one
    of the run already in ``out`` when everything else matches (a resumed run keeps its chunks whatever ``--jobs``
    it is resumed with), else guided chunks (:func:`guided_chunk_bounds`) for the workers (``jobs``, default one per
    core)."""

    def unsized(pl: dict) -> dict:
        return dict(pl, settings=dict(pl["settings"], chunk_frames=None, chunk_workers=None))

    try:
        old = read_json(out / "batch.json")["plan"]
        size, workers = old["settings"]["chunk_frames"], old["settings"]["chunk_workers"]
        if unsized(old) == json.loads(json.dumps(unsized(plan))):
            if isinstance(size, int) and size >= 2 and workers is None:
                return {"chunk_frames": size, "chunk_workers": None}
            if size is None and isinstance(workers, int) and workers >= 1:
                return {"chunk_frames": None, "chunk_workers": workers}
    except (InputError, KeyError, TypeError, AttributeError):
        pass
    return {"chunk_frames": None, "chunk_workers": int(jobs or available_cores())}


def _note_end(ended: dict, name: str, eof) -> None:
    """Keep in ``ended`` the earliest position at which an exam's video ended (a chunk's ``eof``; None: it did not):
    the frames read, where the container's count (``Exam.n_positions``) was an estimate."""
    if eof is not None:
        ended[name] = min(int(eof), ended.get(name, int(eof)))


def _valid_chunk(path: Path, i: int, first: int, last: int) -> dict | None:
    """A chunk file of an earlier run that holds chunk ``i`` of ``first..last``, read; None where it does not."""
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    ok = isinstance(d, dict) and d.get("chunk") == i and d.get("first") == first and d.get("last") == last
    return d if ok and "steps" in d else None


def _iter_chunks(exam_dir: Path) -> Iterator[dict]:
    for f in sorted((exam_dir / "chunks").glob("chunk_*.json")):
        yield json.loads(f.read_text(encoding="utf-8"))


def _checkpoint(f: Path, key: str) -> dict | None:
    """An exam-level checkpoint written whole (``{key: value}``), or None when it is missing or unreadable (then
    its step runs again)."""
    try:
        d = json.loads(f.read_text(encoding="utf-8"))
        return d if isinstance(d, dict) and key in d else None
    except (OSError, ValueError):
        return None


def _step_rows(d: Path) -> Iterator[list]:
    """The exam's step rows (``motion_row``s) from its chunk files, in order, up to the end of a video."""
    for ch in _iter_chunks(d):
        yield from ch["steps"]
        if ch["eof"] is not None:
            break


def _engine_base(exam: Exam, settings: BatchSettings, mask) -> dict:
    """The visual engine's task fields for the exam (what a worker needs besides positions)."""
    return {"source": exam.frame_source(), "camera": exam.camera, "settings": settings.motion,
            "radius_m": exam.radius_m, "mask": mask}


def _bridge_exam(exam: Exam, d: Path, settings: BatchSettings, mask, jobs, scheduler) -> None:
    """Bridge the exam's gaps (:func:`bodyslam.vision.odometry.bridge_gaps`, the rule ``bodyslam motion`` follows)
    once all its chunks are done: those across a seam here, those inside a chunk taken from its file (bridged by
    its worker, :func:`process_chunk`); the result is a checkpoint too (``bridges.json``: ``{step item: row}``)."""
    from bodyslam.vision.odometry import bridge_gaps
    from bodyslam.steps import StepStatus

    f = d / "bridges.json"
    if _checkpoint(f, "bridged") is not None:
        return
    statuses, done, rows = [], [], {}
    for ch in _iter_chunks(d):  # (as _step_rows: up to the end of a video)
        statuses.extend(StepStatus(row[8]) for row in ch["steps"])
        done.extend(tuple(g) for g in ch.get("gaps", ()))
        rows.update(ch.get("bridged", {}))
        if ch["eof"] is not None:
            break
    shares = bridge_gaps(statuses, settings.motion, _engine_base(exam, settings, mask), jobs,
                         run_tasks=lambda func, tasks: _run_tasks(func, tasks, jobs, scheduler, ordered=True),
                         done=done)
    rows.update((str(i), motion_row(0, 0.0, s)) for i, s in shares.items())
    with atomic_path(f) as tmp:
        tmp.write_text(json.dumps({"bridged": {k: rows[k] for k in sorted(rows, key=int)}}), encoding="utf-8")


def _ring_every(exam: Exam, settings: BatchSettings) -> int:
    """Which of the exam's steps measure its lumen scale (:func:`bodyslam.vision.lumen_scale.ring_every`; 0: none,
    where it is not measured, :func:`bodyslam.vision.odometry.lumen_scale_measured`)."""
    from bodyslam.vision.lumen_scale import ring_every
    from bodyslam.vision.odometry import lumen_scale_measured

    return ring_every(exam.n_positions) if lumen_scale_measured(settings.motion, exam.radius_sd_rel) else 0


def _lumen_scale_exam(exam: Exam, d: Path, settings: BatchSettings) -> None:
    """The exam's lumen scale from its chunks' ring ratios (``lumen_scale.json``: the summary of
    :func:`bodyslam.vision.lumen_scale.lumen_scale_summary`, or None where it is not measured), and before it each
    step's scale tied to its neighbours' where the scale chain is on (``scale_chain.npz``: every step's link and
    factor, :mod:`bodyslam.vision.scale_chain`); the outputs apply both as they read the steps (:func:`_exam_rows`).
    Cheap: written again on every run."""
    from bodyslam.vision.lumen_scale import exam_scale, exam_scale_sd_rel, lumen_scale_summary, ring_tried
    from bodyslam.vision.odometry import lumen_scale_measured
    from bodyslam.vision.scale_chain import chain_factors, chain_summary

    every = _ring_every(exam, settings)
    res = None
    measured = lumen_scale_measured(settings.motion, exam.radius_sd_rel)
    steps, ring, statuses = _scale_inputs(d)
    apply = measured and settings.motion.scale_chain
    factor = (chain_factors(steps[:, 0], steps[:, 1], steps[:, 2], steps[:, 3], steps[:, 4] > 0, exam.radius_m)
              if apply else np.ones(len(steps)))
    with atomic_path(d / "scale_chain.npz") as tmp:  # every step's link (the seams' too) and its factor
        with open(tmp, "wb") as fh:
            np.savez(fh, factor=factor, link=steps[:, 2], link_sd=steps[:, 3])
    if measured:
        tried = ring_tried(statuses, every)
        scale, samples = exam_scale(ring, tried)
        res = lumen_scale_summary(scale, samples, every, exam.radius_m,
                                  chain_summary(factor, np.isfinite(steps[:, 2])) if apply else None, tried,
                                  exam_scale_sd_rel(ring) if scale != 1.0 else None)
    with atomic_path(d / "lumen_scale.json") as tmp:
        tmp.write_text(json.dumps({"lumen_scale": res}), encoding="utf-8")


def _scale_inputs(d: Path) -> tuple[np.ndarray, list[float], list[str]]:
    """One pass over the exam's chunks for what its scales need: per step ``(distance, 1-sigma, scale link, its
    1-sigma, measured 1/0)``, the seams' links made from the points the chunks handed on (the rule ``bodyslam
    motion`` follows, :mod:`bodyslam.vision.scale_chain`), the ring ratios (:mod:`bodyslam.vision.lumen_scale`) and
    the steps' statuses (which steps had the ring fitted). A few numbers a step."""
    from bodyslam.steps import MEASURED
    from bodyslam.vision.scale_chain import Signature, scale_link

    cols = [MOTION_COLUMNS.index(c) for c in ("distance_m", "sigma_distance_m", "scale_link", "scale_link_sd")]
    st, rr = MOTION_COLUMNS.index("status"), MOTION_COLUMNS.index("ring_ratio")
    vals, ring, statuses, seam = [], [], [], None
    for ch in _iter_chunks(d):
        for j, row in enumerate(ch["steps"]):
            v = [float(row[c]) if len(row) > c else math.nan for c in cols] + [float(row[st] in MEASURED)]
            statuses.append(row[st])
            if j == 0 and seam is not None and ch.get("seam_in") is not None:  # the seam's link
                v[2:4] = scale_link(seam, Signature.from_json(ch["seam_in"]))
            vals.append(v)
            if len(row) > rr:
                ring.append(float(row[rr]))
        seam = Signature.from_json(ch.get("seam_out"))
        if ch["eof"] is not None:
            break
    return np.array(vals, float).reshape(-1, 5), ring, statuses


def _lumen_scale_of(d: Path) -> dict | None:
    """The exam's lumen scale as :func:`_lumen_scale_exam` wrote it (None: not measured, or no checkpoint)."""
    return (_checkpoint(d / "lumen_scale.json", "lumen_scale") or {}).get("lumen_scale")


def _steps_sd_rel(exam: Exam, d: Path) -> float:
    """The relative 1-sigma of the radius the exam's steps amount to: its lumen scale's where one was applied, else
    the radius's own (:func:`bodyslam.vision.lumen_scale.radius_sd_rel_after`). The steps' 1-sigma, the fusion's
    scale state and the path's variance all take it."""
    from bodyslam.vision.lumen_scale import radius_sd_rel_after

    return radius_sd_rel_after(_lumen_scale_of(d), exam.radius_sd_rel)


def _consistency_exam(exam: Exam, d: Path, settings: BatchSettings, mask, jobs, scheduler) -> None:
    """The k-step check of the per-step 1-sigma (:func:`bodyslam.vision.odometry.step_consistency`: up to 30
    three-frame pairs spread over the exam, each estimated straight and against its single steps); a checkpoint
    (``consistency.json``) that ``summary.json`` reports as ``step_consistency``."""
    from bodyslam.vision.odometry import consistency_pairs, step_consistency

    f = d / "consistency.json"
    if _checkpoint(f, "step_consistency") is not None:
        return
    pairs = consistency_pairs([row[8] for row in _step_rows(d)])
    keep = {i for a, b in pairs for i in range(a, b)}
    steps = [step_from_row(dict(zip(MOTION_COLUMNS, row))) if i in keep else None
             for i, row in enumerate(_step_rows(d))]
    res = step_consistency(steps, settings.motion, _engine_base(exam, settings, mask), jobs=jobs, pairs=pairs,
                           run_tasks=lambda func, tasks: _run_tasks(func, tasks, jobs, scheduler, ordered=True),
                           shape_sd_rel=exam.shape_sd_rel)
    with atomic_path(f) as tmp:
        tmp.write_text(json.dumps({"step_consistency": res}), encoding="utf-8")


def _exam_rows(exam: Exam, d: Path, info: dict | None = None) -> Iterator[tuple[list, list | None, object]]:
    """The exam's frames in order from its chunk files, up to the end of a video: ``(frame row, step row, step)``,
    the step into the frame as its ``motion.csv`` row and :class:`~bodyslam.steps.StepMotion` (None for the first
    frame), its gap's bridge applied and the lumen's uncertainty in its 1-sigma. ``info``: its ``problems`` list
    gets the chunks' problems, ``eof`` the frame a video ended at."""
    from bodyslam.vision.lumen_scale import local_sd_rel_after, radius_sd_rel_after, rescaled
    from bodyslam.vision.odometry import with_lumen_uncertainty

    bridged = json.loads((d / "bridges.json").read_text(encoding="utf-8"))["bridged"]
    sc = _lumen_scale_of(d)
    factor = sc["factor"] if sc else 1.0
    chain = None  # each step's factor and scale link (scale_chain.npz)
    if (d / "scale_chain.npz").is_file():
        with np.load(d / "scale_chain.npz") as z:
            chain = (z["factor"], z["link"], z["link_sd"])
    rel, shape, local = radius_sd_rel_after(sc, exam.radius_sd_rel), exam.shape_sd_rel, local_sd_rel_after(sc)
    item = 0
    for ch in _iter_chunks(d):
        if info is not None:
            info["problems"].extend(ch["problems"])
        fr = iter(ch["frames"])
        if ch["first"] == 0 and ch["frames"]:
            yield next(fr), None, None
        for row, step in zip(fr, ch["steps"]):
            if str(item) in bridged:
                step = step[:2] + bridged[str(item)][2:]
            if chain is not None and item < len(chain[0]):  # the seams' links, and the steps tied to neighbours
                step = list(step) + [math.nan] * (len(MOTION_COLUMNS) - len(step))
                step[_LINK:_LINK + 2] = float(chain[1][item]), float(chain[2][item])
                if chain[0][item] != 1.0:
                    f = float(chain[0][item])
                    step[_DISTANCE] *= f
                    step[_TX:_TX + 3] = [x * f for x in step[_TX:_TX + 3]]
                    step[_CHAIN] = f
            item += 1
            s = step_from_row(dict(zip(MOTION_COLUMNS, step)))
            if factor != 1.0 and s.has_estimate:  # the exam's lumen scale (lumen_scale.json)
                s = rescaled(s, factor)
                step = list(step)
                step[_DISTANCE], step[_SIGMA_D] = s.distance_m, s.sigma_distance_m
                step[_TX:_TX + 3] = map(float, s.t_c1_c2_m)
            if (rel > 0 or shape > 0 or local > 0) and s.has_estimate:  # the lumen's uncertainty in its 1-sigma
                s = with_lumen_uncertainty([s], rel, shape, local)[0]
                step = list(step)
                step[_SIGMA_D] = s.sigma_distance_m
            yield row, step, s
        if ch["eof"] is not None:
            if info is not None:
                info["eof"] = ch["eof"]
            return


def _finalize(exam: Exam, d: Path, settings: BatchSettings, wait_check: Callable[[], None] | None = None,
              fusion: Callable[[], dict] | None = None, jobs: int | None = 1) -> tuple[dict, list[list]]:
    """Rebuild an exam's outputs from its chunk files and bridges (streamed). ``wait_check``: blocks until the
    exam's k-step check (``consistency.json``, run meanwhile) is written, before the summary reads it.
    ``fusion``: gives the exam's :func:`_fuse_task` result, started on a worker (:func:`bodyslam.parallel.submit`)
    while this writes the frame and step tables; None: the fusion runs here, after them (an exam with RF).
    ``jobs``: the run's workers (the trajectory plot is drawn on one of them while this writes the page)."""
    from scipy.spatial.transform import Rotation

    from bodyslam.fusion.body_slam import DeadReckoner
    from bodyslam.io import write_tum
    from bodyslam.fusion.localize import write_uncertainty
    from bodyslam.steps import LOST_STEP_FLOOR_R, WITH_ROTATION, lost_step_floor_m, lost_to_motion
    from bodyslam.vision.tracking import path_from_lengths, share_beside_wall, share_without_estimate, step_length

    problems = [list(p) for p in exam.problems]
    n_expected = exam.n_positions
    acc = _Track(n_expected)  # ~200 bytes per frame, preallocated
    classes = {"FT": 0, "FL": 0, "": 0, "unlit": 0}  # unlit: FL because too dark or saturated to classify
    statuses: dict[str, int] = {}
    n_beside = 0  # steps whose tube fit put the camera beside its own cylinder's wall (StepMotion.beside_wall)
    # dead reckoning is the trajectory only where no fusion gives one: with RF it runs after a failed fusion only
    # (a second pass over the steps, _dead_reckon_into), not on the serial end of every exam (~0.12 ms a step)
    dr = DeadReckoner(lost_step_floor_m(exam.radius_m))
    info = {"problems": problems, "eof": None}
    rel = _steps_sd_rel(exam, d)
    with atomic_path(d / "frames.csv") as ftmp, atomic_path(d / "motion.csv") as mtmp, \
            open(ftmp, "w", newline="", encoding="utf-8") as ff, open(mtmp, "w", newline="", encoding="utf-8") as mf:
        fw, mw = csv.writer(ff, lineterminator="\n"), csv.writer(mf, lineterminator="\n")
        fw.writerow(FRAME_COLUMNS)
        mw.writerow(MOTION_COLUMNS)
        for row, step, s in _exam_rows(exam, d, info):
            fw.writerow(_csv_cells(row))
            if step is None:  # the first frame
                acc.record(row, dr, classes, (math.nan, 0.0))
                continue
            mw.writerow(_csv_cells(step))
            statuses[step[8]] = statuses.get(step[8], 0) + 1
            n_beside += s.beside_wall
            if not exam.rf:
                dr.step(s)
            acc.record(row, dr, classes, step_length(s), lost_to_motion(s), s.beside_wall, s.status in WITH_ROTATION)
    eof = None if info["eof"] is None else info["eof"] + exam.video_start  # a frame number, as the user counts
    n = acc.n
    t = acc.t[:n]
    frame_idx = acc.frame[:n].tolist()
    path_info: dict = {}
    path_m, path_var = path_from_lengths(acc.length[1:n], acc.length_var[1:n], rel, lost=acc.lost[1:n],
                                         radius_m=exam.radius_m, beside_wall=acc.beside_wall[1:n],
                                         rotated=acc.rotated[1:n], info=path_info)
    # the fusion does not change path.png: drawn on a worker while the fusion runs and this goes on
    path_drawn = submit(_path_png, {"exam": exam, "dir": d, "t": t, "frame_idx": frame_idx, "path_m": path_m,
                                    "path_var": path_var}, jobs)
    fused = None
    if exam.rf:
        res = fusion() if fusion is not None else _fuse_task({"exam": exam, "dir": str(d), "settings": settings})
        problems.extend(res["problems"])
        fused = res["fused"]
    if fused is not None:
        P, Q, cov, sd_head = fused["P"], fused["Q"], fused["cov"], fused["sd_heading"]
    else:  # dead reckoning: its steps without an estimate take the path travelled's lengths
        if exam.rf:  # the fusion gave nothing (its reason is in problems): dead reckoning, skipped so far
            _dead_reckon_into(acc, exam, d)
        P, Q = acc.pos[:n], Rotation.from_matrix(acc.rot[:n]).as_quat()
        cov, sd_head = acc.cov[:n], acc.sd_heading[:n]
        P = _with_path_lengths(P, path_m, acc.length[1:n], acc.beside_wall[1:n])
    sd = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    write_tum(d / "trajectory.tum", t, P, Rotation.from_quat(Q),
              world="body frame" if fused is not None else "first camera frame")
    write_uncertainty(d / "uncertainty.csv", frame_idx, t, cov, sd_head, path_m, path_var)
    marks = _marks(exam, d, frame_idx, t, P, sd, path_m, path_var, problems, rel)
    problems = collapse_format_notes(problems)  # how the exam was stored: once, not once per frame
    classified = settings.motion.classify
    if wait_check is not None:  # the k-step check, run meanwhile, is in consistency.json from here on
        wait_check()
    summary = {"exam": exam.name, "source": exam.source, "kind": exam.kind, "frames": n,
               "frames_expected": n_expected, "video_ended_at": eof,
               "frame_range": [frame_idx[0], frame_idx[-1]] if exam.frame_range is not None and n else None,
               "duration_s": float(t[-1] - t[0]) if n else 0.0, "frame_rate_hz": exam.frame_rate_hz,
               "classes": ({"FT": classes["FT"], "FL": classes["FL"], "none": classes[""],
                            "FL_dark_or_saturated": classes["unlit"]} if classified else "not classified"),
               "steps": dict(sorted(statuses.items())),
               # estimated steps whose 1-sigma was widened: fitted beside their own tube's wall or across the view
               "steps_beside_wall": n_beside, "path_travelled_m": float(path_m[-1]) if n else 0.0,
               "sd_path_travelled_m": math.sqrt(float(path_var[-1])) if n else 0.0,
               # the share of that path in steps without an estimate: the missing-step model's lengths, not the frames'
               "path_without_estimate_share": share_without_estimate(path_m, acc.length[1:n]) if n else 0.0,
               # ... and in fits beside the wall, whose lengths are the speed model's (the fit a weak reading)
               "path_beside_wall_share": (share_beside_wall(path_m, acc.length[1:n], acc.beside_wall[1:n]) if n
                                          else 0.0),
               # the lumen radii at which the path model took matching to lose half of the steps: the measured
               # curve's 0.4 times the exam's own scale (bodyslam.vision.tracking.missing_step_lengths); None: the
               # model did not run (every step estimated, or no radius)
               "path_loss_half_length_r": (round(LOST_STEP_FLOOR_R * path_info["loss_scale"], 3)
                                           if "loss_scale" in path_info else None),
               "trajectory": ("dead reckoning" if fused is None else "fused (RF + vision, RTS-smoothed"
                              + (" and refined" if settings.fusion == "rss" else "")
                              + ("; per-sensor RSS bias states)"
                                 if settings.rss_bias_states and settings.fusion == "rss" else ")")),
               # what the fused covariances were scaled by (bodyslam.fusion.channel): 1 = independent RSS errors;
               # kappa is the whole exam's, kappa_smoothed_mean the smoother's (its window's share, per frame)
               "rss_error_correlation": None if fused is None else fused["channel"],
               # the lumen radius the fusion's scale state implies along the exam (radius * (1 + s), smoothed)
               "lumen_radius_estimate_m": None if fused is None else fused["radius"],
               # the scale the steps were rescaled by, seen in the images (bodyslam.vision.lumen_scale)
               "lumen_scale": _lumen_scale_of(d),
               "marks": len(marks), "problems": len(problems), "assumed": exam.assumed,
               "camera": exam.camera, "radius_m": exam.radius_m, "radius_sd_m": exam.radius_sd_m,
               "lumen_shape_sd_rel": exam.shape_sd_rel,
               "vision": _vision_text(settings.motion),
               # does the per-step 1-sigma hold? (k-frame motions against their single steps)
               "step_consistency": (_checkpoint(d / "consistency.json", "step_consistency") or {}).get(
                   "step_consistency")}
    write_json(d / "summary.json", summary)
    _report(exam, d, summary, t, P, cov, frame_idx, marks, fused is not None, jobs)
    path_drawn()  # the plot is in place before the run says it is done
    return summary, problems


def _dead_reckon_into(acc: "_Track", exam: Exam, d: Path) -> None:
    """Fill ``acc``'s poses, covariances and heading 1-sigmas with the exam's dead reckoning (a second pass over its
    steps, as :func:`_finalize`'s first pass would have made them): for an exam with RF whose fusion gave nothing."""
    from bodyslam.fusion.body_slam import DeadReckoner
    from bodyslam.steps import lost_step_floor_m

    dr = DeadReckoner(lost_step_floor_m(exam.radius_m))
    for k, (_, step, s) in enumerate(_exam_rows(exam, d)):
        if k >= acc.n:
            break
        if step is not None:
            dr.step(s)
        acc.pos[k], acc.rot[k], acc.cov[k] = dr.p_w_m, dr.R_w_c_matrix, dr.P[:3, :3]
        acc.sd_heading[k] = math.sqrt(max(float(np.trace(dr.P[3:, 3:])), 0.0))


def unlit_text(classes: dict | str, template: str = "{}") -> str:
    """What the summary's FL count holds of frames too dark or saturated to classify (they are FL by rule, not by the
    classifier: a capsule in the dark, a blinded sensor), put into ``template``; ``""`` when none."""
    n = classes.get("FL_dark_or_saturated", 0) if isinstance(classes, dict) else 0
    return template.format(f"{n} of the FL too dark or saturated to classify") if n else ""


def _consistency_text(c: dict | None) -> str:
    if not c or not c.get("pairs_estimated"):
        return "not measured (no run of 3 estimated steps, or the thesis estimator)"
    ratio = c.get("median_distance_ratio_pair_over_singles")
    # no ratio where every pair's single steps add up to no length (a capsule at rest, frames repeated)
    ratio_text = "n/a (the single steps add up to no length)" if ratio is None else f"{ratio:.2f}"
    stated = ("" if c.get("stated_within_1sigma") is None else
              f"; with the lumen shape's {c['lumen_shape_sd_rel']:.0%} of each step (the 1-sigma motion.csv states, "
              f"less the radius's; generous: a pair and its steps see much of the same wall) "
              f"{c['stated_within_1sigma']:.0%} / {c['stated_within_2sigma']:.0%}")
    own = "the fit's own 1-sigma: " if stated else ""
    return (f"{c['pairs_estimated']} three-frame motions against their single steps, {own}{c['within_1sigma']:.0%} "
            f"within 1-sigma, {c['within_2sigma']:.0%} within 2{stated} (68% / 95% if it holds); distance ratio "
            f"{ratio_text}")


def _with_path_lengths(pos_m: np.ndarray, path_m: np.ndarray, length_m: np.ndarray,
                       beside_wall: np.ndarray | None = None) -> np.ndarray:
    """Dead-reckoned positions ``(n, 3)`` whose steps without an estimate (NaN in ``length_m``, ``n - 1``) and
    steps fitted beside the wall (``beside_wall``) are stretched along their direction to the length the path
    travelled gave them (``path_m``, ``n``:
    :func:`bodyslam.vision.tracking.path_from_lengths`). The dead reckoner is causal and streams, so it counts a lost
    step as the estimated steps so far at their 90th percentile; the path's model sees both sides. Afterwards the
    trajectory's length is the path travelled, and marks' positions and their path from the start agree (except
    where the dead reckoner did not move at all: such a step has no direction to stretch along and stays)."""
    if len(pos_m) < 2:
        return pos_m
    dp = np.diff(pos_m, axis=0)
    norm = np.linalg.norm(dp, axis=1)
    fix = ~np.isfinite(length_m)
    if beside_wall is not None:
        fix |= beside_wall
    fix &= norm > 1e-12
    dp[fix] *= (np.diff(path_m)[fix] / norm[fix])[:, None]
    return np.vstack([pos_m[:1], pos_m[0] + np.cumsum(dp, axis=0)])


def _radius_estimate(exam: Exam, fused, lumen_scale: dict | None = None) -> dict | None:
    """The lumen radius the fusion's scale state implies along the exam: the radius the steps amount to (the
    prior's, times the lumen scale they were rescaled by) times ``1 + s``."""
    s = None if fused is None else fused.smoothed.scale
    if s is None:
        return None
    radius = lumen_scale["effective_radius_m"] if lumen_scale else exam.radius_m
    r = radius * (1.0 + s)
    return {"median": float(np.median(r)), "p10": float(np.percentile(r, 10)), "p90": float(np.percentile(r, 90)),
            "median_1sigma": float(radius * np.median(fused.smoothed.scale_sd))}


def _csv_cells(row: list) -> list:
    """A chunk row as CSV cells, formatted as :func:`bodyslam.io.write_csv` does (so files are identical)."""
    return [f"{x:.9g}" if isinstance(x, float) else x for x in row]


class _Track:
    """Per-frame numbers the outputs need after streaming (pose, covariance, step length), preallocated."""

    def __init__(self, n: int):
        self.n = 0
        self.frame = np.zeros(n, np.int64)
        self.t, self.sd_heading, self.length, self.length_var = (np.zeros(n) for _ in range(4))
        self.lost = np.zeros(n, bool)  # the step into the frame was lost to motion (its path length's rule)
        self.beside_wall = np.zeros(n, bool)  # ... was fitted beside the wall (ditto)
        self.rotated = np.zeros(n, bool)  # ... carries a rotation (ditto)
        self.pos = np.zeros((n, 3))
        self.rot = np.zeros((n, 3, 3))
        self.cov = np.zeros((n, 3, 3))

    def record(self, row: list, dr, classes: dict, length_var: tuple[float, float], lost: bool = False,
               beside_wall: bool = False, rotated: bool = False) -> None:
        k = self.n
        if k >= len(self.t):  # more frames than planned (cannot happen for folders; a video may say less)
            for name in ("frame", "t", "sd_heading", "length", "length_var", "lost", "beside_wall", "rotated", "pos",
                         "rot", "cov"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.zeros_like(a[: max(len(a), 16)])]))
        self.frame[k] = int(row[0])
        self.t[k] = float(row[2])
        classes[row[3]] = classes.get(row[3], 0) + 1
        if row[4] in ("dark", "saturated"):  # frames.csv's status: called FL without being classified
            classes["unlit"] += 1
        self.pos[k] = dr.p_w_m
        self.rot[k] = dr.R_w_c_matrix
        self.cov[k] = dr.P[:3, :3]
        self.sd_heading[k] = math.sqrt(max(float(np.trace(dr.P[3:, 3:])), 0.0))
        self.length[k], self.length_var[k] = length_var
        self.lost[k] = lost
        self.beside_wall[k] = beside_wall
        self.rotated[k] = rotated
        self.n = k + 1


def _fuse_task(task: dict) -> dict:
    """An exam's fusion with RF (a worker's task: ``exam``, ``dir``, ``settings``): its steps and stamps from its
    chunk files exactly as ``motion.csv`` and ``frames.csv`` hold them (:func:`_exam_rows`, each step's numbers
    through the file's text), then :func:`_fuse`. Returns ``{"problems", "fused"}``, ``fused`` None where RF was
    not used, else what the exam's outputs take from the smoothed run: positions ``P (n, 3)``, quaternions ``Q``,
    position covariances ``cov (n, 3, 3)``, the heading's 1-sigma, the readings' correlation and the lumen radius
    the scale state implies."""
    exam, d, settings = task["exam"], Path(task["dir"]), task["settings"]
    frames, stamps, steps = [], [], []
    for row, step, _ in _exam_rows(exam, d):
        frames.append(int(row[0]))
        stamps.append(float(row[2]))
        if step is not None:
            steps.append(step_from_row(motion_values({c: str(v) for c, v in zip(MOTION_COLUMNS, _csv_cells(step))})[1]))
    problems: list[list] = []
    loc = _fuse(exam, d, np.array(stamps), frames, steps, settings, problems) if len(frames) >= 2 else None
    if loc is None:
        return {"problems": problems, "fused": None}
    sm = loc.smoothed
    return {"problems": problems, "fused": {
        "P": sm.positions_w_m, "Q": sm.rotations_w_c.as_quat(), "cov": sm.cov[:, :3, :3],
        "sd_heading": np.sqrt(np.trace(sm.cov[:, 3:, 3:], axis1=1, axis2=2)),
        "channel": ({**loc.channel.as_dict(), "kappa_smoothed_mean": round(float(np.mean(loc.kappa_smoothed)), 3)}
                    if loc.channel else None),
        "radius": _radius_estimate(exam, loc, _lumen_scale_of(d))}}


def _fuse(exam: Exam, d: Path, t: np.ndarray, frame_idx: list[int], steps: list, settings: BatchSettings,
          problems: list[list]):
    """The exam's localization (:func:`bodyslam.fusion.localize.localize`), or None with the reason listed."""
    from bodyslam.io import write_tum
    from bodyslam.fusion.localize import RfInput, localize, write_rss_bias

    try:
        rf = RfInput.read(exam.rf, exam.sensors, exam.pathloss)
        loc = localize(steps, t, rf, exam.frame_rate_hz, np.asarray(frame_idx), mode=settings.fusion,
                       radius_sd_rel=_steps_sd_rel(exam, d), radius_m=exam.radius_m,
                       bias_states=settings.rss_bias_states,
                       travelled=False)  # _finalize makes the path travelled meanwhile
    except InputError as exc:
        problems.append([exam.rf, "", "error", f"RF not used: {exc}"])
        return None
    problems.extend([exam.rf, "", "warning", msg] for msg in rf.problems)
    write_tum(d / "trajectory_filter.tum", t, loc.filtered.positions_w_m, loc.filtered.rotations_w_c)
    write_rss_bias(d / "rss_bias.csv", loc)
    return loc


def _landmark_span(landmarks: list[int]) -> tuple[int, int] | None:
    """The first and the last of an exam's landmark frames that it holds, where they are two frames or more."""
    return (min(landmarks), max(landmarks)) if len(set(landmarks)) >= 2 else None


def _marks(exam: Exam, d: Path, frame_idx: list[int], t, P, sd, path_m, path_var, problems,
           rel: float) -> list[list]:
    from bodyslam.vision.tracking import LOCAL_SCALE_SD_REL, fraction_between, segment_variance

    where = {f: k for k, f in enumerate(frame_idx)}
    lms = [lm for lm in exam.landmarks if lm in where]

    def absent(f: int) -> str:
        r = exam.frame_range
        if r is not None and not (r[0] <= f <= ((frame_idx[-1] if frame_idx else f) if r[1] is None else r[1])):
            return f"not in the exam: outside its frame range {_range_text(r)}"
        return "not in the exam (or unreadable)"

    # a landmark is checked whether or not there are marks (an absent one, given alone, was not mentioned)
    for lm in exam.landmarks:
        if lm not in where:
            problems.append([exam.source, lm, "error", f"landmark frame {absent(lm)}"])
    if not exam.marks:
        if lms:
            problems.append([exam.source, lms[0], "warning", "landmark(s) given without a marked frame: no path is "
                                                             "measured from them (--mark, --mark-file)"])
        return []
    header = ["frame", "label", "t", "x_m", "y_m", "z_m", "sd_position_m", "path_from_start_m",
              "sd_path_from_start_m"]
    for lm in lms:
        header += [f"path_from_{lm}_m", f"sd_path_from_{lm}_m"]
    # two landmarks or more: how far along the stretch between the first and the last (the pylorus and the
    # ileocaecal valve, say) by the path travelled, free of the radius's scale, and by the time (the clinical
    # convention, a share of the transit time) beside it
    span = _landmark_span(lms)
    if span is not None:
        header += [f"fraction_{span[0]}_{span[1]}", f"sd_fraction_{span[0]}_{span[1]}",
                   f"time_fraction_{span[0]}_{span[1]}"]
    rows = []
    for f, label in exam.marks:
        k = where.get(f)
        if k is None:
            problems.append([exam.source, f, "error", f"marked frame {absent(f)}"])
            continue
        row = [f, label, t[k], *P[k], sd[k], path_m[k], math.sqrt(path_var[k])]
        for lm in lms:
            j = where[lm]
            row += [path_m[k] - path_m[j],
                    math.sqrt(segment_variance(path_m, path_var, j, k, rel))]
        if span is not None:
            a, b = where[span[0]], where[span[1]]
            # the lumen's local scale does not cancel, unless the lumen is taken as a cylinder (no shape share)
            local = LOCAL_SCALE_SD_REL if exam.shape_sd_rel > 0 else 0.0
            row += [*fraction_between(path_m, path_var, a, b, k, rel, local_sd_rel=local),
                    (t[k] - t[a]) / (t[b] - t[a]) if t[b] > t[a] else math.nan]
        rows.append(row)
    write_csv(d / "marks.csv", header, rows)
    return rows


# what the report says beside a step status (bodyslam.steps.StepStatus)
STEP_WORDS = {"wall": " (fitted although a frame faces the wall; wider 1-sigma)",
              "bridged": " (shares of gaps measured end to end)",
              "rotation": " (fast steps: only the rotation measured, the distance unknown)",
              "rotation_slow": " (only the rotation measured; the frames overlap as a slow step's do, so not counted "
                               "lost to motion)",
              "lost": " (fast steps: no match between frames rich in features; counted long in the path)",
              "no_lumen": " (a frame too dark or saturated, or facing the wall, and not fitted)"}


def duration_text(seconds: float) -> str:
    """An exam's length as a person reads it: ``"1.5 s"``, ``"4.2 min"``, ``"7 h 38 min"``."""
    if not math.isfinite(seconds) or seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    h, m = divmod(int(round(seconds / 60)), 60)
    return f"{h} h {m:02d} min"


def _vision_text(m: MotionSettings) -> str:
    """How the steps were measured, in words (summary.json ``vision``, the report): the matcher and its tries, the
    estimator, what was done with steps facing the wall and with steps the fit failed on."""
    tries = {"fast": "tracking, then SIFT at 0.5 and 0.7 scale" + (", then on the full frame" if m.rescue else ""),
             "sift": "SIFT", "asift": "ASIFT"}[m.match_mode]
    est = "tube fit" if m.estimator == "tube" else f"the dissertation's equations ({m.unroll_mode} unrolling)"
    wall = ("not classified" if not m.classify else "facing the wall: fitted"
            if m.wall_steps == "estimate" and m.estimator == "tube" else "facing the wall: dropped")
    rot = "failed steps: their rotation by guided matching" if m.rotation_steps else "failed steps: no rotation"
    return f"{m.match_mode} matcher ({tries}); {est}; {wall}; {rot}"


def _path_png(task: dict) -> None:
    """``path.png``: how far along the gut against time, with its 1-sigma, the marked frames and the landmarks (a
    worker's task: ``exam``, ``dir``, ``t``, ``frame_idx``, ``path_m``, ``path_var``)."""
    from bodyslam.plots import path_figure

    exam, d, t, frame_idx = task["exam"], Path(task["dir"]), task["t"], task["frame_idx"]
    path_m, path_var = task["path_m"], task["path_var"]
    if len(t) < 2:
        return
    where = {f: k for k, f in enumerate(frame_idx)}
    write_image(d / "path.png", path_figure(f"{exam.name}: how far along the gut", t, path_m, path_var,
                                            [(t[where[f]], f"frame {f}") for f, _ in exam.marks if f in where],
                                            landmarks=[(t[where[f]], f"landmark {f}") for f in exam.landmarks
                                                       if f in where]))


def _trajectory_png(task: dict) -> None:
    """``trajectory.png`` (a worker's task: ``path``, and ``args`` / ``kw`` of
    :func:`bodyslam.plots.trajectory_figure`)."""
    from bodyslam.plots import trajectory_figure

    write_image(task["path"], trajectory_figure(*task["args"], **task["kw"]))


def radius_text(radius_m: float, sd_m: float) -> str:
    """The report's lumen radius: a prior with its 1-sigma, or a radius known exactly (``sd_m`` 0: given on the
    command line, or a testbed tube of one radius), which is then the steps' scale."""
    if sd_m > 0:
        return f"{radius_m * 100:.2f} +- {sd_m * 100:.2f} cm (the prior, 1-sigma)"
    return f"{radius_m * 100:.2f} cm (known exactly: the steps' scale)"


def _report(exam: Exam, d: Path, summary: dict, t, P, cov, frame_idx, marks: list[list], fused: bool,
            jobs: int | None = 1) -> None:
    """The exam's ``trajectory.png`` (3-D and three projections with the 1-sigma and the marked frames; drawn on
    a worker of the run's pool while this writes the page, :func:`bodyslam.parallel.submit`) and ``report.html``
    (the summary, the marked frames, a 3-D view to turn, the plots; ``path.png`` is :func:`_path_png`'s)."""
    from bodyslam.plots import Mark, Path3D
    from bodyslam.report import table, view_3d, write_page
    from bodyslam.steps import LOST_STEP_FLOOR_R, MISSING_STEP_REL_SD
    from bodyslam.vision.lumen_scale import lumen_scale_text
    from bodyslam.vision.tracking import path_share_text

    if len(t) < 2:
        return
    where = {f: k for k, f in enumerate(frame_idx)}
    name = "Body-SLAM (RF + vision, smoothed)" if fused else "dead reckoning (vision only)"
    paths = [Path3D(name, P, (214, 39, 40), 1.8, cov)]
    mk = [Mark(f"frame {r[0]}" + (f" {r[1]}" if r[1] else ""), P[where[r[0]]], cov[where[r[0]]]) for r in marks]
    mk += [Mark(f"landmark {f}", P[where[f]], cov[where[f]], landmark=True) for f in exam.landmarks if f in where]
    frame_txt = "body frame" if fused else "first camera frame: no RF, so no body frame"
    drawn = submit(_trajectory_png, {"path": d / "trajectory.png",
                                     "args": (f"{exam.name}: where the capsule was ({frame_txt})", paths, mk),
                                     "kw": {"body_frame": fused}}, jobs)
    sm = summary
    cls = sm["classes"]
    filled = path_share_text(sm.get("path_without_estimate_share", 0.0), sm.get("path_beside_wall_share", 0.0))
    fr = sm.get("frame_range")
    rows = [["source", f"{sm['source']} ({sm['kind']})" + (f"; frames {fr[0]}-{fr[1]} of it" if fr else "")],
            ["frames read / expected", f"{sm['frames']} / {sm['frames_expected']}"
             + (f" (the video ended at frame {sm['video_ended_at']})" if sm["video_ended_at"] is not None else "")],
            ["duration", f"{duration_text(sm['duration_s'])} at {sm['frame_rate_hz']:g} frames/s"],
            ["facing the tunnel / the wall",
             cls if isinstance(cls, str) else f"{cls['FT']} / {cls['FL']}" + unlit_text(cls, " ({})")],
            ["steps", ", ".join(f"{v} {k}" + STEP_WORDS.get(k, "") for k, v in sm["steps"].items())
             + (f"; {sm['steps_beside_wall']} of the estimated steps fitted beside the wall of their own tube or "
                "across the view (a folded or collapsed lumen: motion kept, wider 1-sigma)"
                if sm["steps_beside_wall"] else "")],
            ["path travelled", f"{sm['path_travelled_m'] * 100:.1f} +- {sm['sd_path_travelled_m'] * 100:.1f} cm "
             + (f"(1-sigma; {filled})" if filled else "(1-sigma)")],
            ["trajectory", sm["trajectory"]],
            ["lumen radius", radius_text(exam.radius_m, exam.radius_sd_m)],
            ["lumen scale seen in the frames", lumen_scale_text(sm.get("lumen_scale"))],
            ["lumen shape", f"steps +- {exam.shape_sd_rel:.0%} (1-sigma) for a lumen that is not a cylinder"
             if exam.shape_sd_rel > 0 else "a cylinder (each step's 1-sigma has no shape share)"],
            ["steps measured by", sm["vision"]],
            ["per-step 1-sigma check", _consistency_text(sm.get("step_consistency"))],
            ["assumed", "; ".join(sm["assumed"]) or "nothing"],
            ["problems", f"{sm['problems']} (problems.csv)"]]
    body = table(None, rows)
    if marks:
        span = _landmark_span([lm for lm in exam.landmarks if lm in where])
        head = ["frame", "label", "t (s)", "x (cm)", "y (cm)", "z (cm)", "1-sigma (cm)", "path from start (cm)",
                "1-sigma (cm)"]
        cells = [[r[0], r[1], f"{r[2]:.1f}", *(f"{v * 100:.1f}" for v in r[3:9])] for r in marks]
        if span is not None:  # the last three cells: fraction, its 1-sigma, time fraction (_marks)
            head += [f"from frame {span[0]} to {span[1]}: by the path (1-sigma)", "by the time"]
            for c, r in zip(cells, marks):
                c += [f"{r[-3]:.0%} +- {r[-2]:.0%}" if math.isfinite(r[-3]) else "-",
                      f"{r[-1]:.0%}" if math.isfinite(r[-1]) else "-"]
        body += "<h2>Marked frames</h2>" + table(head, cells)
    body += "<h2>3-D view</h2>" + view_3d(paths, mk, t, np.asarray(frame_idx), body_frame=fused) + "<h2>Plots</h2>"
    write_page(d / "report.html", f"Exam {exam.name}", f"{name}; positions in the {frame_txt}"
               + (". The 1-sigma is dead reckoning's: it grows with every step" if not fused else
                  " (x toward the patient's left, y anterior, z cranial). The 1-sigma is the filter's, scaled by the "
                  "RF readings' measured correlation")
               + "; the path travelled is the sum of the visual steps, a step without a distance given a length "
                 "from the capsule's speed around it, one lost to motion (status rotation or lost; not rotation_slow) "
                 "as one the matcher could not reach (half of the steps are lost at "
                 f"{sm.get('path_loss_half_length_r') or LOST_STEP_FLOOR_R:g} lumen radii: the matcher's measured "
                 f"{LOST_STEP_FLOOR_R:g}, scaled to this exam's losses), and a fit beside the wall its length mostly "
                 "from that speed "
                 "too (the fit a weak reading of it); its 1-sigma includes the lumen radius's and each filled step's "
                 f"(at least {MISSING_STEP_REL_SD:.0%} of it).", body,
               ["trajectory.png", "path.png"])
    drawn()  # the plot is in place before the run says it is done

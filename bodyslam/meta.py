"""``meta.json`` of a sequence directory, read, validated and written in one place (SPEC.md "Files").

:class:`SequenceMeta` is what the pipeline may know of a recording: frame count and rate, the camera, the
nominal lumen radius and how far the lumen departs from a cylinder, where the frames are, the RF calibration, a
rear camera's extrinsics. Every reader (``bodyslam check``, ``motion``, ``track``, ``localize``, ``batch``,
``classify``, the testbed's evaluation) goes through :func:`read_meta`, and ``testbed simulate`` writes through
:func:`write_meta`, so what ``check`` accepts the pipeline runs, and what it refuses is refused everywhere with one
line naming the file, the field and the value. Keys this module does not know (provenance, depth, units, other
systems' tables) are kept in ``raw``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bodyslam.camera import CameraModel, camera_from_dict
from bodyslam.errors import InputError
from bodyslam.io import read_json, write_json

__all__ = ["SequenceMeta", "RfMeta", "RearCamera", "read_meta", "write_meta", "meta_from_dict", "lumen_radius_problem",
           "LUMEN_RADIUS_RANGE_M"]


@dataclass(frozen=True)
class RfMeta:
    """The RF calibration a real system would have: file names and the path-loss model (a dict for
    :meth:`bodyslam.fusion.rf.PathLossModel.from_dict`, already validated; ``None``: Table 2.2's defaults)."""

    file: str = "rf.csv"
    sensors: str = "sensors.csv"
    pathloss: dict | None = None


@dataclass(frozen=True)
class RearCamera:
    camera: dict
    frames_dir: str
    q_front_rear_xyzw: tuple[float, float, float, float]
    t_front_rear_m: tuple[float, float, float]


@dataclass(frozen=True)
class SequenceMeta:
    n_frames: int
    frame_rate_hz: float
    camera: dict  # a valid camera_from_dict description
    tube_radius_m: float | None = None  # nominal lumen radius (the scale of the tube estimator)
    frames_dir: str = "frames"
    rf: RfMeta | None = None
    rear_camera: RearCamera | None = None
    raw: dict = field(default_factory=dict, repr=False, compare=False)
    path: Path | None = field(default=None, compare=False)  # the meta.json read, for messages
    tube_radius_sd_m: float = 0.0  # 1-sigma of tube_radius_m (0: known exactly; a population prior's spread)
    # relative 1-sigma of a step's distance from the lumen not being the cylinder the tube estimator fits (folds,
    # a star-shaped cross-section, a radius that changes within the view); 0 or absent: a cylinder (the ideal tube)
    lumen_shape_sd_rel: float = 0.0

    def camera_model(self) -> CameraModel:
        return camera_from_dict(self.camera)

    @property
    def radius_sd_rel(self) -> float:
        """The lumen radius prior's 1-sigma relative to it (the visual scale's; 0 without a radius)."""
        return self.tube_radius_sd_m / self.tube_radius_m if self.tube_radius_m else 0.0

    def stamp_s(self, k: int) -> float:
        return k / self.frame_rate_hz


def _where(path: Path | None) -> str:
    return f"{path}" if path is not None else "meta.json"


# a gut lumen's radius, metres: from a contracted small bowel to a distended stomach (the testbed's magnetic-capsule
# scenario is 10 cm). Outside it a radius is a unit mistake: 1.25 given for 1.25 cm made every step 80x too long
LUMEN_RADIUS_RANGE_M = (1e-3, 0.15)


def lumen_radius_problem(radius_m: float, what: str) -> str | None:
    """Why ``radius_m`` is no lumen radius in metres (not finite, not positive, or outside
    :data:`LUMEN_RADIUS_RANGE_M`; with the likely unit where it is off by 100 or 1000), or None where it is one."""
    lo, hi = LUMEN_RADIUS_RANGE_M
    if isinstance(radius_m, bool) or not isinstance(radius_m, (int, float)) or not math.isfinite(radius_m):
        return f"{what} must be a number of metres, got {radius_m!r}"
    if lo <= radius_m <= hi:
        return None
    hint = ""
    for unit, per_m in (("centimetres", 100), ("millimetres", 1000)):  # the unit that gives a gut's 0.5-5 cm
        if 0.005 <= radius_m / per_m <= 0.05:
            hint = f" (in metres: {radius_m:g} {unit} is {radius_m / per_m:g})"
            break
    return f"{what} must be a lumen radius in metres, {lo:g}-{hi:g}, got {radius_m:g}{hint}"


def _number(d: dict, key: str, where: str, positive: bool = True, required: bool = True) -> float | None:
    v = d.get(key)
    if v is None:
        if required:
            raise InputError(f"{where}: missing {key}" if key not in d else f"{where}: {key} is null")
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise InputError(f"{where}: {key} must be a {'positive ' if positive else ''}number, got {v!r}")
    return float(v)


def meta_from_dict(d: Any, path: Path | None = None) -> SequenceMeta:
    """Validate a parsed meta.json (see module docstring).

    Raises
    ------
    InputError
        One line naming the file, the field and the value.
    """
    where = _where(path)
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a JSON object, got {type(d).__name__}")
    n = d.get("n_frames")
    if "n_frames" not in d:
        raise InputError(f"{where}: missing n_frames")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        if isinstance(n, float) and n.is_integer() and n >= 1:
            n = int(n)
        else:
            raise InputError(f"{where}: n_frames must be a positive whole number, got {n!r}")
    rate = _number(d, "frame_rate_hz", where)
    if "camera" not in d:
        raise InputError(f"{where}: missing camera")
    cam = d["camera"]
    try:
        camera_from_dict(cam)
    except InputError as exc:
        raise InputError(f"{where}: camera: {exc}") from None
    radius = _number(d, "tube_radius_m", where, required=False)
    if radius is not None and (why := lumen_radius_problem(radius, "tube_radius_m")):
        raise InputError(f"{where}: {why}")
    radius_sd = _number(d, "tube_radius_sd_m", where, positive=False, required=False)
    radius_sd = 0.0 if radius_sd is None else radius_sd
    if radius_sd < 0 or (radius is not None and radius_sd >= radius):
        raise InputError(f"{where}: tube_radius_sd_m must be >= 0 and below tube_radius_m, got {radius_sd!r}")
    shape_sd = _number(d, "lumen_shape_sd_rel", where, positive=False, required=False)
    shape_sd = 0.0 if shape_sd is None else shape_sd
    if not 0.0 <= shape_sd < 1.0:
        raise InputError(f"{where}: lumen_shape_sd_rel must be a fraction of the distance in 0-1, got {shape_sd!r}")
    frames = d.get("frames", {})
    if frames is None:
        frames = {}
    if not isinstance(frames, dict) or not isinstance(frames.get("dir", "frames"), str) or not frames.get("dir", "x"):
        raise InputError(f"{where}: frames must be an object with a non-empty 'dir' string, got {frames!r}")
    rf = None
    if d.get("rf") is not None:
        r = d["rf"]
        if not isinstance(r, dict):
            raise InputError(f"{where}: rf must be an object, got {r!r}")
        for key in ("file", "sensors"):
            if key in r and not (isinstance(r[key], str) and r[key]):
                raise InputError(f"{where}: rf.{key} must be a file name, got {r[key]!r}")
        pl = r.get("pathloss")
        if pl is not None:
            from bodyslam.fusion.rf import PathLossModel

            try:
                PathLossModel.from_dict(pl)
            except InputError as exc:
                raise InputError(f"{where}: rf.pathloss: {exc}") from None
        rf = RfMeta(r.get("file", "rf.csv"), r.get("sensors", "sensors.csv"), pl)
    rear = None
    if d.get("rear_camera") is not None:
        r = d["rear_camera"]
        try:
            camera_from_dict(r["camera"])
            rdir = (r.get("frames") or {}).get("dir", "frames_rear")
            q = tuple(float(x) for x in r["T_front_rear"]["q_xyzw"])
            t = tuple(float(x) for x in r["T_front_rear"]["t_m"])
            if len(q) != 4 or len(t) != 3 or not all(map(math.isfinite, q + t)) or not isinstance(rdir, str):
                raise ValueError("q_xyzw must be 4 numbers, t_m 3")
        except (KeyError, TypeError, ValueError, AttributeError, InputError) as exc:
            raise InputError(f"{where}: malformed rear_camera ({exc})") from None
        rear = RearCamera(r["camera"], rdir, q, t)
    return SequenceMeta(n, rate, cam, radius, frames.get("dir", "frames"), rf, rear, dict(d), path, radius_sd,
                        shape_sd)


def read_meta(seq_dir: str | os.PathLike) -> SequenceMeta:
    """The validated ``meta.json`` of a sequence directory (or the file itself)."""
    p = Path(seq_dir)
    path = p if p.suffix == ".json" and not p.is_dir() else p / "meta.json"
    if p.is_file() and path is not p:
        raise InputError(f"{p}: not a sequence directory (a folder with meta.json and frames/); a video goes to "
                         "`bodyslam batch`, one image to `bodyslam classify` or `segment`")
    if p.is_dir() and not path.exists():
        from bodyslam.frames import IMAGE_EXTS  # here: bodyslam.frames loads OpenCV, which meta.json does not need

        if any(q.suffix.lower() in IMAGE_EXTS for q in p.iterdir()):
            raise InputError(f"{path}: file not found: {p} is a plain frame folder, not a sequence directory "
                             "(meta.json, frames/); `bodyslam batch` takes plain folders and videos, with an assumed "
                             "camera and lumen radius")
    return meta_from_dict(read_json(path), path)


def write_meta(seq_dir: str | os.PathLike, meta: dict) -> SequenceMeta:
    """Validate ``meta`` and write it as ``seq_dir/meta.json`` (atomically); returns what a reader will get."""
    path = Path(seq_dir) / "meta.json"
    m = meta_from_dict(meta, path)
    write_json(path, meta)
    return m

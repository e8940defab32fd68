"""File formats, in one place (SPEC.md "Files").

- Trajectories: TUM text, ``t x y z qx qy qz qw`` (t in s, position in m, unit quaternion scalar-last), readable by
  the public ``evo`` tools. Quaternion order is converted here and nowhere else.
- Sequence metadata: ``meta.json``.
- Images: PNG; colour images are RGB ``uint8 (h, w, 3)`` inside the code, BGR only inside this module.
- Every file is written atomically (temporary file in the same directory, then ``os.replace``), so a killed run
  never leaves a half-written file that looks whole.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.errors import InputError
from bodyslam.geometry import matrix_to_rotvec, rotvec_to_matrix
from bodyslam.steps import StepMotion, StepStatus

__all__ = [
    "read_labels",
    "atomic_path",
    "prepare_output_dir",
    "check_writable",
    "write_bytes_atomic",
    "write_text_atomic",
    "write_json",
    "read_json",
    "read_text",
    "write_tum",
    "read_tum",
    "write_image",
    "read_image",
    "write_csv",
    "read_meta",
    "frame_name",
    "read_motion_csv",
    "motion_values",
    "MOTION_COLUMNS",
    "motion_row",
    "write_motion_csv",
    "read_motion_steps",
    "csv_rows",
    "csv_table",
]

FRAME_INDEX_DIGITS = 6


def frame_name(index: int) -> str:
    """Zero-padded PNG name of frame ``index`` (``000123.png``)."""
    return f"{index:0{FRAME_INDEX_DIGITS}d}.png"


_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed onto ``path``, on error removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def prepare_output_dir(out_dir: str | os.PathLike, force: bool, create: bool = True) -> Path:
    """Create ``out_dir``; refuse to write into a non-empty directory unless ``force``. Returns it as a Path.
    ``create=False`` only checks (before a long computation), so a failed run leaves no empty directory.

    Raises
    ------
    InputError
        Not a directory, not empty (without ``force``), or its parent cannot be written.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a directory")
    if out_dir.exists() and any(out_dir.iterdir()) and not force:
        raise InputError(f"{out_dir}: directory is not empty (use --force to overwrite)")
    probe = out_dir if out_dir.exists() else next((p for p in out_dir.parents if p.exists()), Path("."))
    if not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{probe}: not writable (output directory {out_dir})")
    made = [p for p in (out_dir, *out_dir.parents) if not p.exists()]
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out_dir}: cannot create the output directory ({exc.strerror or exc})") from None
    if not create:  # only a check: leave nothing behind
        for p in made:
            try:
                p.rmdir()
            except OSError:
                break
    return out_dir


def check_writable(path: str | os.PathLike) -> Path:
    """Refuse, before any work starts, an output file that cannot be written: its directory is missing and
    cannot be made, is not writable, or the path is a directory. Returns it as a Path.

    Raises
    ------
    InputError
        Which location, and why.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a directory; give a file name")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{parent}: cannot create the output directory ({exc.strerror or exc})") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{parent}: output directory is not writable")
    return path


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: not valid JSON ({_decode_reason(exc)})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def read_meta(seq_dir: str | os.PathLike) -> dict[str, Any]:
    """``meta.json`` of a sequence directory, checked for the keys every stage relies on."""
    path = Path(seq_dir) / "meta.json"
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise InputError(f"{path}: expected a JSON object")
    for key in ("frame_rate_hz", "camera", "n_frames"):
        if key not in meta:
            raise InputError(f"{path}: missing key {key!r}")
    return meta


def write_tum(
    path: str | os.PathLike, stamps_s: np.ndarray, positions_w_m: np.ndarray, rotations_w_c: Rotation,
    world: str = "body frame",
) -> None:
    """Write poses ``T_w_c`` as TUM lines ``t x y z qx qy qz qw``; ``world`` names the world frame in the header
    (the body frame of fused trajectories; ``"first camera frame"`` for dead reckoning)."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    pos = np.asarray(positions_w_m, dtype=np.float64).reshape(-1, 3)
    q_xyzw = rotations_w_c.as_quat(canonical=True).reshape(-1, 4)  # scipy order is scalar-last (x y z w)
    if not (len(stamps_s) == len(pos) == len(q_xyzw)):
        raise ValueError("stamps, positions and rotations must have the same length")
    buf = io.StringIO()
    buf.write(f"# timestamp_s x_m y_m z_m qx qy qz qw (T_w_c, world = {world})\n")
    for t, p, q in zip(stamps_s, pos, q_xyzw):
        buf.write(f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    write_text_atomic(path, buf.getvalue())


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, Rotation]:
    """Read a TUM trajectory: ``(stamps_s (n,), positions_w_m (n, 3), rotations_w_c)``.

    Raises
    ------
    InputError
        Missing file, or a line that is not 8 numbers or has a non-unit quaternion (file and line are named).
    """
    path = Path(path)
    text = read_text(path)
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise InputError(f"{path}:{lineno}: not a number in {s!r}") from None
        if len(vals) != 8:
            raise InputError(f"{path}:{lineno}: expected 8 values 't x y z qx qy qz qw', got {len(vals)}")
        n = np.linalg.norm(vals[4:])
        if not np.isfinite(vals).all() or abs(n - 1.0) > 1e-3:
            raise InputError(f"{path}:{lineno}: quaternion is not of unit length (|q| = {n:.6f})")
        rows.append(vals)
    if not rows:
        raise InputError(f"{path}: no poses")
    a = np.array(rows)
    return a[:, 0], a[:, 1:4], Rotation.from_quat(a[:, 4:8])


def write_csv(path: str | os.PathLike, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Write a CSV with a header row, atomically. Floats are written with full precision. ``rows`` may be a
    generator (a whole exam's rows need not be held as lists)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([f"{x:.9g}" if isinstance(x, (float, np.floating)) else x for x in r])
    write_text_atomic(path, buf.getvalue())


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB ``uint8 (h, w, 3)``, grey ``(h, w)`` or ``uint16`` image as PNG, atomically."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise InputError(f"{path}: could not encode image of shape {image.shape} dtype {image.dtype}")
    write_bytes_atomic(path, buf.tobytes())


def read_image(path: str | os.PathLike, unchanged: bool = False) -> np.ndarray:
    """Read an image file as RGB ``uint8 (h, w, 3)`` (or as stored with ``unchanged=True``).

    Raises
    ------
    InputError
        Missing, empty or undecodable file (the path is named).
    """
    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not an image") from None
    if data.size == 0:
        raise InputError(f"{path}: empty file (0 bytes)")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED if unchanged else cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"{path}: not a decodable image (corrupt or truncated?)")
    if not unchanged:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


_MOTION_REQUIRED = ("frame", "distance_m", "roll_rad", "pitch_rad", "yaw_rad")
MOTION_COLUMNS = ["frame", "t", "distance_m", "roll_rad", "pitch_rad", "yaw_rad", "tilt_rad", "n_matches", "status",
                  # beyond SPEC's minimum: the full step (translation in the first frame's camera axes, rotation
                  # vector of R_c1_c2) and its 1-sigma uncertainties, so fusion can run from the file alone
                  "tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad", "sigma_distance_m", "sigma_rotation_rad",
                  # 1 where the tube fit put the camera beside its own cylinder's wall (StepMotion.beside_wall)
                  "beside_wall",
                  # the step's length under a ringed tube over the cylinder's, where the lumen's scale was measured
                  # (StepMotion.ring_ratio, bodyslam.vision.lumen_scale); nan elsewhere (a file without it: nan)
                  "ring_ratio",
                  # the step's scale against the previous step's (log ratio, from the points both matched in their
                  # shared frame) and its 1-sigma, and the factor its length was multiplied by to tie it to its
                  # neighbours' (StepMotion.scale_link, scale_link_sd, chain_factor; bodyslam.vision.scale_chain);
                  # nan where there is none (a file without them: nan)
                  "scale_link", "scale_link_sd", "chain_factor"]
_FULL_STEP = ("tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad", "sigma_distance_m", "sigma_rotation_rad")


def motion_row(frame: int, t_s: float, s: StepMotion) -> list:
    """One ``motion.csv`` row (:data:`MOTION_COLUMNS`) for the step into ``frame`` (plain Python numbers)."""
    t = s.t_c1_c2_m if s.t_c1_c2_m is not None else np.full(3, np.nan)
    rv = matrix_to_rotvec(s.R_c1_c2) if s.R_c1_c2 is not None else np.full(3, np.nan)
    return [int(frame), float(t_s), float(s.distance_m), float(s.roll_rad), float(s.pitch_rad), float(s.yaw_rad),
            float(s.tilt_rad), int(s.n_matches), str(s.status), *map(float, t), *map(float, rv),
            float(s.sigma_distance_m), float(s.sigma_rotation_rad), int(s.beside_wall), float(s.ring_ratio),
            float(s.scale_link), float(s.scale_link_sd), float(s.chain_factor)]


def write_motion_csv(path: str | os.PathLike, frames: Sequence[int], stamps_s: Sequence[float],
                     steps: Sequence[StepMotion]) -> None:
    """``motion.csv`` (SPEC.md): the step into ``frames[i]`` at ``stamps_s[i]`` is ``steps[i]``."""
    if not (len(frames) == len(stamps_s) == len(steps)):
        raise ValueError("frames, stamps and steps must have the same length")
    write_csv(path, MOTION_COLUMNS, [motion_row(f, t, s) for f, t, s in zip(frames, stamps_s, steps)])


def step_from_row(row: dict) -> StepMotion:
    """A :class:`StepMotion` from a :func:`read_motion_csv` row (the full step where its columns are finite)."""
    vals = [row.get(c, math.nan) for c in _FULL_STEP]
    R = t = None
    if np.isfinite(vals[3:6]).all():  # a rotation step has its rotation and no translation
        R = rotvec_to_matrix(vals[3:6])
    if R is not None and np.isfinite(vals[:3]).all():
        t = np.array(vals[:3], float)
    return StepMotion(row["distance_m"], row["roll_rad"], row["pitch_rad"], row["yaw_rad"], row["tilt_rad"],
                      int(row.get("n_matches", 0)), row["status"], R, t, vals[6], vals[7],
                      bool(row.get("beside_wall", False)), float(row.get("ring_ratio", math.nan)),
                      float(row.get("scale_link", math.nan)), float(row.get("scale_link_sd", math.nan)),
                      float(row.get("chain_factor", math.nan)))


def read_motion_steps(path: str | os.PathLike, frames: Sequence[int]) -> list[StepMotion]:
    """The steps into ``frames`` (frame numbers of the step's later frame) from a ``motion.csv``; a frame
    without a row gives a step with status ``missing``.

    Raises
    ------
    InputError
        Missing file or columns, a malformed line or an unknown status (file and line are named).
    """
    rows = read_motion_csv(path)
    return [step_from_row(rows[k]) if k in rows else StepMotion.failed(StepStatus.MISSING) for k in frames]


@contextlib.contextmanager
def csv_rows(path: str | os.PathLike, required: Sequence[str]) -> Iterator[Iterator[tuple[int, dict]]]:
    """Open a CSV with a header and check its columns; yields an iterator of ``(line number, row dict)``.

    Raises
    ------
    InputError
        Missing file, or a header without the ``required`` columns (file and header are named).
    """
    with _open_csv(path, required, csv.DictReader) as (path, r, _):
        yield _checked_rows(path, r)


@contextlib.contextmanager
def csv_table(path: str | os.PathLike, required: Sequence[str]) -> Iterator[tuple[list[str], Iterator]]:
    """:func:`csv_rows` with each row a list of cells: yields ``(header, iterator of (line number, cells))``,
    a short row has fewer cells than the header. For long files (rf.csv: a row per reading): no dict per row."""
    with _open_csv(path, required, csv.reader) as (path, r, fields):
        yield fields, _checked_rows(path, r)


@contextlib.contextmanager
def _open_csv(path, required: Sequence[str], reader):
    """``(path, reader past the header, header)``; the errors of :func:`csv_rows`."""
    path = Path(path)
    try:
        f = path.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:  # a directory, no permission ...
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    with f:
        r = reader(f)
        try:
            fields = r.fieldnames if isinstance(r, csv.DictReader) else next(r, None)
        except (UnicodeDecodeError, csv.Error) as exc:
            raise InputError(f"{path}: not a CSV text file ({_decode_reason(exc)})") from None
        missing = [c for c in required if c not in (fields or [])]
        if missing and not fields:  # no header line: an empty or blank file (DictReader gives None, reader [])
            raise InputError(f"{path}: empty file: no header line (it needs the column(s) {', '.join(missing)})")
        if missing:
            raise InputError(f"{path}: missing column(s) {', '.join(missing)}; header is {fields}")
        yield path, r, fields


def _decode_reason(exc: Exception) -> str:
    if isinstance(exc, UnicodeDecodeError):
        return f"not UTF-8 at byte {exc.start}"
    return str(exc)


def _checked_rows(path: Path, r) -> Iterator[tuple[int, Any]]:
    """``(line number, row)`` of a CSV (the reader's own count of lines read: right after blank lines, which
    ``csv.DictReader`` skips, and quoted fields that span lines); a file that stops being text is an error
    naming the line."""
    k = 1
    try:
        for row in r:
            k = r.line_num
            yield k, row
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}:{k + 1}: not CSV text ({_decode_reason(exc)})") from None


def read_text(path: str | os.PathLike) -> str:
    """A whole UTF-8 text file; every way it cannot be read is an :class:`InputError` naming it."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text file ({_decode_reason(exc)})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None


FRAME_LABELS = ("FT", "FL")


def read_labels(path: str | os.PathLike) -> dict[int, str]:
    """A testbed sequence's ``labels.csv`` (``frame,label,...``): frame number -> ``FT`` or ``FL``. A frame without a
    label (empty) is left out; any other row (a frame that is not a whole number, a label that is neither, a frame
    listed twice) is an :class:`~bodyslam.errors.InputError` naming the file and line: the labels are what a model
    learns from, so none is guessed."""
    out: dict[int, str] = {}
    with csv_rows(path, ("frame", "label")) as rows:
        for line, r in rows:
            frame, label = (r.get("frame") or "").strip(), (r.get("label") or "").strip()
            if not (frame.isascii() and frame.isdigit()):  # ("²".isdigit() is true, and int() refuses it)
                raise InputError(f"{path}:{line}: frame must be a whole number, got {r.get('frame')!r}")
            if label == "":
                continue
            if label not in FRAME_LABELS:
                raise InputError(f"{path}:{line}: label must be FT or FL (or empty), got {r.get('label')!r}")
            if int(frame) in out:
                raise InputError(f"{path}:{line}: frame {int(frame)} listed twice")
            out[int(frame)] = label
    return out


def read_motion_csv(path: str | os.PathLike) -> dict[int, dict[str, float | str]]:
    """Rows of a ``motion.csv`` keyed by frame; malformed lines are named by file and line."""
    rows = {}
    with csv_rows(path, _MOTION_REQUIRED) as lines:
        for lineno, row in lines:
            k, vals = motion_values(row, f"{path}:{lineno}")
            rows[k] = vals
    return rows


def motion_values(row: dict, where: str = "motion row") -> tuple[int, dict[str, float | str]]:
    """One ``motion.csv`` line's cells (text, by column) as :func:`read_motion_csv` reads them: ``(frame, values)``;
    ``where`` names the line in an error."""
    try:
        k = int(row["frame"])
        vals = {c: float(row[c]) if row[c] not in ("", None) else math.nan
                for c in ("distance_m", "roll_rad", "pitch_rad", "yaw_rad")}
        vals["tilt_rad"] = float(row["tilt_rad"]) if row.get("tilt_rad") not in ("", None) else math.hypot(
            vals["pitch_rad"], vals["yaw_rad"])
    except (TypeError, ValueError):
        raise InputError(f"{where}: not a number in {row}") from None
    try:
        vals["t"] = float(row["t"]) if row.get("t") not in ("", None) else math.nan
    except ValueError:
        raise InputError(f"{where}: t {row['t']!r} is not a number") from None
    for c in ("tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad", "sigma_distance_m", "sigma_rotation_rad"):
        if row.get(c) not in (None, ""):
            try:
                vals[c] = float(row[c])
            except ValueError:
                raise InputError(f"{where}: not a number in column {c}") from None
    try:  # truth files have no status: every step is known
        vals["status"] = StepStatus(row.get("status") or "ok")
    except ValueError:
        raise InputError(f"{where}: unknown status {row.get('status')!r} (one of "
                         f"{', '.join(map(str, StepStatus))})") from None
    try:
        vals["n_matches"] = int(float(row["n_matches"])) if row.get("n_matches") not in (None, "") else 0
    except (ValueError, OverflowError):
        raise InputError(f"{where}: n_matches {row['n_matches']!r} is not a number") from None
    cell = row.get("beside_wall")
    if cell not in (None, "", "0", "1"):
        raise InputError(f"{where}: beside_wall {cell!r} is not 0 or 1")
    vals["beside_wall"] = cell == "1"
    cell = row.get("ring_ratio")
    try:  # empty (or nan) where the step was not in the lumen scale's sample
        vals["ring_ratio"] = float(cell) if cell not in (None, "") else math.nan
    except ValueError:
        raise InputError(f"{where}: ring_ratio {cell!r} is not a number") from None
    if not (math.isnan(vals["ring_ratio"]) or 0 < vals["ring_ratio"] < math.inf):
        raise InputError(f"{where}: ring_ratio {cell!r} is not a positive number")
    for c in ("scale_link", "scale_link_sd", "chain_factor"):  # empty (or nan) where there is none
        cell = row.get(c)
        try:
            vals[c] = float(cell) if cell not in (None, "") else math.nan
        except ValueError:
            raise InputError(f"{where}: {c} {cell!r} is not a number") from None
        if math.isinf(vals[c]) or (c != "scale_link" and vals[c] <= 0):
            raise InputError(f"{where}: {c} {cell!r} is not a {'finite' if c == 'scale_link' else 'positive'} number")
    vals["label"] = row.get("label") or ""
    return k, vals

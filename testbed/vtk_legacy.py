"""Surfaces in VTK's legacy format (``.vtk``, ``DATASET POLYDATA``), as the field's gut models ship them.

The Edinburgh Gut Cell Atlas models (Comparative-Pathology/GCA-Models; the CT gut in ``../shared/data/anatomy``)
keep every surface as an ASCII legacy VTK file, which trimesh does not read. This reader takes what a surface needs:

- ``POINTS n type``: the vertices (``float`` or ``double``; any of VTK's numeric types).
- ``POLYGONS`` and ``TRIANGLE_STRIPS``: faces, in both cell layouts -- the classic one (``POLYGONS n size``, then
  per cell its point count and its point ids) and the one VTK writes since file version 5.1 (``POLYGONS n_offsets
  n_ids`` followed by ``OFFSETS type`` and ``CONNECTIVITY type`` arrays). Polygons of more than three points are
  split into a fan of triangles from their first point, strips into their triangles (every other one turned so
  that all keep the strip's winding).
- ``ASCII`` and ``BINARY`` (big-endian, as the format defines it).

``VERTICES`` and ``LINES`` cells, ``METADATA`` blocks and a dataset's ``FIELD`` arrays are read past; ``POINT_DATA``, ``CELL_DATA`` and
anything after them (attributes: normals, scalars) end the reading, since the geometry is complete by then. Any
other dataset (``UNSTRUCTURED_GRID``, ``STRUCTURED_POINTS``...) is refused: it is not a surface. Every refusal
names the file, the line (ASCII: the section's line; binary: its byte offset) and what is wrong.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from bodyslam.errors import InputError

__all__ = ["read_polydata"]

# legacy type names -> big-endian numpy dtypes (VTK's "long" is 64-bit in the files its writers produce)
_TYPES = {"bit": None, "unsigned_char": ">u1", "char": ">i1", "unsigned_short": ">u2", "short": ">i2",
          "unsigned_int": ">u4", "int": ">i4", "unsigned_long": ">u8", "long": ">i8", "float": ">f4",
          "double": ">f8", "vtktypeint8": ">i1", "vtktypeuint8": ">u1", "vtktypeint16": ">i2",
          "vtktypeuint16": ">u2", "vtktypeint32": ">i4", "vtktypeuint32": ">u4", "vtktypeint64": ">i8",
          "vtktypeuint64": ">u8", "vtkidtype": ">i8"}
_CELLS = ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS")
_SECTIONS = ("POINTS", "METADATA", "FIELD", "POINT_DATA", "CELL_DATA") + _CELLS
_KEYWORD_LINE = re.compile(rb"^[ \t]*[A-Za-z]", re.M)
_OFFSETS_NEXT = re.compile(rb"\s*OFFSETS\b", re.I)
_METADATA_NEXT = re.compile(rb"\s*METADATA\b", re.I)
_BLANK_LINE = re.compile(rb"\n[ \t]*\r?\n|\Z")
_NL = b"\n"


class _Reader:
    """A cursor over the file's bytes: keyword lines, then ``count`` values as text or as big-endian binary."""

    def __init__(self, path: Path, data: bytes):
        self.path, self.data, self.pos = path, data, 0
        self.binary = False

    def where(self, pos: int | None = None) -> str:
        pos = self.pos if pos is None else pos
        if self.binary:
            return f"byte {pos}"
        return f"line {self.data.count(_NL, 0, pos) + 1}"

    def fail(self, msg: str, pos: int | None = None):
        raise InputError(f"{self.path}: {self.where(pos)}: {msg}")

    def line(self) -> tuple[list[str], int] | None:
        """The next non-blank line's words and where it starts; None at the end of the file."""
        n = len(self.data)
        while self.pos < n:
            start = self.pos
            end = self.data.find(_NL, start)
            end = n if end < 0 else end
            self.pos = end + 1
            raw = self.data[start:end].strip()
            if raw:
                try:
                    return raw.decode("ascii").split(), start
                except UnicodeDecodeError:
                    self.fail("expected a keyword line, found binary data (a section's data longer than it says?)",
                              start)
        return None

    def values(self, count: int, vtk_type: str, what: str, at: int) -> np.ndarray:
        """``count`` values of ``vtk_type`` right after the current keyword line."""
        dtype = _TYPES.get(vtk_type.lower(), "missing")
        if dtype == "missing":
            self.fail(f"{what}: unknown data type {vtk_type!r}", at)
        if dtype is None:
            self.fail(f"{what}: data type 'bit' is not supported", at)
        if count < 0:
            self.fail(f"{what}: negative count {count}", at)
        if self.binary:
            size = count * np.dtype(dtype).itemsize
            if self.pos + size > len(self.data):
                self.fail(f"{what}: {count} {vtk_type} values need {size} bytes, the file ends after "
                          f"{len(self.data) - self.pos}", at)
            out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
            self.pos += size
            return out.astype(np.float64 if out.dtype.kind == "f" else np.int64)
        m = _KEYWORD_LINE.search(self.data, self.pos)
        end = len(self.data) if m is None else m.start()
        words = self.data[self.pos:end].split()
        if len(words) < count:
            self.fail(f"{what}: {count} values expected, {len(words)} follow"
                      + ("" if m is None else f" before {self.where(m.start())}"), at)
        try:
            out = np.array(words[:count], dtype=np.float64)
        except ValueError:
            bad = next(w for w in words[:count] if not _is_number(w))
            self.fail(f"{what}: {bad.decode('ascii', 'replace')!r} is not a number", at)
        if len(words) > count:
            self.fail(f"{what}: {count} values expected, {len(words)} follow", at)
        self.pos = end
        if np.dtype(dtype).kind != "f":
            if not np.all(out == np.round(out)):
                self.fail(f"{what}: ids must be whole numbers", at)
            out = out.astype(np.int64)
        return out


def _is_number(w: bytes) -> bool:
    try:
        float(w)
    except ValueError:
        return False
    return True


def _int(words: list[str], i: int, r: _Reader, at: int) -> int:
    try:
        return int(words[i])
    except (IndexError, ValueError):
        r.fail(f"{' '.join(words)!r}: expected a whole number in field {i + 1}", at)


def _cells_classic(r: _Reader, words: list[str], at: int) -> tuple[np.ndarray, np.ndarray]:
    """``NAME n size`` then ``size`` ints: per cell its point count and ids. Returns ``(counts, ids)``."""
    n, size = _int(words, 1, r, at), _int(words, 2, r, at)
    a = r.values(size, "int", words[0], at)
    if n and size == 4 * n and np.all(a[::4] == 3):  # all triangles: the usual surface, without a loop
        return np.full(n, 3, np.int64), a.reshape(n, 4)[:, 1:].ravel()
    counts, keep, i = np.zeros(n, np.int64), np.ones(size, bool), 0
    for c in range(n):
        if i >= size:
            r.fail(f"{words[0]}: {n} cells declared, the {size} values hold {c}", at)
        k = int(a[i])
        if k < 0 or i + 1 + k > size:
            r.fail(f"{words[0]}: cell {c} has {k} points, past the section's {size} values", at)
        counts[c], keep[i] = k, False
        i += 1 + k
    if i != size:
        r.fail(f"{words[0]}: {n} cells use {i} of the {size} values declared", at)
    return counts, a[keep]


def _cells_offsets(r: _Reader, words: list[str], at: int) -> tuple[np.ndarray, np.ndarray]:
    """File version >= 5.1: ``NAME n_offsets n_ids``, then ``OFFSETS type`` and ``CONNECTIVITY type``."""
    n_off, n_ids = _int(words, 1, r, at), _int(words, 2, r, at)
    arrays = {}
    for name in ("OFFSETS", "CONNECTIVITY"):
        got = r.line()
        if got is None or got[0][0].upper() != name or len(got[0]) < 2:
            r.fail(f"{words[0]}: expected an {name} array", at if got is None else got[1])
        arrays[name] = r.values(n_off if name == "OFFSETS" else n_ids, got[0][1], f"{words[0]} {name}", got[1])
    off, conn = arrays["OFFSETS"], arrays["CONNECTIVITY"]
    if n_off == 0:
        return np.zeros(0, np.int64), conn[:0]
    if off[0] != 0 or off[-1] != n_ids or np.any(np.diff(off) < 0):
        r.fail(f"{words[0]}: OFFSETS must rise from 0 to the {n_ids} ids", at)
    return np.diff(off), conn


def _peek_offsets(r: _Reader) -> bool:
    """Whether the next keyword line is ``OFFSETS`` (the 5.1 layout), without moving the cursor (looking at the raw
    bytes: a binary file's classic cell data follows at once)."""
    return _OFFSETS_NEXT.match(r.data, r.pos) is not None


def _skip_metadata(r: _Reader) -> None:
    """A ``METADATA`` block (information keys, component names; text even in binary files) ends at a blank line."""
    r.pos = _BLANK_LINE.search(r.data, r.pos - 1).end()


def _skip_field(r: _Reader, words: list[str], at: int) -> None:
    """``FIELD name n``: n arrays (``name components tuples type`` and their values), none of them geometry."""
    for _ in range(_int(words, 2, r, at)):
        got = r.line()
        if got is None:
            r.fail("FIELD: the file ends before its arrays", at)
        a, a_at = got
        if a[0].upper() == "NULL_ARRAY":
            continue
        if len(a) < 4:
            r.fail(f"FIELD array {' '.join(a)!r}: expected 'name components tuples type'", a_at)
        r.values(_int(a, 1, r, a_at) * _int(a, 2, r, a_at), a[3], f"FIELD array {a[0]}", a_at)
        if _METADATA_NEXT.match(r.data, r.pos):
            r.line()
            _skip_metadata(r)


def _starts(counts: np.ndarray) -> np.ndarray:
    """Where each cell's ids begin in the flat id array."""
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def _triangles(polys: list[tuple[np.ndarray, np.ndarray]], strips: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Polygons as fans from their first point (grouped by size, no loop over cells); strips as their triangles,
    every other one turned to keep the strip's winding."""
    tri = []
    for counts, ids in polys:
        starts = _starts(counts)
        for k in np.unique(counts[counts >= 3]):
            cell = ids[starts[counts == k][:, None] + np.arange(k)]  # (cells of k points, k)
            j = np.arange(1, k - 1)
            tri.append(np.stack([np.repeat(cell[:, :1], k - 2, axis=1), cell[:, j], cell[:, j + 1]], axis=-1)
                       .reshape(-1, 3))
    for counts, ids in strips:
        for s0, k in zip(_starts(counts), counts):
            c = ids[s0:s0 + k]
            for j in range(k - 2):
                tri.append((c[[j, j + 1, j + 2]] if j % 2 == 0 else c[[j + 1, j, j + 2]])[None])
    return np.vstack(tri).astype(np.int64) if tri else np.zeros((0, 3), np.int64)


def read_polydata(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (n, 3) float64, triangles (m, 3) int64)`` of a legacy VTK POLYDATA file (module docstring).

    Raises
    ------
    InputError
        Not found, not a legacy VTK file, not POLYDATA, or a section that does not hold what it declares (the
        file, the line or byte, and what).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: mesh file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    r = _Reader(path, data)
    nl = data.find(_NL)
    if not data[:len(data) if nl < 0 else nl].strip().lower().startswith(b"# vtk datafile version"):
        r.fail("not a legacy VTK file (its first line must be '# vtk DataFile Version x.x')", 0)
    title_end = -1 if nl < 0 else data.find(_NL, nl + 1)  # the title line may hold anything: skipped as it is
    if title_end < 0:
        r.fail("ends within its header (version, title, ASCII or BINARY, DATASET)", len(data))
    r.pos = title_end + 1
    fmt = r.line()
    if fmt is None or fmt[0][0].upper() not in ("ASCII", "BINARY"):
        r.fail("the third line must say ASCII or BINARY", None if fmt is None else fmt[1])
    r.binary = fmt[0][0].upper() == "BINARY"
    ds = r.line()
    if ds is None or ds[0][0].upper() != "DATASET":
        r.fail("expected 'DATASET POLYDATA'", None if ds is None else ds[1])
    if len(ds[0]) < 2 or ds[0][1].upper() != "POLYDATA":
        r.fail(f"dataset {' '.join(ds[0][1:]) or '(none)'} is not a surface: only DATASET POLYDATA is read", ds[1])
    pts, polys, strips = None, [], []
    while (got := r.line()) is not None:
        words, at = got
        key = words[0].upper()
        if key in ("POINT_DATA", "CELL_DATA"):
            break  # attributes only from here on
        if key == "POINTS":
            if len(words) < 3:
                r.fail(f"{' '.join(words)!r}: expected 'POINTS n type'", at)
            n = _int(words, 1, r, at)
            pts = r.values(3 * n, words[2], "POINTS", at).reshape(n, 3)
            if not np.all(np.isfinite(pts)):
                r.fail("POINTS: coordinates must be finite", at)
        elif key in _CELLS:
            if len(words) < 3:
                r.fail(f"{' '.join(words)!r}: expected '{key} n size'", at)
            cells = _cells_offsets(r, words, at) if _peek_offsets(r) else _cells_classic(r, words, at)
            if key == "POLYGONS":
                polys.append(cells)
            elif key == "TRIANGLE_STRIPS":
                strips.append(cells)
        elif key == "METADATA":
            _skip_metadata(r)
        elif key == "FIELD":
            _skip_field(r, words, at)
        else:
            r.fail(f"unexpected {words[0]!r} (known sections: {', '.join(_SECTIONS)})", at)
    if pts is None:
        r.fail("no POINTS section", len(data))
    tri = _triangles(polys, strips)
    if len(tri) == 0:
        raise InputError(f"{path}: no POLYGONS or TRIANGLE_STRIPS: the file holds no surface")
    if tri.min() < 0 or tri.max() >= len(pts):
        raise InputError(f"{path}: a face names point {int(tri.max()) if tri.max() >= len(pts) else int(tri.min())}"
                         f", the file has {len(pts)} points (0-{len(pts) - 1})")
    return pts, tri

"""Scenarios: TOML files that fully determine a testbed run given a seed (SPEC.md "Standard scenarios").

Shipped scenarios live in ``testbed/scenarios/NAME.toml``; a scenario argument is either such a name or a path to a
TOML file. A scenario may name another as its ``base`` (a shipped name): it is that scenario with its own keys
replacing the base's, table by table (``realistic_exam`` is ``realistic`` at a whole exam's pace). ``--set
section.key=value`` overrides one field (the value is parsed as TOML, so ``0.012``, ``true``,
``[1, 2]`` and ``"text"`` work; a bare word is taken as a string).

:func:`build_world` turns a scenario and a seed into the objects the testbed renders. Independent random streams
(path, texture, motion, sensor noise) are spawned from the seed, so changing e.g. the motion settings does not
change the path of the same seed.
"""

from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import dataclass, fields
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from bodyslam.camera import CameraModel, camera_from_dict
from bodyslam.errors import ConfigError, InputError
from testbed.centerline import Centerline, procedural_centerline
from testbed.content import Debris, Fluid, LumenContent
from testbed.motility import Peristalsis
from testbed.motion import MotionConfig
from testbed.artifacts import Bubbles, CameraOptics
from testbed.render import RENDER_BACKENDS, Lighting, SensorNoise
from testbed.texture import Texture, procedural_mucosa, texture_from_image
from testbed.tube import Folds, Tube

__all__ = ["load_scenario", "apply_overrides", "build_world", "World", "scenario_names"]


def scenario_names() -> list[str]:
    d = resources.files("testbed") / "scenarios"
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".toml"))


def load_scenario(name_or_path: str, overrides: list[str] | None = None) -> dict[str, Any]:
    """Read a scenario by shipped name or file path and apply ``section.key=value`` overrides.

    Raises
    ------
    ConfigError
        Unknown scenario, malformed TOML or a bad override (the message names it).
    """
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise ConfigError(f"scenario file {p} not found")
        text, origin = p.read_text(encoding="utf-8"), str(p)
    else:
        res = resources.files("testbed") / "scenarios" / f"{name_or_path}.toml"
        if not res.is_file():
            raise ConfigError(f"unknown scenario {name_or_path!r} (shipped: {', '.join(scenario_names())})")
        text, origin = res.read_text(encoding="utf-8"), f"testbed/scenarios/{name_or_path}.toml"
    try:
        scn = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{origin}: malformed TOML ({exc})") from None
    base = scn.pop("base", None)
    if base is not None:
        if not isinstance(base, str) or Path(base).suffix or base in _loading:
            raise ConfigError(f"{origin}: base must name another shipped scenario, got {base!r}")
        _loading.append(base)
        try:
            parent = load_scenario(base)
        except ConfigError as exc:
            raise ConfigError(f"{origin}: its base: {exc}") from None
        finally:
            _loading.pop()
        for k in ("_origin", "name", "description"):  # the scenario's own (its file's name where it gives none)
            parent.pop(k, None)
        scn = _merged(parent, scn)
    scn.setdefault("name", p.stem)
    scn["_origin"] = origin
    return apply_overrides(scn, overrides or [])


_loading: list[str] = []  # the bases being read (a scenario that is its own base, at any depth, is refused)


def _merged(base: dict, own: dict) -> dict:
    """``base`` with ``own``'s keys in its place, tables merged key by key (nested tables too)."""
    out = copy.deepcopy(base)
    for k, v in own.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


# Keys the world reads from its plain sections with a default (so a scenario file may leave them out), with their
# kind: what ``--set`` may add there besides the keys the scenario already has. Sections read into dataclasses
# (lighting, noise, motion, motility, fluid, debris, artifacts, optics, rf.pathloss, rf.toa, rf.channel) and
# [texture] (keyword arguments) are checked by those when the world is built; the other papers' systems read their
# own sections, where an override may only replace a key the scenario has.
_NUM, _INT, _BOOL, _STR, _LIST, _TABLE = "a number", "an integer", "true or false", "a string", "a list", "a table"
OPTIONAL_KEYS: dict[str, dict[str, str]] = {
    "sequence": {"frames": _INT, "frame_rate_hz": _NUM, "duration_s": _NUM, "interval_s": _NUM},
    "camera": {"model": _STR, "width": _INT, "height": _INT, "fov_deg": _NUM, "fx": _NUM, "fy": _NUM, "cx": _NUM,
               "cy": _NUM, "k": _LIST},
    "path": {"kind": _STR, "file": _STR, "length_m": _NUM, "abdomen_box_m": _LIST,
             "min_self_distance_diameters": _NUM},
    "tube": {"radius_m": _NUM, "radius_end_m": _NUM, "radius_variation_m": _NUM, "radius_wavelength_m": _NUM,
             "contraction_frac": _NUM, "contraction_length_m": _NUM, "contraction_spacing_m": _NUM,
             "radius_in_meta_m": _NUM, "radius_sd_in_meta_m": _NUM, "shape_sd_in_meta_rel": _NUM, "sections": _INT,
             "ring_spacing_m": _NUM, "fold_depth_frac": _NUM,
             "fold_spacing_m": _NUM, "fold_width_m": _NUM, "fold_coverage": _NUM, "lobes": _INT,
             "lobe_depth_frac": _NUM, "lobe_twist_rad_per_m": _NUM},
    "render": {"backend": _STR},
    "rear_camera": {"enabled": _BOOL, "baseline_m": _NUM},
    "output": {"depth": _BOOL},
    "rf": {"enabled": _BOOL, "layout": _STR, "file": _STR, "n_side": _INT, "width_m": _NUM, "plane_y_m": _NUM,
           "both_sides": _BOOL, "size_m": _LIST, "pathloss": _TABLE, "toa": _TABLE, "channel": _TABLE},
}
_CHECKED_ELSEWHERE = {"lighting", "noise", "motion", "motility", "fluid", "debris", "artifacts", "optics", "texture",
                      "rf.pathloss", "rf.toa", "rf.channel"}


def _kind_of(value) -> str:
    for typ, kind in ((bool, _BOOL), (int, _INT), (float, _NUM), (str, _STR), (list, _LIST), (dict, _TABLE)):
        if isinstance(value, typ):  # bool before int: True is an int to Python
            return kind
    return type(value).__name__


def _check_override(key: str, sec_name: str, name: str, value, old) -> None:
    """Refuse an override whose key the scenario does not know or whose value is of the wrong kind."""
    known = OPTIONAL_KEYS.get(sec_name, {})
    if old is None and name not in known and sec_name not in _CHECKED_ELSEWHERE:
        raise ConfigError(f"--set {key}: unknown key {name!r} in [{sec_name}]"
                          + (f" (known: {', '.join(sorted(known))})" if known else " (not in this scenario)"))
    want = known.get(name) or (None if old is None else _kind_of(old))
    if want is None:
        return
    got = _kind_of(value)
    ok = got == want or (want == _NUM and got == _INT)
    if not ok:
        raise ConfigError(f"--set {key}: expected {want}, got {value!r}")


def apply_overrides(scn: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """``section.key=value`` overrides (the value in TOML syntax; a bare word is a string), each checked: the key
    must be one the scenario has or the world reads (:data:`OPTIONAL_KEYS`; dataclass sections are checked when the
    world is built) and the value of the same kind (a number for a number)."""
    out = copy.deepcopy(scn)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set expects section.key=value, got {item!r}")
        key, raw = item.split("=", 1)
        key = key.strip()
        parts = key.split(".")
        if len(parts) < 2 or not all(parts):
            raise ConfigError(f"--set key must be section.key, got {key!r}")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {key}: {part!r} is not a section")
        old = node.get(parts[-1])
        if isinstance(old, dict):
            raise ConfigError(f"--set {key}: [{key}] is a section, not a value")
        _check_override(key, ".".join(parts[:-1]), parts[-1], value, old)
        node[parts[-1]] = value
    return out


def section(scn: dict, name: str) -> dict:
    """A scenario's ``[name]`` table (empty when absent); anything else there is a ConfigError."""
    sec = scn.get(name, {})
    if not isinstance(sec, dict):
        raise ConfigError(f"scenario section [{name}] must be a table")
    return sec


def _dataclass_from(cls, sec: dict, sec_name: str):
    names = {f.name for f in fields(cls)}
    unknown = set(sec) - names
    if unknown:
        raise ConfigError(f"[{sec_name}] has unknown key(s) {sorted(unknown)}; known: {sorted(names)}")
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in sec.items()}
    try:
        return cls(**kw)
    except TypeError as exc:
        raise ConfigError(f"[{sec_name}]: {exc}") from None


@dataclass(frozen=True, eq=False)
class World:
    """Everything a testbed run renders from, built from a scenario and a seed."""

    scenario: dict
    seed: int
    n_frames: int
    camera: CameraModel
    tube: Tube
    texture: Texture
    lighting: Lighting
    noise: SensorNoise
    motion: MotionConfig
    write_depth: bool
    rngs: dict
    render_backend: str = "raycast"
    rear_baseline_m: float | None = None  # a second, rear-facing camera this far behind the front lens (None: off)
    bubbles: Bubbles = Bubbles()
    rf: dict | None = None  # {"layout", "pathloss", "toa", "channel"} (testbed.rf), or None (off)
    optics: CameraOptics = CameraOptics()  # the capsule camera's imaging chain (field stop, overlay, JPEG ...)
    # the lumen radius meta.json tells the pipeline: None = this tube's mean (the ideal world), else a population
    # prior ([tube] radius_in_meta_m; the realistic testbed hides the true radius)
    radius_in_meta_m: float | None = None
    radius_sd_in_meta_m: float = 0.0  # ... and its stated 1-sigma (0: exact, the ideal world)
    shape_sd_in_meta_rel: float = 0.0  # the lumen's stated departure from a cylinder (meta.json lumen_shape_sd_rel)
    motility: Peristalsis = Peristalsis()  # contractions travelling along the gut ([motility]; off by default)
    content: LumenContent | None = None  # fluid and debris in the lumen ([fluid], [debris]; None: none)


def _radius_fn(sec: dict, rng: np.random.Generator):
    r0 = float(sec.get("radius_m", 0.015))
    r1 = float(sec.get("radius_end_m", r0))
    var = float(sec.get("radius_variation_m", 0.0))
    wl = float(sec.get("radius_wavelength_m", 0.15))
    if not (0.002 <= min(r0, r1) and max(r0, r1) <= 0.05):
        raise ConfigError(f"[tube] radius_m and radius_end_m (the radius at the gut's start and end) must be within "
                          f"0.002-0.05 m (2-50 mm), got {r0:g} and {r1:g} m")
    # contracted segments: narrowings by `contraction_frac` of the radius, `contraction_length_m` long, one every
    # `contraction_spacing_m` on average (positions drawn per seed); 0: none
    c_frac = float(sec.get("contraction_frac", 0.0))
    c_len = float(sec.get("contraction_length_m", 0.02))
    c_gap = float(sec.get("contraction_spacing_m", 0.15))
    if not (0 <= c_frac < 0.7 and c_len > 0 and c_gap > 0):
        raise ConfigError(f"[tube] contraction_frac must be in [0, 0.7), lengths positive; got {c_frac}, {c_len}, "
                          f"{c_gap}")
    ph = rng.uniform(0, 2 * math.pi, size=3)
    centres = np.cumsum(rng.exponential(c_gap, size=400)) if c_frac > 0 else np.zeros(0)

    def fn(s):
        s = np.asarray(s, dtype=np.float64)
        frac = s / max(s[-1], 1e-9) if s.size > 1 else np.zeros_like(s)
        wave = (np.sin(2 * math.pi * s / wl + ph[0]) + 0.5 * np.sin(2 * math.pi * s / (0.37 * wl) + ph[1])) / 1.5
        r = r0 + (r1 - r0) * frac + var * wave
        if c_frac > 0:
            near = centres[(centres > s.min() - 4 * c_len) & (centres < s.max() + 4 * c_len)]
            squeeze = np.zeros_like(s)
            for c in near:
                squeeze = np.maximum(squeeze, np.exp(-0.5 * ((s - c) / (c_len / 2.3548)) ** 2))
            r = r * (1.0 - c_frac * squeeze)
        return r

    return fn, max(r0, r1) + var


def build_world(scn: dict[str, Any], seed: int, n_frames: int | None = None) -> World:
    """Build camera, tube, texture, lighting and motion settings of a scenario for one seed."""
    if not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    ss = np.random.SeedSequence(seed)
    # (a stream added at the end leaves the others as they were: SeedSequence children depend on their index only)
    rngs = dict(zip(("path", "texture", "motion", "noise", "rf", "motility", "content"),
                    (np.random.default_rng(s) for s in ss.spawn(7))))
    seq = section(scn, "sequence")
    n = int(n_frames if n_frames is not None else seq.get("frames", 100))
    if n < 2:
        raise ConfigError(f"need at least 2 frames, got {n}")
    camera = camera_from_dict(section(scn, "camera"))

    tube_sec = dict(section(scn, "tube"))
    radius_fn, r_max = _radius_fn(tube_sec, rngs["path"])
    path = section(scn, "path")
    kind = path.get("kind", "procedural")
    if kind == "procedural":
        cl = procedural_centerline(
            float(path.get("length_m", 2.5)),
            rngs["path"],
            radius_fn=radius_fn,
            radius_max_m=r_max,
            abdomen_box_m=tuple(path.get("abdomen_box_m", (0.32, 0.24, 0.34))),
            min_self_distance_diameters=float(path.get("min_self_distance_diameters", 2.0)),
        )
    elif kind == "file":
        f = path.get("file")
        if not f:
            raise ConfigError("[path] kind = 'file' needs file = 'centerline.csv'")
        fp = Path(f)
        if not fp.is_absolute() and "_origin" in scn and Path(scn["_origin"]).exists():
            fp = Path(scn["_origin"]).parent / fp
        cl = Centerline.read_csv(fp)
        if "radius_m" in tube_sec:  # the scenario's radius profile replaces the file's
            cl = Centerline(cl.s_m, cl.points_w, cl.tangents_w, cl.normals_w, cl.binormals_w, radius_fn(cl.s_m))
    else:
        raise ConfigError(f"[path] kind must be 'procedural' or 'file', got {kind!r}")
    folds = Folds(
        depth_frac=float(tube_sec.get("fold_depth_frac", 0.0)),
        spacing_m=float(tube_sec.get("fold_spacing_m", 0.008)),
        width_m=float(tube_sec.get("fold_width_m", 0.002)),
        coverage=float(tube_sec.get("fold_coverage", 0.7)),
        lobes=int(tube_sec.get("lobes", 0)),
        lobe_depth_frac=float(tube_sec.get("lobe_depth_frac", 0.0)),
        lobe_twist_rad_per_m=float(tube_sec.get("lobe_twist_rad_per_m", 15.0)),
    )
    tube = Tube(cl, folds=folds, sections=int(tube_sec.get("sections", 96)),
                ring_spacing_m=float(tube_sec.get("ring_spacing_m", 0.0015)))

    tex = dict(section(scn, "texture"))
    tkind = tex.pop("kind", "procedural")
    if tkind == "procedural":
        try:
            texture = procedural_mucosa(rngs["texture"], **tex)
        except TypeError as exc:
            raise ConfigError(f"[texture]: {exc}") from None
    elif tkind == "image":
        if "file" not in tex:
            raise ConfigError("[texture] kind = 'image' needs file = 'texture.png'")
        try:
            texture = texture_from_image(tex["file"], float(tex.get("length_m", 0.1)))
        except InputError as exc:
            raise ConfigError(f"[texture]: {exc}") from None
    else:
        raise ConfigError(f"[texture] kind must be 'procedural' or 'image', got {tkind!r}")

    lighting = _dataclass_from(Lighting, section(scn, "lighting"), "lighting")
    noise = _dataclass_from(SensorNoise, section(scn, "noise"), "noise")
    msec = dict(section(scn, "motion"))
    msec.setdefault("frame_rate_hz", float(seq.get("frame_rate_hz", 2.0)))
    motion = _dataclass_from(MotionConfig, msec, "motion")
    out = section(scn, "output")
    backend = str(section(scn, "render").get("backend", "raycast"))
    if backend not in RENDER_BACKENDS:
        raise ConfigError(f"[render] backend must be one of {', '.join(RENDER_BACKENDS)}, got {backend!r}")
    rear = section(scn, "rear_camera")
    rear_baseline = None
    if rear.get("enabled", False):
        rear_baseline = float(rear.get("baseline_m", 0.026))
        if not 0.0 <= rear_baseline <= 0.05:
            raise ConfigError(f"[rear_camera] baseline_m must be within 0-0.05 m, got {rear_baseline}")
    bubbles = _dataclass_from(Bubbles, section(scn, "artifacts"), "artifacts")
    optics = _dataclass_from(CameraOptics, section(scn, "optics"), "optics")
    rf = _rf_from(section(scn, "rf"), Path(scn["_origin"]).parent if "_origin" in scn else None)
    told = tube_sec.get("radius_in_meta_m")
    if told is not None and not (isinstance(told, (int, float)) and 0.002 <= told <= 0.05):
        raise ConfigError(f"[tube] radius_in_meta_m must be a radius of 2-50 mm (in m), got {told!r}")
    told_sd = tube_sec.get("radius_sd_in_meta_m", 0.0)
    if not (isinstance(told_sd, (int, float)) and 0.0 <= told_sd <= 0.02) or (told_sd and told is None):
        raise ConfigError(f"[tube] radius_sd_in_meta_m must be 0-20 mm (in m), with radius_in_meta_m, got {told_sd!r}")
    told_shape = tube_sec.get("shape_sd_in_meta_rel", 0.0)
    if isinstance(told_shape, bool) or not (isinstance(told_shape, (int, float)) and 0.0 <= told_shape < 1.0):
        raise ConfigError(f"[tube] shape_sd_in_meta_rel must be a fraction in 0-1, got {told_shape!r}")
    for name in ("motility", "fluid"):
        if "stretches" in section(scn, name):
            raise ConfigError(f"[{name}] stretches are drawn per seed, not set")
    motility = _dataclass_from(Peristalsis, section(scn, "motility"), "motility")
    motility = motility.drawn(cl.length_m, rngs["motility"])
    if motility.active and backend != "raycast":
        raise ConfigError("[motility] (a moving wall) needs the raycast backend: pyrender uploads its mesh once")
    content = LumenContent.draw(_dataclass_from(Fluid, section(scn, "fluid"), "fluid"),
                                _dataclass_from(Debris, section(scn, "debris"), "debris"), cl.length_m,
                                rngs["content"])
    return World(scn, seed, n, camera, tube, texture, lighting, noise, motion, bool(out.get("depth", True)), rngs,
                 backend, rear_baseline, bubbles, rf, optics, None if told is None else float(told), float(told_sd),
                 float(told_shape), motility, content if content.active else None)


def rf_channel(scn: dict):
    """The scenario's ``[rf.channel]`` as a :class:`testbed.rf.ChannelModel` (ideal when absent): what the real
    channel departs from the calibration by. For scoring only (the bound under it); the pipeline is never told."""
    from testbed.rf import ChannelModel

    return _dataclass_from(ChannelModel, section(section(scn, "rf"), "channel"), "rf.channel")


def _rf_from(sec: dict, base_dir: Path | None) -> dict | None:
    """RF emulation settings; on by default with the thesis sensor grids (``[rf] enabled = false`` turns it off)."""
    from testbed.rf import PathLossModel, TOAModel, layout_from_config

    if not sec.get("enabled", True):
        return None
    pl = {k: (tuple(v) if isinstance(v, list) else v) for k, v in sec.get("pathloss", {}).items()}
    return {"layout": layout_from_config(sec, base_dir),
            "pathloss": _dataclass_from(PathLossModel, pl, "rf.pathloss"),
            "toa": _dataclass_from(TOAModel, sec.get("toa", {}), "rf.toa"),
            "channel": rf_channel({"rf": sec})}

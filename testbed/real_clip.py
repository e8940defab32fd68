"""Clips of known motion made from one real capsule frame: real texture and optics, known geometry.

A real clip's truth is never known, and the testbed's own frames are rendered texture. This module makes a
sequence from a real frame: frame i is the real frame seen from a camera that has advanced i x ``step_m`` along a
lumen's axis and rolled i x ``roll_rad`` about its optical axis, the real pixels carried to where that lumen puts
them (one remap from the original frame, never a chain of them). The frame is taken as the wall's texture as the
first camera saw it. The lumen (:class:`Lumen`): a cylinder of ``radius_m``, or folded (``lobes``, ``lobe_depth``:
r(phi) = R (1 + depth cos(lobes phi))), with the camera on its axis or ``offset_m`` off it; its axis runs toward
the frame's darkest area (``axis="dark"``, where a lumen-facing frame shows the lumen) or along the optical axis.

Light (``light``): ``capsule`` (default) -- the light moves with the camera: each pixel's brightness is scaled by
cos(incidence) / range^2 against the same at the first frame (a point source at the lens, Lambertian wall), then
the frame's median is brought back to the first frame's, as a capsule's light control does; ``baked`` -- the
first frame's shading travels with the wall. The field stop, the black corners and the burned-in logo stay where
they are, as on a capsule (:func:`field_mask`: the largest lit area's convex hull, found here without the
pipeline's own field-of-view detection); each frame gets its own sensor noise and JPEG round trip.

The lens is by default the one `bodyslam batch` assumes without a calibration (equidistant, 156 deg across the
shorter side), so a clip's geometry is exactly what the pipeline's camera model says; another field of view
(``fov_deg``) made into a plain folder shows what a wrong lens assumption does. The field stop's corners lie past
the lens's stated field, and the equidistant model is carried on there.

Written like ``testbed simulate``'s sequences (SPEC.md "Files"): ``frames/NNNNNN.png``, ``meta.json`` (the
assumed lens and the population's lumen-radius prior: the true radius is hidden), and for scoring only
``groundtruth.tum``, ``motion_truth.csv`` (each step's truth; label as given, else empty) and ``truth.json`` (the
parameters). ``testbed score-motion`` scores a ``motion.csv`` against it. What it cannot show: a lumen that
deforms between frames, things that move on their own (bubbles, debris), motion blur, and a frame's parallax
beyond the model -- the texture is one picture.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam import __version__
from bodyslam.camera import FisheyeCamera
from bodyslam.errors import InputError
from bodyslam.exam.batch import DEFAULT_FOV_DEG, DEFAULT_RADIUS_M, DEFAULT_RADIUS_SD_M, DEFAULT_SHAPE_SD_REL
from bodyslam.geometry import relative_motion
from bodyslam.io import frame_name, prepare_output_dir, read_image, write_csv, write_image, write_json, write_tum
from bodyslam.meta import write_meta
from testbed.simulate import clear_earlier_sequence

__all__ = ["Lumen", "field_mask", "axis_direction", "fill_outside", "source_map", "magnification", "tube_view",
           "make_clip"]

# what `bodyslam batch` assumes for a plain folder: the lens without a calibration, and the population's lumen
# radius prior and shape share, which meta.json states (the clip's true radius is hidden)
FOV_DEG = DEFAULT_FOV_DEG
PRIOR_RADIUS_M, PRIOR_RADIUS_SD_M, PRIOR_SHAPE_SD_REL = DEFAULT_RADIUS_M, DEFAULT_RADIUS_SD_M, DEFAULT_SHAPE_SD_REL
MAX_MAGNIFICATION = 2.0  # past it a frame's texture is the real frame's pixels blurred (truth.json counts them)
MAP_STEP = 4  # pixels between the nodes where the geometry is cast (the maps are interpolated between them)


def _bilinear(grid: np.ndarray, H: int, W: int) -> np.ndarray:
    """``grid`` (gh, gw, c) at nodes j * MAP_STEP, interpolated to every pixel of an H x W image."""
    y = np.arange(H) / MAP_STEP
    x = np.arange(W) / MAP_STEP
    y0 = np.minimum(y.astype(int), grid.shape[0] - 2)
    x0 = np.minimum(x.astype(int), grid.shape[1] - 2)
    fy, fx = (y - y0)[:, None, None], (x - x0)[None, :, None]
    g00, g01 = grid[y0][:, x0], grid[y0][:, x0 + 1]
    g10, g11 = grid[y0 + 1][:, x0], grid[y0 + 1][:, x0 + 1]
    return ((1 - fy) * ((1 - fx) * g00 + fx * g01) + fy * ((1 - fx) * g10 + fx * g11)).astype(np.float32)


def _odd(x: float) -> int:
    return max(3, int(round(x)) | 1)


def field_mask(rgb: np.ndarray) -> np.ndarray:
    """The frame's field: the convex hull of the largest connected area brighter than the black corners.

    Made here without the pipeline's own field-of-view detection (that is what a clip checks); the opening takes off
    burned-in text that touches the field."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    lit = (cv2.medianBlur(gray, 5) > 20).astype(np.uint8)
    k = _odd(31 * min(gray.shape) / 576)  # wider than a logo's strokes on a 576-px PillCam frame
    lit = cv2.morphologyEx(lit, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(lit, connectivity=8)
    if n < 2:
        raise InputError("no lit field found in the frame (is it all black?)")
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    pts = np.column_stack(np.nonzero(labels == big)[::-1]).astype(np.int32)
    mask = np.zeros_like(gray)
    cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    return mask.astype(bool)


def axis_direction(rgb: np.ndarray, mask: np.ndarray, cam: FisheyeCamera, how: str) -> np.ndarray:
    """The tube's axis in the frame's camera: the optical axis, or the ray through the darkest blurred point."""
    if how == "centre":
        return np.array([0.0, 0.0, 1.0])
    sigma = 15.0 * min(mask.shape) / 576  # the dark lumen's scale, not the texture's
    gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), sigma)
    k = _odd(6 * sigma)  # 3 blur widths inside the field: the black beyond it does not pull the blur there
    inner = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    if not inner.any():
        raise InputError("the frame's lit field is too small to find its darkest area in")
    gray[~inner] = np.inf
    v, u = np.unravel_index(int(np.argmin(gray)), gray.shape)
    ray, _ = cam.unproject(np.array([[u, v]], dtype=np.float64))
    return ray[0] / np.linalg.norm(ray[0])


def fill_outside(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The field's content carried past the field stop (inpainted), so that a view that brings in wall from just
    outside the stop gets texture, not the stop's black edge moving with the scene."""
    small = cv2.resize(rgb, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    msmall = cv2.resize(mask.astype(np.uint8), None, fx=0.25, fy=0.25, interpolation=cv2.INTER_NEAREST)
    msmall = cv2.erode(msmall, np.ones((3, 3), np.uint8))
    far = cv2.resize(cv2.inpaint(small, 1 - msmall, 9, cv2.INPAINT_TELEA), rgb.shape[1::-1],
                     interpolation=cv2.INTER_LINEAR)
    far[mask] = rgb[mask]
    return far


@dataclass(frozen=True)
class Lumen:
    """The lumen the frame is moved through, in the first frame's camera coordinates (metres).

    Cross-section ``r(phi) = radius_m * (1 + lobe_depth * cos(lobes * phi))`` about ``axis`` (``lobes`` 0: a
    circle); the camera starts ``offset_m`` (perpendicular to the axis) from it and moves parallel to it."""

    axis: np.ndarray
    radius_m: float = PRIOR_RADIUS_M
    lobes: int = 0
    lobe_depth: float = 0.0
    offset_m: float = 0.0

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        a = self.axis / np.linalg.norm(self.axis)
        e1 = np.cross(a, [0.0, 1.0, 0.0] if abs(a[1]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(a, e1)

    def _r(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r(phi) and dr/dphi."""
        k, a = self.lobes, self.lobe_depth
        return self.radius_m * (1.0 + a * np.cos(k * phi)), -self.radius_m * a * k * np.sin(k * phi)

    def hit(self, c: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First wall point along each ray ``c + t v`` (``v`` unit, (n, 3)): its range ``t`` (inf where none within
        a metre) and the wall's outward unit normal there. The crossing is bracketed on 64 ranges from 0.1 mm to
        1 m (each 16% beyond the last) and bisected; a fold thinner than that spacing can be missed."""
        e1, e2 = self.basis()
        cx, cy, vx, vy = float(c @ e1), float(c @ e2), v @ e1, v @ e2
        t = np.full(len(v), np.inf)
        normal = np.zeros_like(v)
        grid = np.geomspace(1e-4, 1.0, 64)
        for lo in range(0, len(v), 40_000):
            sl = slice(lo, lo + 40_000)
            x, y = cx + grid[None, :] * vx[sl, None], cy + grid[None, :] * vy[sl, None]
            g = np.hypot(x, y) - self._r(np.arctan2(y, x))[0]
            out = g > 0
            has = out.any(axis=1)
            j = np.argmax(out, axis=1)
            a = np.where(j > 0, grid[np.maximum(j - 1, 0)], 0.0)
            b = grid[j]
            for _ in range(40):  # bisection to ~1e-12 of the bracket
                m = 0.5 * (a + b)
                xm, ym = cx + m * vx[sl], cy + m * vy[sl]
                gm = np.hypot(xm, ym) - self._r(np.arctan2(ym, xm))[0]
                a, b = np.where(gm > 0, a, m), np.where(gm > 0, m, b)
            tt = np.where(has, 0.5 * (a + b), np.inf)
            t[sl] = tt
            xm, ym = cx + np.where(has, tt, 0.0) * vx[sl], cy + np.where(has, tt, 0.0) * vy[sl]
            rho = np.maximum(np.hypot(xm, ym), 1e-12)
            _, dr = self._r(np.arctan2(ym, xm))
            gx, gy = xm / rho + dr * ym / rho**2, ym / rho - dr * xm / rho**2
            n3 = gx[:, None] * e1 + gy[:, None] * e2
            normal[sl] = n3 / np.maximum(np.linalg.norm(n3, axis=1, keepdims=True), 1e-12)
        return t, normal


def source_map(shape: tuple[int, int], cam: FisheyeCamera, lumen: Lumen, advance_m: float, roll_rad: float,
               light: str = "capsule") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each pixel of the moved camera's view comes from in the first frame: ``(src (h, w, 2) float32 pixel
    coordinates, gain (h, w): the light's change there (1 with ``light="baked"``), ok (h, w) bool)``."""
    h, w = shape
    # The geometry cast on a grid of every MAP_STEP-th pixel and interpolated between its nodes: the maps are
    # smooth (at 576 px, 1 grey level from casting every pixel at the 99th percentile), and casting every pixel
    # takes seconds a frame.
    gh, gw = (h + MAP_STEP - 1) // MAP_STEP + 1, (w + MAP_STEP - 1) // MAP_STEP + 1
    gv, gu = np.mgrid[0:gh, 0:gw].astype(np.float64) * MAP_STEP
    rays_k, _ = cam.unproject(np.stack([gu, gv], axis=-1).reshape(-1, 2))  # the field stop's corners lie past
    # the lens's stated field (the 156 deg circle fits the shorter side): the equidistant model is carried on there
    e1, _ = lumen.basis()
    c0 = -lumen.offset_m * e1  # camera 0, offset_m from the axis (which passes through the origin)
    ck = c0 + advance_m * lumen.axis
    v = Rotation.from_rotvec([0.0, 0.0, roll_rad]).apply(rays_k)  # camera k -> camera 0
    t, normal = lumen.hit(ck, v)
    far = ~np.isfinite(t)
    p = ck + np.where(far, 0.0, t)[:, None] * v  # the wall point
    d0 = p - c0
    r0 = np.linalg.norm(d0, axis=1)
    src_dir = np.where(far[:, None], v, d0)  # no wall within a metre: the lumen's far end, a direction
    uv0, _ = cam.project(src_dir)
    gain = np.ones(len(v))
    if light == "capsule":
        cos_k = np.clip(np.einsum("ij,ij->i", v, normal), 0.05, 1.0)
        cos_0 = np.clip(np.einsum("ij,ij->i", d0 / np.maximum(r0, 1e-12)[:, None], normal), 0.05, 1.0)
        gain = np.where(far, 1.0, (cos_k / np.maximum(t, 1e-6) ** 2) / (cos_0 / np.maximum(r0, 1e-6) ** 2))
        gain = np.clip(gain, 1 / 16, 16)
    grid = np.concatenate([uv0, gain[:, None]], axis=1).reshape(gh, gw, 3).astype(np.float32)
    full = _bilinear(grid, h, w)
    src = np.ascontiguousarray(full[..., :2])
    gain = full[..., 2]
    ok = np.isfinite(src).all(axis=-1)
    src[~ok] = -1
    return src, gain, ok


def magnification(src: np.ndarray, mask: np.ndarray) -> float:
    """How many times the first frame is enlarged in a view made by ``src`` (:func:`source_map`): the median over
    the field of 1 / sqrt|det d src / d pixel|. Past ~2 the view shows the real frame's pixels blurred: its texture
    there is interpolation, no longer the camera's."""
    du_y, du_x = np.gradient(src[..., 0])
    dv_y, dv_x = np.gradient(src[..., 1])
    det = np.abs(du_x * dv_y - du_y * dv_x)
    sel = mask & np.isfinite(det) & (det > 0) & (src[..., 0] >= 0)
    return float(np.median(1.0 / np.sqrt(det[sel]))) if sel.any() else float("nan")


def tube_view(rgb: np.ndarray, mask: np.ndarray, cam: FisheyeCamera, lumen: Lumen, advance_m: float,
              roll_rad: float, filled: np.ndarray | None = None, light: str = "capsule") -> np.ndarray:
    """The frame seen after advancing ``advance_m`` along the lumen's axis and rolling ``roll_rad`` about the
    optical axis; pixels outside the field (corners, logo) stay as they are. ``filled``: :func:`fill_outside`'s
    frame (made here when not given). ``light``: ``capsule`` -- the light moves with the camera (a point source
    at it, Lambertian wall: each pixel's brightness times cos(incidence) / range^2 here over the same at the first
    frame, then the frame's median brought back to the first frame's, as automatic light control does);
    ``baked`` -- the first frame's shading travels with the wall."""
    filled = fill_outside(rgb, mask) if filled is None else filled
    return _compose(rgb, mask, filled, *source_map(mask.shape, cam, lumen, advance_m, roll_rad, light), light)


def _compose(rgb: np.ndarray, mask: np.ndarray, filled: np.ndarray, src: np.ndarray, gain: np.ndarray,
             ok: np.ndarray, light: str) -> np.ndarray:
    warped = cv2.remap(filled, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if light == "capsule":
        lit = warped.astype(np.float32) * gain[..., None]
        ref = float(np.median(rgb[mask].astype(np.float32)))
        now = float(np.median(lit[mask & ok]))
        warped = np.clip(np.rint(lit * (ref / max(now, 1e-6))), 0, 255).astype(np.uint8)
    warped[~ok] = 0
    out = rgb.copy()
    out[mask] = warped[mask]
    return out


def camera_noise(rgb: np.ndarray, mask: np.ndarray, rng: np.random.Generator, sd: float, quality: int) -> np.ndarray:
    """Sensor noise (``sd`` grey levels, inside the field) and a JPEG round trip at ``quality`` (0: none)."""
    noisy = rgb.astype(np.float32)
    noisy[mask] += rng.normal(0.0, sd, size=(int(mask.sum()), 3)).astype(np.float32)
    noisy = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    if quality <= 0:
        return noisy
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(noisy, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def make_clip(frame_path: str | os.PathLike, out_dir: str | os.PathLike, n_frames: int = 18, step_m: float = 0.001,
              roll_rad: float = 0.0, radius_m: float = PRIOR_RADIUS_M, lobes: int = 0, lobe_depth: float = 0.0,
              offset_frac: float = 0.0, light: str = "capsule", axis: str = "dark", noise: float = 2.0,
              jpeg_quality: int = 85, seed: int = 0, frame_rate_hz: float = 2.0, label: str = "",
              fov_deg: float = FOV_DEG,
              max_magnification: float | None = None, force: bool = False,
              progress: Callable[[int, int], None] | None = None) -> dict:
    """Write a clip of ``n_frames`` made from the real frame ``frame_path`` into the sequence directory ``out_dir``
    (see the module docstring); returns ``truth.json``'s content. ``fov_deg``: the lens the clip is made with
    (equidistant, across the shorter side; meta.json states it): 156 is what `bodyslam batch` assumes for a plain
    folder, so another value made into a plain folder shows what a wrong lens assumption does.
    ``max_magnification``: end the clip before the first frame that enlarges the real frame more than that
    (:func:`magnification`; None: every frame, and ``truth.json`` counts those past :data:`MAX_MAGNIFICATION`).

    Raises
    ------
    InputError
        An unreadable frame, a frame without a lit field, parameters that put the camera outside the lumen or
        name no motion, or an output directory that is not empty (without ``force``).
    """
    if n_frames < 2:
        raise InputError(f"a clip needs at least 2 frames, got {n_frames}")
    if not (step_m > 0 and radius_m > 0 and frame_rate_hz > 0):
        raise InputError("the step, the lumen radius and the frame rate must be positive "
                         f"(got {step_m} m, {radius_m} m, {frame_rate_hz} frames/s)")
    if lobes < 0 or not (0.0 <= lobe_depth < 1.0):
        raise InputError(f"lobes must be >= 0 and lobe_depth in [0, 1), got {lobes} and {lobe_depth}")
    if not (0.0 <= offset_frac < 1.0 - lobe_depth):
        raise InputError(f"offset_frac must lie in [0, {1.0 - lobe_depth:g}) (the camera inside the lumen), "
                         f"got {offset_frac}")
    if light not in ("capsule", "baked") or axis not in ("dark", "centre"):
        raise InputError(f"light must be capsule or baked, axis dark or centre; got {light!r}, {axis!r}")
    if not (60.0 <= fov_deg < 360.0):
        raise InputError(f"fov_deg must lie in [60, 360), got {fov_deg}")
    if not (noise >= 0.0 and 0 <= jpeg_quality <= 100):
        raise InputError(f"noise must be >= 0 grey levels and jpeg_quality in 0-100 (0: none), got {noise} and "
                         f"{jpeg_quality}")
    if max_magnification is not None and not max_magnification >= 1.0:
        raise InputError(f"max_magnification must be at least 1 (the first frame is the frame itself), got "
                         f"{max_magnification}")
    if label not in ("", "FT", "FL"):
        raise InputError(f"label must be FT, FL or empty, got {label!r}")
    out = prepare_output_dir(out_dir, force, create=False)
    rgb = read_image(frame_path)
    h, w = rgb.shape[:2]
    cam = FisheyeCamera.equidistant(w, h, fov_deg)
    mask = field_mask(rgb)
    lumen = Lumen(axis=axis_direction(rgb, mask, cam, axis), radius_m=radius_m, lobes=lobes,
                  lobe_depth=lobe_depth, offset_m=offset_frac * radius_m)
    filled = fill_outside(rgb, mask)
    if max_magnification is not None:  # a clip needs two frames: refuse before writing anything
        first = magnification(source_map(mask.shape, cam, lumen, step_m, roll_rad, light)[0], mask)
        if first > max_magnification:
            raise InputError(f"frame 1 already enlarges the real frame {first:.2f}x, past max_magnification "
                             f"{max_magnification:g}: take a shorter step")
    prepare_output_dir(out, force)
    clear_earlier_sequence(out)  # with force: none of an earlier sequence's frames or truth may stay behind
    (out / "frames").mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    enlarged = []  # each frame's magnification of the real frame
    for i in range(n_frames):
        src, gain, ok = source_map(mask.shape, cam, lumen, i * step_m, i * roll_rad, light)
        enlarged.append(magnification(src, mask))
        if max_magnification is not None and enlarged[-1] > max_magnification:
            enlarged.pop()
            n_frames = i  # the clip ends before the first frame past it
            if progress is not None:
                progress(n_frames, n_frames)
            break
        view = _compose(rgb, mask, filled, src, gain, ok, light)
        write_image(out / "frames" / frame_name(i), camera_noise(view, mask, rng, noise, jpeg_quality))
        if progress is not None:
            progress(i + 1, n_frames)
    t = np.arange(n_frames) / frame_rate_hz
    R_w_c = Rotation.from_rotvec(np.outer(np.arange(n_frames) * roll_rad, [0.0, 0.0, 1.0]))  # world: camera 0
    p_w = np.outer(np.arange(n_frames) * step_m, lumen.axis)
    write_tum(out / "groundtruth.tum", t, p_w, R_w_c)
    m = relative_motion(R_w_c, p_w)
    write_csv(out / "motion_truth.csv",
              ["frame", "t", "distance_m", "roll_rad", "pitch_rad", "yaw_rad", "tilt_rad", "label"],
              [[k, t[k], m["distance_m"][k - 1], m["roll_rad"][k - 1], m["pitch_rad"][k - 1], m["yaw_rad"][k - 1],
                m["tilt_rad"][k - 1], label] for k in range(1, n_frames)])
    truth = {"source_frame": str(frame_path), "n_frames": n_frames, "step_m": step_m, "roll_rad": roll_rad,
             "radius_m": radius_m, "lobes": lobes, "lobe_depth": lobe_depth, "offset_m": lumen.offset_m,
             "axis_c0": lumen.axis.tolist(), "axis_deg_off_optical": math.degrees(math.acos(min(1.0, lumen.axis[2]))),
             "fov_deg": fov_deg, "light": light, "noise": noise, "jpeg_quality": jpeg_quality, "seed": seed,
             "label": label,
             "advance_m": (n_frames - 1) * step_m,
             # how many times each frame enlarges the real one (median over the field): past ~2 its texture is
             # interpolation, no longer the camera's, and what matching does there says little about real frames
             "magnification": [round(x, 3) for x in enlarged],
             "frames_past_2x": int(sum(x > MAX_MAGNIFICATION for x in enlarged)),
             # what a step read in units of the assumed radius amounts to (a monocular step sees no scale)
             "step_in_prior_radius_m": step_m * PRIOR_RADIUS_M / radius_m}
    write_json(out / "truth.json", truth)
    write_meta(out, {
        "format": "bodyslam-sequence/1", "n_frames": n_frames, "frame_rate_hz": frame_rate_hz,
        "image_width": w, "image_height": h, "camera": cam.to_dict(),
        "tube_radius_m": PRIOR_RADIUS_M, "tube_radius_sd_m": PRIOR_RADIUS_SD_M,
        "tube_radius_source": "population prior (the true radius is hidden)",
        "lumen_shape_sd_rel": PRIOR_SHAPE_SD_REL,
        "frames": {"dir": "frames", "pattern": "{index:06d}.png", "color": "RGB"}, "depth": None,
        "units": {"length": "m", "angle": "rad", "time": "s"},
        "source": {"generator": "testbed real-clip", "version": __version__, "frame": Path(frame_path).name,
                   "seed": seed}})
    return truth



"""Camera models of capsule endoscopes: pixel <-> unit ray in the camera frame.

Conventions (SPEC.md): camera frame is OpenCV's (x right, y down, z forward along the optical axis); pixel
coordinates ``(u, v)`` are (column, row) with integer values at pixel centres, so a centred principal point of a
``w x h`` image is ``((w - 1) / 2, (h - 1) / 2)``.

Models
------
- :class:`FisheyeCamera`: the Kannala-Brandt model that ``cv2.fisheye`` implements,
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, ``u = fx theta_d x / r + cx``.
  With ``k = 0`` and ``fx = fy`` it is the ideal equidistant fisheye (image radius proportional to the angle from
  the optical axis), the capsule default; build that with :meth:`FisheyeCamera.equidistant`.
- :class:`PinholeCamera`: the ideal pinhole.

Every model has a field of view ``fov_deg`` (full angle of the image circle for fisheyes); rays outside it are
not valid (a real capsule image is black there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bodyslam.errors import InputError

__all__ = ["CameraModel", "FisheyeCamera", "PinholeCamera", "camera_from_dict", "equidistant_on_field"]


class CameraModel:
    """Common interface. Subclasses implement :meth:`project`, :meth:`unproject` and :meth:`to_dict`."""

    width: int
    height: int
    fov_deg: float

    def project(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points.

        Parameters
        ----------
        points_c : (n, 3) float array, metres (any scale), camera frame.

        Returns
        -------
        uv : (n, 2) float64 pixel coordinates (column, row).
        valid : (n,) bool, the point is inside the field of view (not whether it lies on the image).
        """
        raise NotImplementedError

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit rays through pixel coordinates.

        Parameters
        ----------
        uv : (n, 2) float array, pixel coordinates (column, row).

        Returns
        -------
        rays_c : (n, 3) float64 unit vectors in the camera frame.
        valid : (n,) bool, the pixel sees inside the field of view.
        """
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    def pixel_grid(self) -> np.ndarray:
        """(h, w, 2) float64 pixel-centre coordinates (u, v)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return np.stack([u, v], axis=-1)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit rays of every pixel centre: ``(rays_c (h, w, 3), valid (h, w))``, computed once and cached."""
        cache = getattr(self, "_ray_cache", None)
        if cache is None:
            rays, valid = self.unproject(self.pixel_grid().reshape(-1, 2))
            cache = (rays.reshape(self.height, self.width, 3), valid.reshape(self.height, self.width))
            object.__setattr__(self, "_ray_cache", cache)
        return cache

    def fov_mask(self) -> np.ndarray:
        """(h, w) bool: pixels inside the field of view (the image circle of a fisheye)."""
        return self.pixel_rays()[1]


def _check_size(width: int, height: int) -> tuple[int, int]:
    if int(width) != width or int(height) != height or width < 2 or height < 2:
        raise InputError(f"camera image size must be integers >= 2, got {width}x{height}")
    return int(width), int(height)


@dataclass(frozen=True, eq=False)
class FisheyeCamera(CameraModel):
    """Kannala-Brandt fisheye as in ``cv2.fisheye`` (no skew).

    Parameters
    ----------
    width, height : int, pixels.
    fx, fy : float, pixels per radian of distorted angle.
    cx, cy : float, principal point in pixels.
    k : (4,) float, distortion coefficients k1..k4 (0 for the ideal equidistant lens).
    fov_deg : float, full field of view in degrees (rays with angle > fov/2 from the axis are invalid).
    name : str, ``"equidistant"`` when built by :meth:`equidistant`, kept in files for readability.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    fov_deg: float
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    name: str = field(default="opencv_fisheye")

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not (0.0 < self.fov_deg < 360.0):
            raise InputError(f"fisheye fov_deg must be in (0, 360), got {self.fov_deg}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"fisheye focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if len(self.k) != 4:
            raise InputError(f"fisheye needs 4 distortion coefficients k1..k4, got {len(self.k)}")
        object.__setattr__(self, "k", tuple(float(x) for x in self.k))
        # theta_d(theta) must increase up to fov/2, else unprojection is ambiguous.
        th = np.linspace(0.0, math.radians(self.fov_deg) / 2.0, 512)
        if np.any(np.diff(self._theta_d(th)) <= 0):
            raise InputError("fisheye distortion k1..k4 is not monotonic inside the field of view")

    @classmethod
    def equidistant(
        cls, width: int, height: int, fov_deg: float, cx: float | None = None, cy: float | None = None
    ) -> "FisheyeCamera":
        """Ideal equidistant fisheye whose image circle (``fov_deg`` across) fits the shorter image side."""
        width, height = _check_size(width, height)
        if not (0.0 < fov_deg < 360.0):
            raise InputError(f"fov_deg must be in (0, 360), got {fov_deg}")
        f = (min(width, height) / 2.0) / (math.radians(fov_deg) / 2.0)
        return cls(
            width=width,
            height=height,
            fx=f,
            fy=f,
            cx=(width - 1) / 2.0 if cx is None else float(cx),
            cy=(height - 1) / 2.0 if cy is None else float(cy),
            fov_deg=float(fov_deg),
            name="equidistant",
        )

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix as ``cv2.fisheye`` expects it."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        """(4, 1) distortion vector as ``cv2.fisheye`` expects it."""
        return np.array(self.k, dtype=np.float64).reshape(4, 1)

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.k
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _theta_d_prime(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.k
        return 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))

    def project(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(points_c, dtype=np.float64).reshape(-1, 3)
        r = np.hypot(p[:, 0], p[:, 1])
        theta = np.arctan2(r, p[:, 2])
        td = self._theta_d(theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(r > 0, td / np.where(r > 0, r, 1.0), 0.0)
        uv = np.stack([self.fx * scale * p[:, 0] + self.cx, self.fy * scale * p[:, 1] + self.cy], axis=-1)
        valid = (theta <= math.radians(self.fov_deg) / 2.0) & np.isfinite(uv).all(axis=1)
        return uv, valid

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        xd = (q[:, 0] - self.cx) / self.fx
        yd = (q[:, 1] - self.cy) / self.fy
        td = np.hypot(xd, yd)
        theta = td.copy()
        if any(self.k):
            for _ in range(20):  # Newton on theta_d(theta) = td; converges in a few steps for monotonic k
                theta = theta - (self._theta_d(theta) - td) / self._theta_d_prime(theta)
        half_fov = math.radians(self.fov_deg) / 2.0
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(td > 0, np.sin(theta) / np.where(td > 0, td, 1.0), 0.0)
        rays = np.stack([s * xd, s * yd, np.cos(theta)], axis=-1)
        valid = theta <= half_fov + 1e-12
        return rays, valid

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "model": self.name,
            "width": self.width,
            "height": self.height,
            "fov_deg": self.fov_deg,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "k": list(self.k),
        }
        return d


@dataclass(frozen=True, eq=False)
class PinholeCamera(CameraModel):
    """Ideal pinhole camera; ``fov_deg`` is derived (diagonal field of view) and every pixel is valid."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"pinhole focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> "PinholeCamera":
        """Centred pinhole with horizontal field of view ``hfov_deg``."""
        width, height = _check_size(width, height)
        if not (0.0 < hfov_deg < 180.0):
            raise InputError(f"pinhole hfov_deg must be in (0, 180), got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def fov_deg(self) -> float:  # type: ignore[override]
        corners = np.array([[-0.5, -0.5], [self.width - 0.5, self.height - 0.5]])
        rays, _ = self.unproject(corners)
        return float(math.degrees(np.arccos(np.clip(rays[:, 2], -1, 1)).max() * 2.0))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(points_c, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            uv = np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=-1)
        return uv, z > 0

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        rays = np.stack([(q[:, 0] - self.cx) / self.fx, (q[:, 1] - self.cy) / self.fy, np.ones(len(q))], axis=-1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays, np.ones(len(q), dtype=bool)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "pinhole",
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
        }


# An assumed lens (no calibration) is centred on the detected field of view, its image circle as wide as the field
# (the visible field spans the assumed angle), where the field is off the frame's centre by more than
# FIELD_CENTRE_TOL of the shorter side or spans less than FIELD_MIN_SHARE of it: an export that puts the image beside
# a panel of text, or a small image in a large frame. Otherwise the centred lens across the shorter side stands (the
# rule before session 54): the five real PillCam COLON 2 frames' octagon is centred to the pixel and 510 of 576 px
# wide (89%), and every figure on them was measured with that lens. Measured (session 54) on a real clip of known
# motion (`testbed real-clip`, 12 frames, 1.10 cm) put at the left of an 800 x 600 frame beside text: the centred
# lens fitted 9 of 11 steps beside the wall and read 1.2-1.3 +- 0.6-0.7 cm; centred on the field 1.0-1.1 +- 0.2 cm
# with the field's 510 px as the circle or the lens's true 576 px alike (fast, sift, asift)
FIELD_CENTRE_TOL = 0.02
FIELD_MIN_SHARE = 0.75


def equidistant_on_field(field: np.ndarray, fov_deg: float) -> FisheyeCamera | None:
    """The equidistant lens of ``fov_deg`` whose image circle is the field of view ``field`` (bool ``(h, w)``,
    :func:`bodyslam.vision.matching.detect_fov_mask`): centred on the field's bounding box, as wide as its wider
    side. None where the centred lens of :meth:`FisheyeCamera.equidistant` already fits it
    (:data:`FIELD_CENTRE_TOL`, :data:`FIELD_MIN_SHARE`) or where the field touches the frame's edge (cut off by
    it: its extent does not tell the circle's)."""
    m = np.asarray(field, bool)
    h, w = m.shape
    rows, cols = np.nonzero(m.any(axis=1))[0], np.nonzero(m.any(axis=0))[0]
    if not len(rows):
        return None
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])
    if x0 == 0 or y0 == 0 or x1 == w - 1 or y1 == h - 1:
        return None
    side = min(w, h)
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    diameter = float(max(x1 - x0, y1 - y0) + 1)
    off = math.hypot(cx - (w - 1) / 2.0, cy - (h - 1) / 2.0)
    if off <= FIELD_CENTRE_TOL * side and diameter >= FIELD_MIN_SHARE * side:
        return None
    f = (diameter / 2.0) / (math.radians(fov_deg) / 2.0)
    return FisheyeCamera(width=w, height=h, fx=f, fy=f, cx=cx, cy=cy, fov_deg=float(fov_deg), name="equidistant")


# a described fisheye's field of view (its image circle, radius fx theta_d(fov / 2)) must reach at least this share of
# half the image's shorter side: a capsule camera's fills most of its frame. fov_deg given in radians (2.72 for a
# 156-degree lens) made a circle of 3 px, every step lost, and exit 0
DESCRIBED_FIELD_MIN_SHARE = 0.25


def _field_that_shows(cam: "FisheyeCamera") -> "FisheyeCamera":
    """``cam``, refused where its field of view covers a speck of the image (:data:`DESCRIBED_FIELD_MIN_SHARE`)."""
    r_px = min(cam.fx, cam.fy) * float(cam._theta_d(np.array([math.radians(cam.fov_deg) / 2.0]))[0])
    half = min(cam.width, cam.height) / 2.0
    if r_px < DESCRIBED_FIELD_MIN_SHARE * half:
        hint = (f"; fov_deg is in degrees ({cam.fov_deg:g} rad is {math.degrees(cam.fov_deg):.0f} deg)"
                if cam.fov_deg <= 2 * math.pi else "")
        raise InputError(f"fov_deg {cam.fov_deg:g} with fx {cam.fx:g} px leaves a field of view of radius "
                         f"{r_px:.0f} px on a {cam.width}x{cam.height} image (a capsule camera's fills most of it)"
                         f"{hint}")
    return cam


def camera_from_dict(d: dict[str, Any]) -> CameraModel:
    """Build a camera from its ``meta.json`` / scenario description.

    Accepted forms: ``{"model": "equidistant", "width", "height", "fov_deg"[, "cx", "cy"]}``,
    ``{"model": "opencv_fisheye", "width", "height", "fx", "fy", "cx", "cy", "k": [k1..k4], "fov_deg"}``,
    ``{"model": "pinhole", "width", "height", "fx", "fy", "cx", "cy"}`` or ``{"model": "pinhole", ..., "hfov_deg"}``.

    Raises
    ------
    InputError
        Unknown model or a missing or invalid parameter (the message names it).
    """
    if not isinstance(d, dict):
        raise InputError(f"camera description must be a table/object, got {type(d).__name__}")
    model = d.get("model")
    try:
        if model == "equidistant" and "fx" not in d:
            return FisheyeCamera.equidistant(d["width"], d["height"], float(d["fov_deg"]), d.get("cx"), d.get("cy"))
        if model in ("equidistant", "opencv_fisheye", "kannala_brandt"):
            return _field_that_shows(FisheyeCamera(
                width=int(d["width"]),
                height=int(d["height"]),
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                fov_deg=float(d["fov_deg"]),
                k=tuple(float(x) for x in d.get("k", (0.0, 0.0, 0.0, 0.0))),
                name=str(model),
            ))
        if model == "pinhole":
            if "hfov_deg" in d:
                return PinholeCamera.from_fov(int(d["width"]), int(d["height"]), float(d["hfov_deg"]))
            return PinholeCamera(
                int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"])
            )
    except KeyError as exc:
        raise InputError(f"camera model {model!r} is missing parameter {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise InputError(f"camera model {model!r} has an invalid parameter: {exc}") from None
    raise InputError(f"unknown camera model {model!r} (known: equidistant, opencv_fisheye, pinhole)")

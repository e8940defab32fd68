"""Motility: peristaltic contractions that travel along the gut while the capsule films it (issue 15, item 1).

The static tube (:class:`testbed.tube.Tube`: varying radius, contracted segments, folds, a star-shaped lumen) is
the gut at rest. :class:`Peristalsis` pulls its wall toward the centre line in rings that travel aborally (toward
increasing arc length ``s``) over time, so that consecutive frames see a wall that moved between them -- the
non-rigid scene that the tube estimator's rigid-cylinder model does not know. Ground truth stays exact: the
capsule's pose is the trajectory's, and ``depth/`` is the range to the moved wall.

The radius at ``(s, t)`` is the resting one times

    ``1 - amplitude_frac * env(s) * pulse(s - speed * t) * (1 - hold(s))``

- ``pulse``: a train of Gaussian rings ``width_m`` wide (full width at half maximum), one every
  ``speed_m_s / frequency_hz`` along the gut, moving at ``speed_m_s``. Small-intestine peristaltic waves travel at
  0.5-2 cm/s, paced by slow waves at about 12/min in the duodenum and 8-9/min in the terminal ileum (Guyton and
  Hall, Textbook of Medical Physiology, ch. 63 "Propulsive movements of the small intestine"); defaults 1 cm/s and
  10/min (6 cm apart).
- ``env``: where the waves run. They "normally die out after traveling only 3 to 5 centimeters" (the same source):
  the gut is split into active stretches of ``active_length_m`` on average, covering ``active_frac`` of it, and
  quiet ones between (exponential lengths, drawn per seed), the indicator smoothed over ~5 mm.
- ``hold``: the capsule (11 x 26 mm) holds the lumen open over its own length: no contraction from ``hold_back_m``
  behind the camera to ``hold_ahead_m`` ahead of it, tapering over ``hold_taper_m``; the wall can never close on
  the lens.
- ``amplitude_frac``: how far a ring closes the lumen (0: off, the default, so the ideal scenarios are unchanged).
  Contractions can occlude the lumen; 0.5 (stated choice) halves it at a ring's crest.

Frames are rendered from the moved wall by rebuilding the mesh around the capsule (``window_m`` either side)
per frame (:meth:`testbed.tube.Tube.mesh_window`), and the FT/FL truth's occlusion test sees that wall too
(:func:`testbed.simulate.moving_wall_cast`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import erf

from bodyslam.errors import ConfigError

__all__ = ["Peristalsis", "draw_stretches"]


def draw_stretches(length_m: float, mean_on_m: float, frac_on: float,
                   rng: np.random.Generator) -> list[tuple[float, float]]:
    """Alternating on / off stretches along ``[0, length_m]``, exponential lengths with means ``mean_on_m`` and
    ``mean_on_m (1 - frac_on) / frac_on`` (so that about ``frac_on`` of the gut is on): the on ones' ``(start,
    end)`` in metres."""
    quiet = mean_on_m * (1.0 - frac_on) / frac_on
    out, s, on = [], -rng.uniform(0.0, mean_on_m + quiet), bool(rng.random() < frac_on)
    while s < length_m:
        span = rng.exponential(mean_on_m if on else max(quiet, 1e-6))
        if on:
            out.append((float(s), float(s + span)))
        s, on = s + span, not on
    return out


@dataclass(frozen=True)
class Peristalsis:
    """Scenario section ``[motility]`` (module docstring). ``stretches`` is set by :meth:`drawn` per seed."""

    amplitude_frac: float = 0.0
    speed_m_s: float = 0.01
    frequency_hz: float = 10.0 / 60.0
    width_m: float = 0.02
    active_frac: float = 0.5
    active_length_m: float = 0.04
    hold_back_m: float = 0.026
    hold_ahead_m: float = 0.003
    hold_taper_m: float = 0.01
    window_m: float = 0.30
    stretches: tuple[tuple[float, float], ...] = ()  # active (start, end) arc lengths, m

    def __post_init__(self) -> None:
        if not 0.0 <= self.amplitude_frac <= 0.8:
            raise ConfigError(f"[motility] amplitude_frac must be in [0, 0.8], got {self.amplitude_frac}")
        if not (self.speed_m_s > 0 and self.frequency_hz > 0 and self.width_m > 0 and self.active_length_m > 0):
            raise ConfigError("[motility] speed_m_s, frequency_hz, width_m and active_length_m must be positive")
        if not 0.0 < self.active_frac <= 1.0:
            raise ConfigError(f"[motility] active_frac must be in (0, 1], got {self.active_frac}")
        if min(self.hold_back_m, self.hold_ahead_m, self.hold_taper_m) < 0 or not 0.05 <= self.window_m <= 2.0:
            raise ConfigError("[motility] hold lengths must be >= 0 and window_m within 0.05-2 m")

    @property
    def active(self) -> bool:
        return self.amplitude_frac > 0

    @property
    def spacing_m(self) -> float:
        """Distance between successive waves along the gut."""
        return self.speed_m_s / self.frequency_hz

    def drawn(self, length_m: float, rng: np.random.Generator) -> "Peristalsis":
        """This gut's active stretches: alternating active / quiet lengths, exponential with means
        ``active_length_m`` and ``active_length_m (1 - active_frac) / active_frac``, over ``length_m``."""
        if not self.active:
            return self
        return replace(self, stretches=tuple(draw_stretches(length_m, self.active_length_m, self.active_frac, rng)))

    def envelope(self, s_m: np.ndarray) -> np.ndarray:
        """Where waves run, in [0, 1]: the active stretches' indicator smoothed by a Gaussian of sigma 2 mm."""
        s_m = np.asarray(s_m, dtype=np.float64)
        if not self.stretches:
            return np.ones_like(s_m) if self.active_frac >= 1.0 else np.zeros_like(s_m)
        a = np.array(self.stretches)
        sigma = 0.002
        # smoothed indicator of a union of disjoint intervals: sum of the intervals' smoothed indicators
        z0 = (s_m[:, None] - a[None, :, 0]) / (sigma * math.sqrt(2.0))
        z1 = (s_m[:, None] - a[None, :, 1]) / (sigma * math.sqrt(2.0))
        return np.clip(0.5 * (erf(z0) - erf(z1)).sum(axis=1), 0.0, 1.0)

    def hold(self, s_m: np.ndarray, s_capsule_m: float) -> np.ndarray:
        """1 where the capsule holds the lumen open (module docstring), tapering to 0 over ``hold_taper_m``."""
        lo = s_capsule_m - self.hold_back_m
        hi = s_capsule_m + self.hold_ahead_m
        out_of = np.where(s_m < lo, lo - s_m, np.where(s_m > hi, s_m - hi, 0.0))  # distance outside the hold
        if self.hold_taper_m <= 0:
            return (out_of == 0).astype(np.float64)
        x = np.clip(out_of / self.hold_taper_m, 0.0, 1.0)
        return 0.5 * (1.0 + np.cos(math.pi * x))

    def pulse(self, s_m: np.ndarray, t_s: float) -> np.ndarray:
        """The travelling train of contraction rings at time ``t_s`` (1 at a crest)."""
        lam = self.spacing_m
        x = np.mod(np.asarray(s_m, dtype=np.float64) - self.speed_m_s * t_s, lam)
        d = np.minimum(x, lam - x)
        return np.exp(-0.5 * (d / (self.width_m / 2.3548)) ** 2)

    def radius_factor(self, s_m: np.ndarray, t_s: float, s_capsule_m: float) -> np.ndarray:
        """The wall's radius relative to rest at arc lengths ``s_m`` and time ``t_s``, capsule at ``s_capsule_m``."""
        s_m = np.asarray(s_m, dtype=np.float64)
        if not self.active:
            return np.ones_like(s_m)
        squeeze = self.envelope(s_m) * self.pulse(s_m, t_s) * (1.0 - self.hold(s_m, s_capsule_m))
        return 1.0 - self.amplitude_frac * squeeze

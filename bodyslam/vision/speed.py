"""Capsule speed statistics from estimated per-step motion, and a fitted speed model (dissertation Sec. 4.1.2).

The dissertation's loop: estimate speeds from real videos, build a motion model from them, drive the testbed
with it. Here: :func:`speed_statistics` reads ``motion.csv`` rows, :func:`fit_speed_model` fits the testbed's
Markov phase model (:class:`testbed.motion.MotionConfig`: phases stopped / slow / fast / backward with
exponential durations) and the mean step, roll and tilt, and writes them as a JSON file that
``testbed simulate --speed-model FILE`` takes.

Fit: a step is *stopped* when its speed is under ``stop_speed_m_s`` (default 0.5 mm/s), *backward* when it moves
backward faster than that, else forward; forward steps split into *slow* and *fast* at the median of the log
speed (two classes, the testbed's model). Consecutive steps of one class form a run; ``phase_probs`` are the
fractions of runs per class, ``phase_mean_frames`` their mean lengths, ``phase_speed`` each class's mean speed
relative to the mean forward speed of the moving classes, ``speed_jitter`` the standard deviation of the log
speed within a class. Steps without an estimate are left out (and counted).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bodyslam.errors import InputError
from bodyslam.io import read_json, write_image, write_json
from bodyslam.plots import Figure
from bodyslam.steps import MEASURED

__all__ = ["speed_statistics", "fit_speed_model", "write_speed_report", "load_speed_model"]

FORMAT = "bodyslam-speed-model/1"
CLASSES = ("stopped", "slow", "fast", "backward")


def speed_statistics(rows: dict[int, dict], frame_rate_hz: float) -> dict:
    """Speeds (m/s, signed) of the steps that have an estimate, with their per-step roll and tilt."""
    ks = sorted(k for k, r in rows.items() if r["status"] in MEASURED and np.isfinite(r["distance_m"]))
    if len(ks) < 5:
        raise InputError(f"need at least 5 steps with an estimate to fit speeds, got {len(ks)}")
    d = np.array([rows[k]["distance_m"] for k in ks])
    return {
        "frames": np.array(ks),
        "speed_m_s": d * frame_rate_hz,
        "roll_rad": np.array([rows[k]["roll_rad"] for k in ks]),
        "tilt_rad": np.array([rows[k]["tilt_rad"] for k in ks]),
        "n_without_estimate": len(rows) - len(ks),
        "frame_rate_hz": frame_rate_hz,
    }


def fit_speed_model(stats: dict, stop_speed_m_s: float = 5e-4) -> dict:
    v = stats["speed_m_s"]
    frames = stats["frames"]
    cls = np.where(np.abs(v) < stop_speed_m_s, 0, np.where(v < 0, 3, 1))
    fwd = cls == 1
    if fwd.sum() >= 2:
        split = np.median(np.log(v[fwd]))
        cls[fwd & (np.log(np.maximum(v, 1e-12)) > split)] = 2
    # runs of one class over consecutive frames (a gap in the frames ends a run)
    runs = []
    start = 0
    for i in range(1, len(cls) + 1):
        if i == len(cls) or cls[i] != cls[start] or frames[i] != frames[i - 1] + 1:
            runs.append((int(cls[start]), i - start))
            start = i
    run_cls = np.array([c for c, _ in runs])
    run_len = np.array([n for _, n in runs])
    moving = (cls == 1) | (cls == 2)
    v_ref = float(np.mean(v[moving])) if moving.any() else 1.0
    probs, mean_frames, rel_speed, jit = [], [], [], []
    for c in range(4):
        sel = run_cls == c
        probs.append(float(sel.mean()))
        mean_frames.append(float(run_len[sel].mean()) if sel.any() else 1.0)
        vs = v[cls == c]
        rel_speed.append(0.0 if c == 0 or len(vs) == 0 else float(np.mean(vs) / v_ref))
        if c in (1, 2) and len(vs) > 1:
            jit.append(float(np.std(np.log(np.abs(vs)))))
    rate = stats["frame_rate_hz"]
    motion = {
        "frame_rate_hz": rate,
        "mean_step_m": float(np.mean(np.abs(v)) / rate),
        "mean_roll_deg": float(np.degrees(np.mean(np.abs(stats["roll_rad"])))),
        "mean_tilt_deg": float(np.degrees(np.nanmean(stats["tilt_rad"]))),
        "phase_probs": probs,
        "phase_mean_frames": mean_frames,
        "phase_speed": rel_speed,
        "speed_jitter": float(np.mean(jit)) if jit else 0.35,
    }
    return {
        "format": FORMAT,
        "phases": list(CLASSES),
        "motion": motion,
        "fit": {
            "n_steps": int(len(v)),
            "n_steps_without_estimate": int(stats["n_without_estimate"]),
            "stop_speed_m_s": stop_speed_m_s,
            "mean_speed_m_s": float(np.mean(np.abs(v))),
            "median_speed_m_s": float(np.median(np.abs(v))),
            "fraction_stopped": float(np.mean(cls == 0)),
            "fraction_backward": float(np.mean(cls == 3)),
        },
    }


def load_speed_model(path: str | os.PathLike) -> dict:
    """The ``[motion]`` table of a speed-model file, checked."""
    m = read_json(path)
    if not isinstance(m, dict) or m.get("format") != FORMAT or not isinstance(m.get("motion"), dict):
        raise InputError(f"{path}: not a speed model (expected format {FORMAT!r})")
    mot = m["motion"]
    p = mot.get("phase_probs")
    if not (isinstance(p, list) and len(p) == 4 and abs(sum(p) - 1) < 1e-6):
        raise InputError(f"{path}: phase_probs must be 4 numbers summing to 1")
    return mot


def write_speed_report(stats: dict, model: dict, out_dir: str | os.PathLike) -> list[Path]:
    """``speed_pdf.png``, ``speed_cdf.png`` and ``speed_model.json`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    v_mm = stats["speed_m_s"] * 1000.0
    hi = max(float(np.percentile(np.abs(v_mm), 99)), 1e-3)
    edges = np.linspace(min(float(v_mm.min()), 0.0), hi, 31)
    hist, _ = np.histogram(np.clip(v_mm, edges[0], edges[-1]), bins=edges, density=True)
    n = len(v_mm)
    pdf = Figure(f"Capsule speed PDF ({n} steps)", "speed (mm/s)", "density (1/(mm/s))").bars(edges, hist)
    xs = np.sort(v_mm)
    cdf = Figure(f"Capsule speed CDF ({n} steps)", "speed (mm/s)", "fraction of steps <= speed").line(
        xs, np.arange(1, n + 1) / n, step=True)
    paths = [out / "speed_pdf.png", out / "speed_cdf.png", out / "speed_model.json"]
    write_image(paths[0], pdf.image())
    write_image(paths[1], cdf.image())
    write_json(paths[2], model)
    return paths


def summary_line(model: dict) -> str:
    f, m = model["fit"], model["motion"]
    return (f"{f['n_steps']} steps: mean speed {f['mean_speed_m_s'] * 1000:.2f} mm/s (median "
            f"{f['median_speed_m_s'] * 1000:.2f}), stopped {f['fraction_stopped']:.0%}, backward "
            f"{f['fraction_backward']:.0%}; mean step {m['mean_step_m'] * 100:.3f} cm, roll {m['mean_roll_deg']:.2f} deg,"
            f" tilt {m['mean_tilt_deg']:.2f} deg per step")

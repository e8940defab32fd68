"""The ``popek`` scenario (paper 001): a screw-type magnetic capsule with six Hall sensors, propelled through a
lumen by a single rotating actuator magnet that follows the EKF's estimate (closed loop, Fig. 2).

Truth (integrated every ``sim_step_s``): the lumen holds the capsule on its centre line with ``x_c`` along the
tangent (a straight tube, or an arc); the capsule's roll about ``x_c`` and its advance obey the helical map of
Eq. 15/18 with the *true* torque and force of the actuator's dipole (Eq. 16, 17 corrected), inertia neglected as
in the paper: ``d roll/dt = a tau_x + e f_x``, ``ds/dt = e tau_x + l f_x``. So the capsule rotates synchronously
with the field while the torque it needs is available, and steps out where it is not (a sticky stretch of lumen
scales the whole mobility matrix down: the capsule then rocks back and forth with little net motion, Sec. VII). The actuator moves with the estimate (Algorithm I: offset ``p_des`` from the estimated capsule,
rotation axis by Eq. 5 from the estimated heading, rate cut to 80% then 50% when the monitor says the capsule
is not rotating). The estimator never sees the truth: it gets the Hall readings (Eq. 4 at the true pose plus
Gaussian noise with the paper's N), the actuator's pose it commanded, and a calibration of a, e, l that is off by
``calibration_error_frac``.

Scores (Sec. VIII): mean position error (mm) and mean heading error (deg, angle between the estimated and true
principal axes; roll is not scored, as in the paper) over each run, the capsule's average speed, and how often
the rotation monitor agrees with the truth (the same criterion on the noise-free lead angle).
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.errors import ConfigError
from bodyslam.io import write_csv, write_image, write_json, write_tum
from bodyslam.systems.magnetic import (ActuatorController, HallArray, MagneticEkf, Propulsion, RotationMonitor,
                               _force, cross, field_at, field_in_capsule, measure)
from bodyslam.plots import Figure
from testbed.htmlpage import table, write_report_page
from testbed.scenario import section

log = logging.getLogger(__name__)

__all__ = ["simulate_run", "simulate_scenario", "evaluate_scenario", "report_line"]


def _lumen(scn: dict):
    """``frame(s) -> (point, tangent, normal, binormal)`` of the lumen's centre line at arc length s (m)."""
    p = section(scn, "path")
    kind = p.get("kind", "straight")
    if kind == "straight":
        def frame(s):
            return np.array([s, 0.0, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    elif kind == "arc":
        R = float(p.get("radius_m", 0.10))

        def frame(s):
            th = s / R
            t = np.array([math.cos(th), math.sin(th), 0.0])
            n = np.array([-math.sin(th), math.cos(th), 0.0])
            return np.array([R * math.sin(th), R * (1 - math.cos(th)), 0.0]), t, n, np.array([0, 0, 1.0])
    else:
        raise ConfigError(f"[path] kind must be 'straight' or 'arc', got {kind!r}")
    return frame


def _quat(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _sensors(scn: dict) -> tuple[HallArray, np.ndarray, float]:
    s = section(scn, "sensors")
    arr = HallArray(np.asarray(s["offsets_mm"], float) * 1e-3, np.asarray(s["axes"], float))
    N = np.diag(np.asarray(s["noise_var_t2"], float))
    if N.shape[0] != len(arr.alpha):
        raise ConfigError(f"[sensors] noise_var_t2 has {N.shape[0]} entries for {len(arr.alpha)} sensors")
    return arr, N, float(s.get("rate_hz", 100.0))


def simulate_run(scn: dict, seed: int, record: bool = False, variant: str = "paper") -> dict:
    """One closed-loop run with the EKF ``variant`` driving the actuator; per-sample errors and regime flags (and,
    with ``record``, the logs). Variants: ``paper`` (Sec. VI's Q) and ``body_q`` (orientation noise in the
    capsule frame: ``[filter] body_sd_rad`` for roll, pitch, yaw per step)."""
    mg, pr, ac, pa, fl = (section(scn, k) for k in ("magnets", "propulsion", "actuator", "path", "filter"))
    sensors, N, rate_hz = _sensors(scn)
    frame = _lumen(scn)
    r_cal, r_noise, r_init = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    m_a_mag = float(mg.get("actuator_moment_am2", 71.0))
    mcc = np.array([0.0, float(mg.get("capsule_moment_am2", 0.112)), 0.0])
    a_t, e_t, l_t = float(pr["a"]), float(pr["e"]), float(pr["l"])
    cal = 1 + float(pr.get("calibration_error_frac", 0.1)) * r_cal.normal(size=3)
    prop_f = Propulsion(a_t * cal[0], e_t * cal[1], l_t * cal[2], tuple(mcc))
    sticky = (float(pr.get("sticky_from_m", -1)), float(pr.get("sticky_to_m", -1)), float(pr.get("sticky_factor", 1)))
    dt = 1.0 / rate_hz
    h = float(pa.get("sim_step_s", 0.002))
    n_sub = max(1, int(round(dt / h)))
    h = dt / n_sub
    K = int(round(float(pa.get("max_duration_s", 90.0)) / dt))  # the run ends when the capsule reaches the end
    length = float(pa.get("length_m", 0.24))
    rate_des = 2 * math.pi * float(ac.get("rate_hz", 0.5))
    p_des = np.asarray(ac.get("p_des_mm", (-58.0, 0.0, -100.0)), float) * 1e-3

    def capsule(s_arc, roll):
        pt, t, n, b = frame(s_arc)
        y = math.cos(roll) * n + math.sin(roll) * b
        return pt, np.column_stack([t, y, cross(t, y)])

    # initial state: truth at the lumen's start; the estimate from the initial localization of [12]
    s_arc, roll = 0.0, 0.0
    p_true, R_true = capsule(s_arc, roll)
    ang = np.radians(float(fl.get("init_angle_sd_deg", 3.0)))
    sd_p = float(fl.get("init_position_sd_m", 0.003))
    p_est0 = p_true + r_init.normal(0.0, sd_p, 3)
    R_est0 = R_true @ Rotation.from_rotvec(r_init.normal(0.0, ang, 3)).as_matrix()
    P0 = np.diag([sd_p**2] * 3 + [(ang / 2) ** 2] * 4)
    if variant not in ("paper", "body_q"):
        raise ConfigError(f"unknown filter variant {variant!r}; expected 'paper' or 'body_q'")
    body = tuple(float(x) for x in fl.get("body_sd_rad", (0.01, 0.001, 0.001))) if variant == "body_q" else None
    ekf = MagneticEkf(np.concatenate([p_est0, _quat(R_est0)]), P0, prop_f, sensors,
                      np.diag(np.asarray(fl.get("q_diag", [1e-8] * 3 + [1e-3] * 4), float)), N, body_sd_rad=body)
    ctrl = ActuatorController(rate_des, p_des)
    o_a, axis, rate = ctrl.command(ekf.position, ekf.heading, True, 0.0)
    # the actuator's dipole starts perpendicular to its axis, turned so the field at the capsule is along m_c
    m_a = cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    m_a *= m_a_mag / np.linalg.norm(m_a)
    b = R_true.T @ field_at(p_true - o_a, m_a)
    roll = math.atan2(b[2], b[1])
    window = int(round(rate_hz / float(ac.get("rate_hz", 0.5))))
    smooth = max(1, int(round(float(ac.get("monitor_smooth_rotations", 0.125)) * window)))
    mon_est, mon_true = RotationMonitor(window, tuple(mcc), smooth), RotationMonitor(window, tuple(mcc), smooth)
    n_rec = K + 1
    out = {"t": np.arange(n_rec) * dt, "pos_err": np.zeros(n_rec), "head_err": np.zeros(n_rec),
           "s": np.zeros(n_rec), "rate": np.zeros(n_rec), "rot_est": np.ones(n_rec, bool),
           "rot_true": np.ones(n_rec, bool)}
    if record:
        out.update({"true_pos": np.zeros((n_rec, 3)), "est_pos": np.zeros((n_rec, 3)), "true_quat": np.zeros((n_rec, 4)),
                    "est_quat": np.zeros((n_rec, 4)), "hall": np.zeros((n_rec, len(sensors.alpha))),
                    "actuator_meas": np.full((n_rec, 6), np.nan), "actuator_cmd": np.zeros((n_rec, 6))})

    def log_sample(k, z, pose_at_measurement=None):
        p_t, R_t = capsule(s_arc, roll)
        out["pos_err"][k] = np.linalg.norm(ekf.position - p_t)
        out["head_err"][k] = math.degrees(math.acos(np.clip(ekf.heading @ R_t[:, 0], -1.0, 1.0)))
        out["s"][k], out["rate"][k] = s_arc, rate
        if record:
            out["true_pos"][k], out["est_pos"][k] = p_t, ekf.position
            out["true_quat"][k], out["est_quat"][k] = _quat(R_t), ekf.s[3:] / np.linalg.norm(ekf.s[3:])
            out["hall"][k] = z
            out["actuator_cmd"][k] = np.concatenate([o_a, m_a])  # for the next interval
            if pose_at_measurement is not None:
                out["actuator_meas"][k] = pose_at_measurement

    log_sample(0, np.full(len(sensors.alpha), np.nan))
    for k in range(1, K + 1):
        o_prev, m_prev = o_a.copy(), m_a.copy()
        c_h, s_h = math.cos(rate * h), math.sin(rate * h)
        for _ in range(n_sub):  # the truth: quasi-static helical propulsion in the actuator's real field
            p_t, R_t = capsule(s_arc, roll)
            mc_w = R_t @ mcc
            p_rel = p_t - o_a
            tx = cross(mc_w, field_at(p_rel, m_a)) @ R_t[:, 0]
            fx = _force(p_rel, m_a, mc_w) @ R_t[:, 0]
            g = sticky[2] if sticky[0] <= s_arc <= sticky[1] else 1.0  # a sticky lumen: less mobility
            roll += g * (a_t * tx + e_t * fx) * h
            s_arc = min(max(s_arc + g * (e_t * tx + l_t * fx) * h, 0.0), length)
            # the actuator turns about its axis (Rodrigues)
            m_a = m_a * c_h + cross(axis, m_a) * s_h + axis * (axis @ m_a) * (1 - c_h)
        p_t, R_t = capsule(s_arc, roll)
        z = measure(np.concatenate([p_t, _quat(R_t)]), o_a, m_a, sensors) + r_noise.normal(0.0, 1.0, len(N)) * \
            np.sqrt(np.diag(N))
        ekf.predict(o_prev, m_prev, dt)  # the input held over the interval (Sec. VI)
        ekf.update(z, o_a, m_a)
        pose_meas = np.concatenate([o_a, m_a])
        rotating = mon_est.push(field_in_capsule(z, sensors))
        out["rot_true"][k] = mon_true.push(R_t.T @ field_at(p_t - o_a, m_a))  # the same test, noise-free
        out["rot_est"][k] = rotating
        o_a, axis, rate = ctrl.command(ekf.position, ekf.heading, rotating, dt)
        m_a = m_a - (m_a @ axis) * axis  # the actuator's dipole stays perpendicular to its (new) axis
        m_a *= m_a_mag / np.linalg.norm(m_a)
        log_sample(k, z, pose_meas)
        if s_arc >= length:
            break
    out = {key: (v[: k + 1] if isinstance(v, np.ndarray) else v) for key, v in out.items()}
    out["calibration"] = cal.tolist()
    out["completed"] = bool(s_arc >= length)
    out["filter"] = {"a": prop_f.a, "e": prop_f.e, "l": prop_f.l, "m_c_capsule_am2": mcc.tolist(),
                     "initial_state": np.concatenate([p_est0, _quat(R_est0)]).tolist(), "P0": P0.tolist(),
                     "q_diag": list(np.diag(ekf.Q_proc)), "noise_var_t2": list(np.diag(N)),
                     "body_sd_rad": list(body) if body else None, "rate_hz": rate_hz}
    return out


def _headings_rot(quats: np.ndarray) -> Rotation:
    return Rotation.from_quat(quats[:, [1, 2, 3, 0]])


def simulate_scenario(scn: dict, seed: int, out_dir: str | os.PathLike) -> str:
    """``testbed simulate``: the Hall readings and the actuator's pose as the capsule's PC would log them, the
    filter's calibration and initial localization in ``meta.json``, plus the truth; ``bodyslam magnetic-localize``
    runs the EKF on them without the testbed (the same estimates as the closed loop's, tested)."""
    r = simulate_run(scn, seed, record=True, variant=str(section(scn, "filter").get("variants", ["paper"])[0]))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = r["hall"].shape[1]
    write_csv(out / "hall.csv", ["t"] + [f"b{i}_t" for i in range(n)],
              [[float(t), *map(float, z)] for t, z in zip(r["t"][1:], r["hall"][1:])])
    # the actuator's pose when each reading was taken, and the pose it was commanded to for the next interval
    write_csv(out / "actuator.csv", ["t", "x_m", "y_m", "z_m", "mx_am2", "my_am2", "mz_am2", "cmd_x_m", "cmd_y_m",
                                     "cmd_z_m", "cmd_mx_am2", "cmd_my_am2", "cmd_mz_am2"],
              [[float(t), *map(float, a), *map(float, c)]
               for t, a, c in zip(r["t"], r["actuator_meas"], r["actuator_cmd"])])
    write_tum(out / "groundtruth.tum", r["t"], r["true_pos"], _headings_rot(r["true_quat"]))
    write_tum(out / "estimate.tum", r["t"], r["est_pos"], _headings_rot(r["est_quat"]))
    write_json(out / "meta.json", {"scenario": scn.get("name"), "seed": seed, "kind": "magnetic",
                                   "sensors": section(scn, "sensors"), "magnets": section(scn, "magnets"),
                                   "filter": r["filter"],
                                   "units": "SI: T, A m^2, m, s; quaternions in TUM order (x y z w)"})
    return (f"{len(r['t'])} Hall samples; capsule travelled {r['s'][-1] * 1000:.0f} mm; mean position error "
            f"{r['pos_err'].mean() * 1000:.1f} mm, heading {r['head_err'].mean():.1f} deg")


VARIANT_LABELS = {"paper": "EKF, the paper's Q (Sec. VI)", "body_q": "EKF, orientation noise in the capsule frame"}


def _seed_task(args) -> dict:
    from threadpoolctl import threadpool_limits

    scn, seed, variant = args
    with threadpool_limits(1):
        t0 = time.perf_counter()
        r = simulate_run(scn, seed, variant=variant)
        r["seed"], r["variant"], r["seconds"] = seed, variant, time.perf_counter() - t0
        return r


def _stats(x: np.ndarray) -> dict:
    return {"mean": float(x.mean()), "rmse": float(np.sqrt(np.mean(x**2))), "median": float(np.median(x)),
            "p90": float(np.percentile(x, 90))}


def evaluate_scenario(scn: dict, seeds: list[int], out_dir: str | os.PathLike, jobs: int | None = None,
                      progress: Callable[[str], None] | None = None) -> dict:
    """``testbed evaluate``: every seed's closed-loop run for each filter variant; ``report.json``,
    ``report.html``, plots. Errors are averaged over each run (the paper's "average error"), then over runs."""
    from bodyslam.parallel import imap_tasks

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    variants = list(section(scn, "filter").get("variants", ["paper"]))
    length = float(section(scn, "path").get("length_m", 0.24))
    runs: dict[str, list] = {v: [] for v in variants}
    tasks = [(scn, s, v) for s in seeds for v in variants]
    for i, r in enumerate(imap_tasks(_seed_task, tasks, jobs)):
        runs[r["variant"]].append(r)
        if progress:
            progress(f"seed {r['seed']} {r['variant']} ({i + 1}/{len(tasks)}): position {r['pos_err'].mean() * 1000:.1f}"
                     f" mm, heading {r['head_err'].mean():.1f} deg, {r['t'][-1]:.1f} s")
    report = {"scenario": scn.get("name"), "seeds": list(seeds), "n_runs": len(seeds), "paper": section(scn, "paper"),
              "variants": {}, "labels": {v: VARIANT_LABELS.get(v, v) for v in variants}}
    for v, rs in runs.items():
        done = [r for r in rs if r["completed"]]
        agree = np.concatenate([r["rot_est"][1:] == r["rot_true"][1:] for r in rs])
        stepped = np.concatenate([~r["rot_true"][1:] for r in rs])
        report["variants"][v] = {
            "position_error_mm": {**_stats(np.array([r["pos_err"].mean() for r in rs]) * 1000),
                                  "all_samples": _stats(np.concatenate([r["pos_err"] for r in rs]) * 1000)},
            "heading_error_deg": {**_stats(np.array([r["head_err"].mean() for r in rs])),
                                  "all_samples": _stats(np.concatenate([r["head_err"] for r in rs]))},
            "completed_runs": len(done),
            "completion_time_s": float(np.mean([r["t"][-1] for r in done])) if done else None,
            "speed_mm_s": float(length * 1000 / np.mean([r["t"][-1] for r in done])) if done else None,
            "regime": {"agreement": float(agree.mean()), "true_step_out_fraction": float(stepped.mean()),
                       "step_out_detected_fraction": float(np.mean(agree[stepped])) if stepped.any() else None},
            "seconds_per_run": float(np.mean([r["seconds"] for r in rs]))}
    report["seconds"] = {"wall": round(time.perf_counter() - t0, 2)}
    write_json(out / "report.json", report)
    cols = [(214, 39, 40), (31, 119, 180), (44, 160, 44)]
    f = Figure("Position error (mm) against time, mean over runs", "time (s)", "position error (mm)")
    g = Figure("Heading error (deg) against time, mean over runs", "time (s)", "heading error (deg)")
    for (v, rs), c in zip(runs.items(), cols):
        n = min(len(r["t"]) for r in rs)
        t = rs[0]["t"][:n]
        f.line(t, np.mean([r["pos_err"][:n] for r in rs], axis=0) * 1000, label=VARIANT_LABELS.get(v, v), colour=c)
        g.line(t, np.mean([r["head_err"][:n] for r in rs], axis=0), label=VARIANT_LABELS.get(v, v), colour=c)
    write_image(out / "position_error_vs_time.png", f.image())
    write_image(out / "heading_error_vs_time.png", g.image())
    r0 = runs[variants[0]][0]
    f = Figure(f"Seed {r0['seed']} ({variants[0]}): field rate (Hz) and regime (1 = synchronous)", "time (s)", "")
    f.line(r0["t"], r0["rate"] / (2 * math.pi), label="commanded rate (Hz)", colour=(0, 0, 0))
    f.line(r0["t"], r0["rot_true"] * 0.9, label="truth synchronous", colour=(44, 160, 44))
    f.line(r0["t"], r0["rot_est"] * 0.8, label="detected synchronous", colour=(214, 39, 40))
    write_image(out / "regime.png", f.image())
    _html(out, report)
    return report


def _html(out: Path, rep: dict) -> None:
    pp = rep.get("paper", {})
    rows = [[rep["labels"].get(v, v), f"{x['position_error_mm']['mean']:.2f}", f"{x['heading_error_deg']['mean']:.2f}",
             f"{x['speed_mm_s'] or float('nan'):.2f}", x["completed_runs"], f"{x['regime']['agreement']:.3f}"]
            for v, x in rep["variants"].items()]
    body = table(["filter", "mean position error (mm)", "mean heading error (deg)", "speed (mm/s)",
                  "runs completed", "rotation monitor agreement"], rows)
    write_report_page(out, rep["scenario"], f"{rep['n_runs']} closed-loop runs per filter. Paper (hardware, straight "
                      f"lumen): {pp.get('position_error_mm')} mm, {pp.get('heading_error_deg')} deg, "
                      f"{pp.get('speed_mm_s')} mm/s.", body,
                      ["position_error_vs_time.png", "heading_error_vs_time.png", "regime.png"])


def report_line(rep: dict) -> str:
    pp = rep.get("paper", {})
    parts = [f"{v}: position {x['position_error_mm']['mean']:.2f} mm, heading {x['heading_error_deg']['mean']:.2f} deg, "
             f"speed {x['speed_mm_s'] or float('nan'):.2f} mm/s, monitor agreement {x['regime']['agreement']:.3f}"
             for v, x in rep["variants"].items()]
    return (f"{rep['n_runs']} runs of {rep['scenario']} (paper: {pp.get('position_error_mm')} mm, "
            f"{pp.get('heading_error_deg')} deg, {pp.get('speed_mm_s')} mm/s): " + "; ".join(parts))

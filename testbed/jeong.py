"""The ``jeong2017`` scenario (paper 000): TOA/DOA at two body-worn URAs and an IMU, fused by the EKF of
Algorithm 1, against the four reference schemes and the PCRB of Algorithm 2.

Truth: the capsule starts at rest at the mouth (``p0 = [0, 8, 0]`` cm, ``v0 = 0``, Sec. 5) and follows a fixed
tract (the scenario's ``[path] seed``; the paper's Fig. 2 map is not published as data): an oesophagus, then a
procedural small-intestine centre line between the arrays, at ``speed_mps`` after a smooth start. The state is
sampled every ``delta`` with constant acceleration within a slot, so the truth obeys Eq. 10 exactly with
``a_k = (v_{k+1} - v_k) / delta``. Every run follows the same tract; the seed draws the channel and the noise
(the paper's Monte Carlo runs).

Emulation per slot (clean signal and noise drawn separately): for each URA the SNR from Eq. 2 with log-normal
shadowing and Rayleigh small-scale fading (Sec. 5); TOA, azimuth and elevation (Eq. 3a, 5) plus Gaussian errors
with the CRB variances of Eq. 7-8 at that SNR; the IMU reading ``u_k = a_k + N(0, sigma^2)`` per axis (Eq. 12).

Algorithms (``bodyslam.systems.toa_doa``): ``toa_doa_imu`` (Algorithm 1), ``doa_imu``, ``toa_imu``, ``imu_only`` (the
same EKF with fewer channels) and ``rf_only`` (each slot's TOA/DOA alone). Scores (paper Sec. 5): RMS error over
runs per step (Eq. 30) and its mean over the steps, against the mean square root of the PCRB of the same scheme;
Table 2's mean drift per metre, ``sum_k mean error_k / sum_k (path travelled until k)``.

Files of a simulated run (SPEC.md conventions): ``rf.csv`` (``t,sensor,toa_s,azimuth_rad,elevation_rad,snr_db``;
one row per URA and slot), ``imu.csv`` (``t,ax_mps2,ay_mps2,az_mps2``: the reading for the slot starting at t),
``sensors.csv`` (each URA's reference element), ``meta.json`` (arrays, radio, IMU, initial state) and
``groundtruth.tum``. ``bodyslam hybrid-localize`` runs the algorithms on such files without the testbed.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam.errors import ConfigError
from bodyslam.io import write_csv, write_image, write_json, write_tum
from bodyslam.plots import Figure
from bodyslam.systems.toa_doa import SCHEMES, Radio, Ura, channel_draws, run_scheme, scheme_pcrb, toa_doa
from testbed.centerline import Centerline, procedural_centerline
from testbed.htmlpage import table, write_report_page
from testbed.scenario import section

log = logging.getLogger(__name__)

__all__ = ["ALGORITHMS", "LABELS", "arrays_from", "radio_from", "truth_motion", "emulate", "simulate_hybrid",
           "run_algorithm", "evaluate_hybrid", "report_line"]

ALGORITHMS = SCHEMES
LABELS = {"toa_doa_imu": "Algorithm 1 (TOA/DOA + IMU)", "doa_imu": "DOA + IMU", "toa_imu": "TOA + IMU",
          "rf_only": "RF only (TOA/DOA), each slot alone",
          "rf_only_cv": "RF only (TOA/DOA), Algorithm 1 without the IMU input", "imu_only": "IMU only"}
SHORT = {"toa_doa_imu": "Alg. 1 TOA/DOA+IMU", "doa_imu": "DOA+IMU", "toa_imu": "TOA+IMU",
         "rf_only_cv": "RF only (CV EKF)", "rf_only": "RF only (per slot)", "imu_only": "IMU only"}
_COLOURS = {"toa_doa_imu": (214, 39, 40), "doa_imu": (31, 119, 180), "toa_imu": (44, 160, 44),
            "rf_only": (255, 127, 14), "rf_only_cv": (148, 103, 189), "imu_only": (120, 120, 120)}


def arrays_from(scn: dict) -> list[Ura]:
    a = section(scn, "arrays")
    w, h, n = float(a.get("width_m", 0.4)), float(a.get("height_m", 0.4)), int(a.get("n", 5))
    x0, z0 = float(a.get("centre_x_m", 0.0)) - w / 2, float(a.get("bottom_z_m", -0.5))
    return [Ura.spanning("front", (x0, float(a.get("front_y_m", 0.2)), z0), w, h, n, n),
            Ura.spanning("back", (x0, float(a.get("back_y_m", -0.2)), z0), w, h, n, n)]


def radio_from(scn: dict) -> Radio:
    r = section(scn, "radio")
    known = {"pt_dbm", "n0_dbm_hz", "fc_hz", "beta_hz", "c_avg_mps"}
    bad = set(r) - known
    if bad:
        raise ConfigError(f"[radio] has unknown keys {sorted(bad)}; known: {sorted(known)}")
    return Radio(**{k: float(v) for k, v in r.items()})


def _tract(scn: dict) -> Centerline:
    p = section(scn, "path")
    rng = np.random.default_rng(int(p.get("seed", 2017)))
    cl = procedural_centerline(float(p.get("intestine_length_m", 1.5)), rng,
                               radius_max_m=float(p.get("radius_m", 0.0125)),
                               abdomen_box_m=tuple(p.get("intestine_box_m", (0.24, 0.20, 0.20))),
                               min_self_distance_diameters=1.5)
    gut = cl.points_w[::20] + np.asarray(p.get("intestine_centre_m", (0.0, 0.0, -0.33)), float)
    mouth, oes = np.asarray(p.get("mouth_m", (0, 0.08, 0)), float), np.asarray(p.get("oesophagus_end_m"), float)
    head = np.linspace(mouth, oes, 12)[:-1]
    # the stomach: a bend from the oesophagus to the start of the intestine, halfway points pulled outward
    mid = 0.5 * (oes + gut[0]) + np.array([0.04, 0.0, 0.0])
    bridge = np.array([oes + 0.5 * (mid - oes), mid, mid + 0.5 * (gut[0] - mid)])
    return Centerline.from_points(np.vstack([head, oes, bridge, gut]), float(p.get("radius_m", 0.0125)),
                                  smoothing_m=0.002)


def truth_motion(scn: dict) -> dict[str, np.ndarray]:
    """``t (K+1,)``, ``pos``/``vel`` ``(K+1, 3)``, ``acc (K, 3)`` (slot-constant), ``travelled_m (K+1,)``."""
    seq, p = section(scn, "sequence"), section(scn, "path")
    delta = float(seq.get("interval_s", 1.0))
    K = int(round(float(seq.get("duration_s", 100.0)) / delta))
    v, ramp = float(p.get("speed_mps", 0.01)), float(p.get("ramp_s", 10.0))
    cl = _tract(scn)
    h = 0.01 * delta
    tf = np.arange(0.0, K * delta + 2 * h + 1e-12, h)
    speed = np.where(tf < ramp, v * 0.5 * (1 - np.cos(np.pi * np.minimum(tf / max(ramp, 1e-9), 1.0))), v)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * h)])
    if s[-1] > cl.length_m:
        raise ConfigError(f"the tract ({cl.length_m:.2f} m) is shorter than {s[-1]:.2f} m travelled: lengthen "
                          "path.intestine_length_m or slow down")
    pf = cl.frame_at(s)[0]
    pf += np.asarray(p.get("mouth_m", (0.0, 0.08, 0.0)), float) - pf[0]  # start exactly at the mouth (p0)
    vf = np.gradient(pf, h, axis=0)
    idx = np.rint(np.arange(K + 1) * delta / h).astype(int)
    vel = vf[idx]
    acc = np.diff(vel, axis=0) / delta
    pos = np.empty((K + 1, 3))
    pos[0] = pf[0]
    for k in range(K):  # Eq. 10 with w = 0: the truth is exactly the model's
        pos[k + 1] = pos[k] + delta * vel[k] + 0.5 * delta**2 * acc[k]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    return {"t": np.arange(K + 1) * delta, "pos": pos, "vel": vel, "acc": acc, "travelled_m": travelled}


@functools.lru_cache(maxsize=8)
def _truth_for(key: str) -> dict[str, np.ndarray]:
    out = truth_motion(json.loads(key))
    for v in out.values():
        v.setflags(write=False)  # shared between the set-ups of one worker
    return out


def _truth(scn: dict) -> dict[str, np.ndarray]:
    """:func:`truth_motion`, computed once per tract and timing (the sweeps change only the radio, arrays and IMU;
    building the tract is most of a set-up's time)."""
    return _truth_for(json.dumps({k: section(scn, k) for k in ("path", "sequence")}, sort_keys=True))


def emulate(truth: dict, arrays: list[Ura], radio: Radio, sigma_acc: float,
            rng: np.random.Generator) -> dict[str, np.ndarray]:
    """What the URAs and the IMU report: ``y (K+1, n_arrays, 3)`` (row 0: no reading, NaN), ``snr`` (linear,
    same layout), ``imu (K, 3)``. Channel, RF noise and IMU noise come from separate streams of ``rng``."""
    r_ch, r_rf, r_imu = rng.spawn(3)
    pos = truth["pos"]
    K1, n = len(pos), len(arrays)
    y = np.full((K1, n, 3), np.nan)
    snr = np.full((K1, n), np.nan)
    for i, a in enumerate(arrays):
        clean = toa_doa(pos[1:], a.ref_m, radio.c_avg_mps)
        d = np.linalg.norm(pos[1:] - np.asarray(a.ref_m), axis=1)
        snr[1:, i] = channel_draws(d, radio, r_ch)
        var = radio.variances(clean[:, 1], clean[:, 2], snr[1:, i], a)
        y[1:, i] = clean + r_rf.normal(0.0, 1.0, clean.shape) * np.sqrt(var)
    imu = truth["acc"] + r_imu.normal(0.0, sigma_acc, truth["acc"].shape)
    return {"y": y, "snr": snr, "imu": imu}


def _filter_cfg(scn: dict) -> tuple[np.ndarray, str]:
    f = section(scn, "filter")
    P0 = np.diag([float(f.get("p0_pos_var_m2", 5e-4))] * 3 + [float(f.get("p0_vel_var_m2ps2", 1e-5))] * 3)
    return P0, str(f.get("q_model", "eq15"))


def run_algorithm(name: str, x0: np.ndarray, P0: np.ndarray, meas: dict, arrays: list[Ura], radio: Radio,
                  sigma_acc: float, delta_s: float, q_model: str = "eq15") -> np.ndarray:
    """Positions ``(K+1, 3)`` estimated by one scheme from the readings alone (and the known start, Sec. 5)."""
    return run_scheme(name, x0, P0, meas["y"], meas["snr"], meas["imu"], arrays, radio, sigma_acc, delta_s,
                      q_model)[0]


def _world(scn: dict, seed: int):
    truth = _truth(scn)
    arrays, radio = arrays_from(scn), radio_from(scn)
    sigma = float(section(scn, "imu").get("sigma_acc_mps2", 3e-4))
    meas = emulate(truth, arrays, radio, sigma, np.random.default_rng(seed))
    return truth, arrays, radio, sigma, meas


def simulate_hybrid(scn: dict, seed: int, out_dir: str | os.PathLike) -> dict:
    """Write one run as files (module docstring); returns a summary."""
    truth, arrays, radio, sigma, meas = _world(scn, seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = truth["t"]
    write_csv(out / "sensors.csv", ["sensor", "x", "y", "z"], [[a.name, *a.ref_m] for a in arrays])
    rows = [[float(t[k]), a.name, *(float(v) for v in meas["y"][k, i]), float(10 * np.log10(meas["snr"][k, i]))]
            for k in range(1, len(t)) for i, a in enumerate(arrays)]
    write_csv(out / "rf.csv", ["t", "sensor", "toa_s", "azimuth_rad", "elevation_rad", "snr_db"], rows)
    write_csv(out / "imu.csv", ["t", "ax_mps2", "ay_mps2", "az_mps2"],
              [[float(t[k]), *map(float, meas["imu"][k])] for k in range(len(t) - 1)])
    write_tum(out / "groundtruth.tum", t, truth["pos"], _headings(truth["vel"]))
    P0, q_model = _filter_cfg(scn)
    write_json(out / "meta.json", {
        "scenario": scn.get("name"), "seed": seed, "kind": "hybrid_imu", "interval_s": float(t[1] - t[0]),
        "n_steps": len(t), "arrays": [{"name": a.name, "ref_m": list(a.ref_m), "n_x": a.n_x, "n_z": a.n_z,
                                       "dx_m": a.dx_m, "dz_m": a.dz_m} for a in arrays],
        "radio": {k: getattr(radio, k) for k in ("pt_dbm", "n0_dbm_hz", "fc_hz", "beta_hz", "c_avg_mps")},
        "imu": {"sigma_acc_mps2": sigma},
        "initial_state": {"position_m": truth["pos"][0].tolist(), "velocity_mps": truth["vel"][0].tolist(),
                          "covariance": P0.tolist()},
        "units": "SI; toa in s, angles in rad (azimuth from +x in the x-y plane, elevation from it), SNR in dB"})
    return {"steps": len(t), "path_travelled_m": float(truth["travelled_m"][-1])}


def simulate_scenario(scn: dict, seed: int, out_dir: str | os.PathLike) -> str:
    """``testbed simulate`` for this kind of scenario: the files, and one line saying what was written."""
    s = simulate_hybrid(scn, seed, out_dir)
    return f"{s['steps']} slots of TOA/DOA per array and IMU readings; path {s['path_travelled_m'] * 100:.1f} cm"


def _headings(vel: np.ndarray) -> Rotation:
    z = vel / np.maximum(np.linalg.norm(vel, axis=1, keepdims=True), 1e-12)
    z[np.linalg.norm(vel, axis=1) < 1e-9] = (0.0, 0.0, -1.0)
    up = np.where(np.abs(z[:, 2:3]) > 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 0, 1.0]]))
    x = np.cross(up, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return Rotation.from_matrix(np.stack([x, np.cross(z, x), z], axis=-1))


# ------------------------------------------------------------------------------------------------ evaluation


def _set(scn: dict, key: str, value) -> dict:
    out = copy.deepcopy(scn)
    if "." not in key:
        raise ConfigError(f"sweep key must be 'section.key', got {key!r}")
    sec, name = key.split(".", 1)
    out.setdefault(sec, {})[name] = value
    return out


def _point_task(args) -> dict:
    """One set-up (the scenario with one sweep value) over ``seeds``: errors per run and the PCRB per scheme."""
    from threadpoolctl import threadpool_limits

    scn, seeds, algs, want_estimates = args
    with threadpool_limits(1):
        t0 = time.perf_counter()
        truth = _truth(scn)
        arrays, radio = arrays_from(scn), radio_from(scn)
        sigma = float(section(scn, "imu").get("sigma_acc_mps2", 3e-4))
        delta = float(truth["t"][1] - truth["t"][0])
        P0, q_model = _filter_cfg(scn)
        x0 = np.concatenate([truth["pos"][0], truth["vel"][0]])
        errors = {a: [] for a in algs}
        estimates = {a: [] for a in algs}
        cond = {a: [] for a in algs}
        t_bound = 0.0
        for seed in seeds:
            meas = emulate(truth, arrays, radio, sigma, np.random.default_rng(seed))
            for a in algs:
                est = run_algorithm(a, x0, P0, meas, arrays, radio, sigma, delta, q_model)
                errors[a].append(np.linalg.norm(est - truth["pos"], axis=1))
                if want_estimates:
                    estimates[a].append(est)
                tb = time.perf_counter()
                cond[a].append(scheme_pcrb(a, truth["pos"], arrays, radio, sigma, delta, snr=meas["snr"]))
                t_bound += time.perf_counter() - tb
        t1 = time.perf_counter()
        draws = int(section(scn, "filter").get("pcrb_draws", 400))
        bound = {}
        for i, a in enumerate(algs):  # the bound's channel draws: their own stream, never the evaluation seeds'
            bound[a] = scheme_pcrb(a, truth["pos"], arrays, radio, sigma, delta, np.random.default_rng([2017, i]),
                                   draws=draws)
        return {"errors": {a: np.stack(v) for a, v in errors.items()}, "pcrb_m2": bound, "truth": truth,
                "pcrb_channel_m2": {a: np.stack(v) for a, v in cond.items()},
                "estimates": {a: v for a, v in estimates.items()} if want_estimates else None,
                "seconds": {"filters": t1 - t0 - t_bound, "pcrb": time.perf_counter() - t1 + t_bound}}


def _summary(res: dict) -> dict:
    """Paper-style figures of one set-up: mean RMS error (Eq. 30 then the mean over steps), mean sqrt(PCRB),
    Table 2 drift, plus the SPEC's mean / RMSE / median / p90 over every step of every run (steps 1..K)."""
    travelled = res["truth"]["travelled_m"]
    out = {}
    for a, E in res["errors"].items():
        e = E[:, 1:]
        rms_k = np.sqrt(np.mean(e**2, axis=0))
        bound_k = np.sqrt(res["pcrb_m2"][a][1:])
        chan_k = np.sqrt(np.mean(res["pcrb_channel_m2"][a][:, 1:], axis=0))
        out[a] = {"mean_rms_error_cm": float(rms_k.mean() * 100), "mean_sqrt_pcrb_cm": float(bound_k.mean() * 100),
                  "rms_over_sqrt_pcrb": float(rms_k.mean() / bound_k.mean()),
                  "min_step_rms_over_sqrt_pcrb": float(np.min(rms_k / bound_k)),
                  "mean_sqrt_pcrb_channel_cm": float(chan_k.mean() * 100),
                  "rms_over_sqrt_pcrb_channel": float(rms_k.mean() / chan_k.mean()),
                  "drift_cm_per_m": float(e.mean(axis=0).sum() * 100 / travelled[1:].sum()),
                  "mean_error_cm": float(e.mean() * 100), "rmse_cm": float(np.sqrt(np.mean(e**2)) * 100),
                  "median_error_cm": float(np.median(e) * 100), "p90_error_cm": float(np.percentile(e, 90) * 100),
                  "final_rms_error_cm": float(rms_k[-1] * 100)}
    return out


def evaluate_hybrid(scn: dict, seeds: list[int], out_dir: str | os.PathLike, jobs: int | None = None,
                    progress: Callable[[str], None] | None = None, sweeps: bool = True) -> dict:
    """Table 2 over ``seeds`` and the Fig. 3-7 sweeps (each point over the first ``[sweeps] seeds``); writes
    ``report.json``, ``report.html`` and the plots."""
    from bodyslam.parallel import imap_tasks

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    algs = list(section(scn, "filter").get("algorithms", ALGORITHMS))
    sw = section(scn, "sweeps") if sweeps else {}
    n_sw = min(int(sw.get("seeds", 10)), len(seeds))
    figs = {k: v for k, v in sw.items() if isinstance(v, dict)}
    # the main set-up split in seed chunks (both cores), then every sweep point
    chunks = [seeds[i::2] for i in range(2)] if len(seeds) > 1 else [seeds]
    tasks = [(scn, c, algs, True) for c in chunks if c]
    points = []
    for fig, spec in figs.items():
        for v in spec.get("values", []):
            tasks.append((_set(scn, spec["key"], v), seeds[:n_sw], algs, False))
            points.append((fig, v))
    results = []
    for i, r in enumerate(imap_tasks(_point_task, tasks, jobs)):
        results.append(r)
        if progress:
            progress(f"jeong2017: set-up {i + 1}/{len(tasks)} done")
    n_main = len([c for c in chunks if c])
    main = results[0]
    for r in results[1:n_main]:
        main = {**main, "errors": {a: np.vstack([main["errors"][a], r["errors"][a]]) for a in algs},
                "estimates": {a: main["estimates"][a] + r["estimates"][a] for a in algs},
                "pcrb_channel_m2": {a: np.vstack([main["pcrb_channel_m2"][a], r["pcrb_channel_m2"][a]])
                                    for a in algs}}
    order = [s for c in chunks for s in c]
    paper = section(scn, "paper")
    report = {"scenario": scn.get("name"), "seeds": order, "n_runs": len(seeds),
              "steps_per_run": int(len(main["truth"]["t"])), "duration_s": float(main["truth"]["t"][-1]),
              "path_travelled_cm": float(main["truth"]["travelled_m"][-1] * 100),
              "algorithms": _summary(main), "paper": paper,
              "labels": {a: LABELS.get(a, a) for a in algs}, "sweeps": {}}
    for (fig, v), r in zip(points, results[n_main:]):
        spec = figs[fig]
        entry = report["sweeps"].setdefault(fig, {"key": spec["key"], "label": spec.get("label", spec["key"]),
                                                  "scale": float(spec.get("scale", 1.0)), "n_runs": n_sw,
                                                  "values": [], "algorithms": {a: {"mean_rms_error_cm": [],
                                                                                     "mean_sqrt_pcrb_cm": []}
                                                                                 for a in algs}})
        entry["values"].append(v)
        s = _summary(r)
        for a in algs:
            entry["algorithms"][a]["mean_rms_error_cm"].append(s[a]["mean_rms_error_cm"])
            entry["algorithms"][a]["mean_sqrt_pcrb_cm"].append(s[a]["mean_sqrt_pcrb_cm"])
    report["seconds"] = {"wall": round(time.perf_counter() - t_start, 2),
                         "filters": round(sum(r["seconds"]["filters"] for r in results), 2),
                         "pcrb": round(sum(r["seconds"]["pcrb"] for r in results), 2)}
    write_json(out / "report.json", report)
    _plots(out, main, report, algs)
    _html(out, report)
    return report


evaluate_scenario = evaluate_hybrid  # what ``testbed evaluate`` calls for this kind of scenario


def _plots(out: Path, main: dict, report: dict, algs: list[str]) -> None:
    t = main["truth"]["t"]
    f = Figure("RMS error over runs (thick), sqrt(PCRB) (thin)", "time (s)", "error (cm)", size=(760, 460),
               log_y=True)
    for a in algs:
        e = np.sqrt(np.mean(main["errors"][a] ** 2, axis=0)) * 100
        f.line(t[1:], e[1:], label=SHORT.get(a, a), colour=_COLOURS.get(a, (0, 0, 0)))
        f.line(t[1:], np.sqrt(main["pcrb_m2"][a][1:]) * 100, colour=_COLOURS.get(a, (0, 0, 0)), width=1)
    write_image(out / "error_vs_time.png", f.image())
    f = Figure("Error CDF, all runs", "error (cm)", "fraction of steps")
    for a in algs:
        x = np.sort(main["errors"][a][:, 1:].ravel()) * 100
        f.line(x, np.arange(1, len(x) + 1) / len(x), label=SHORT.get(a, a), colour=_COLOURS.get(a, (0, 0, 0)),
               step=True)
    write_image(out / "error_cdf.png", f.image())
    pos = main["truth"]["pos"] * 100
    f = Figure(f"Tract and run {report['seeds'][0]} (x-z, cm)", "x (cm)", "z (cm)", size=(640, 640), equal=True)
    for a in algs:
        est = main["estimates"][a][0] * 100
        f.line(est[:, 0], est[:, 2], label=SHORT.get(a, a), colour=_COLOURS.get(a, (0, 0, 0)))
    f.line(pos[:, 0], pos[:, 2], label="truth", colour=(0, 0, 0))
    write_image(out / "trajectories_xz.png", f.image())
    for fig, entry in report["sweeps"].items():
        x = np.asarray(entry["values"], float) * entry["scale"]
        f = Figure(f"{fig}: RMS error (thick), sqrt(PCRB) (thin); {entry['n_runs']} runs per point",
                   entry["label"], "error (cm)", size=(760, 460), log_y=True)
        for a in algs:
            c = _COLOURS.get(a, (0, 0, 0))
            f.line(x, entry["algorithms"][a]["mean_rms_error_cm"], label=SHORT.get(a, a), colour=c, marker=True)
            f.line(x, entry["algorithms"][a]["mean_sqrt_pcrb_cm"], colour=c, width=1)
        write_image(out / f"{fig}.png", f.image())


def _html(out: Path, report: dict) -> None:
    paper = report.get("paper", {})
    rows = [[LABELS.get(a, a), f"{v['drift_cm_per_m']:.3f}", paper.get(a + "_drift_cm_per_m", ""),
             f"{v['mean_rms_error_cm']:.3f}", f"{v['mean_sqrt_pcrb_cm']:.3f}", f"{v['rms_over_sqrt_pcrb']:.2f}",
             f"{v['rms_over_sqrt_pcrb_channel']:.2f}", f"{v['mean_error_cm']:.3f}", f"{v['p90_error_cm']:.3f}"]
            for a, v in report["algorithms"].items()]
    body = table(["algorithm", "drift (cm/m)", "paper Table 2 (cm/m)", "mean RMS error (cm)", "mean sqrt(PCRB) (cm)",
                  "RMS / sqrt(PCRB)", "RMS / sqrt(PCRB | channel)", "mean error (cm)", "p90 (cm)"], rows)
    write_report_page(out, report["scenario"], f"{report['n_runs']} runs of {report['duration_s']:.0f} s "
                      f"({report['steps_per_run']} steps, {report['path_travelled_cm']:.0f} cm travelled).", body,
                      ["error_vs_time.png", "error_cdf.png", "trajectories_xz.png",
                       *(f"{k}.png" for k in report["sweeps"])])


def report_line(rep: dict) -> str:
    paper = rep.get("paper", {})
    parts = [f"{a}: drift {v['drift_cm_per_m']:.3f} cm/m (paper {paper.get(a + '_drift_cm_per_m', '-')}), "
             f"RMS {v['mean_rms_error_cm']:.3f} cm = {v['rms_over_sqrt_pcrb']:.2f} sqrt(PCRB)"
             for a, v in rep["algorithms"].items()]
    return f"{rep['n_runs']} runs of {rep['scenario']} ({rep['duration_s']:.0f} s): " + "; ".join(parts)

"""RF-only tracking scenarios of papers 002 (``ito2016``: UWB TOA/RSSI with permittivity estimation) and 003
(``ito_heading``: MICS RSSI, moving distance and heading): emulation, simulation and evaluation runs.

Truth: the capsule follows the small intestine by random waypoints (002 Sec. 4.1, 003 Sec. 4.1): the waypoints
are points every ``waypoint_spacing_m`` along a procedural centre line packed in the analysis area; it moves
straight from one to the next at a speed drawn per leg from N(0.05 cm/s, 0.005 (cm/s)^2) (kept >= 0.005 cm/s)
and stops U(0, 20) s at each. Receivers at the eight vertices of the 40 x 40 x 20 cm area (Table 3 / Sec. 4.1).

Emulation (what the receivers measure; clean signal and noise separate, seeded):

- TOA: ``sqrt(eps_r) d / c`` plus N(0, sigma_s) (Table 3: 62.5 ps, half the 8 GHz sampling interval).
- UWB field at 4.1 GHz: 002 used an FDTD-derived statistical model in which the permittivity inverted from each
  receiver's field (Eq. 11) is log-normal about the true one with sigma_e = 1.23 (Fig. 4). The emulation draws
  that permittivity and reports the field Eq. 9 gives for it (so the pipeline's Eq. 11 recovers the draw), as
  ``uwb_field_db`` = 20 log10(E/E0) (A = 1).
- MICS RSSI (``rss_dbm`` column): 003 Eq. 3-4, 5.5 dB log-normal shadowing.

Written like any sequence: ``rf.csv`` (``t,sensor,rss_dbm,toa_s,uwb_field_db``), ``sensors.csv``,
``groundtruth.tum`` (positions; orientation along the current leg), ``meta.json`` (models, area), ``truth.json``
(true permittivity, waypoints). Evaluation: :func:`evaluate_rf_tracking` runs the scenario's algorithms on the
same draws (``bodyslam.systems.pf``) and reports errors per algorithm in the format of the Body-SLAM runs.
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
from bodyslam.systems.pf import (C_MPS, TRACKERS, MicsRssiModel, Track, TrackSettings, converged_from,
                         field_ratio, simple_distance, track, waypoint_distance)
from bodyslam.plots import Figure
from testbed.centerline import procedural_centerline
from testbed.htmlpage import table, write_report_page
from testbed.scenario import section

log = logging.getLogger(__name__)

__all__ = ["RF_TRACKING_ALGORITHMS", "emulate", "simulate_rf_tracking", "run_algorithm", "evaluate_rf_tracking",
           "report_line"]

RF_TRACKING_ALGORITHMS = TRACKERS
LABELS = {"toa_rssi_pf": "TOA + RSSI PF, permittivity estimated (002, proposed)",
          "toa_pf_true_eps": "TOA PF with the true permittivity (002)",
          "rssi_pf": "MICS RSSI PF (003; 002's conventional RSSI method)"}


def _receivers(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def truth_motion(scn: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(stamps_s (T,), positions_m (T, 3), waypoints_m (K, 3))`` of the random-waypoint capsule."""
    seq, path, mot = section(scn, "sequence"), section(scn, "path"), section(scn, "motion")
    dt = float(seq.get("interval_s", 0.1))
    T = int(round(float(seq.get("duration_s", 600.0)) / dt)) + 1
    cl = procedural_centerline(float(path.get("length_m", 1.0)), rng, radius_max_m=float(path.get("radius_m", 0.0125)),
                               abdomen_box_m=tuple(path.get("box_m", (0.36, 0.36, 0.16))),
                               min_self_distance_diameters=float(path.get("min_self_distance_diameters", 1.5)))
    spacing = float(path.get("waypoint_spacing_m", 0.025))
    s = np.arange(0.0, cl.length_m, spacing)
    wps = cl.frame_at(s)[0]
    mean, sd = float(mot.get("speed_mean_mps", 5e-4)), math.sqrt(float(mot.get("speed_var_m2ps2", 5e-7)))
    stop_max = float(mot.get("stop_max_s", 20.0))
    t = np.arange(T) * dt
    pos = np.zeros((T, 3))
    # piecewise schedule: (start time, end time, from, to) per leg and per stop
    k, now, p = 0, 0.0, wps[0].copy()
    events = []
    while now < t[-1] + dt and k + 1 < len(wps):
        stop = rng.uniform(0.0, stop_max)
        events.append((now, now + stop, p, p))
        now += stop
        v = max(abs(rng.normal(mean, sd)), 0.1 * mean)
        dur = float(np.linalg.norm(wps[k + 1] - wps[k])) / v
        events.append((now, now + dur, wps[k], wps[k + 1]))
        now += dur
        p = wps[k + 1]
        k += 1
    if now < t[-1] + dt:
        raise ConfigError(f"the path ({cl.length_m:.2f} m) is too short for {t[-1]:.0f} s: lengthen path.length_m")
    starts = np.array([e[0] for e in events])
    j = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(events) - 1)
    for i, (ti, ji) in enumerate(zip(t, j)):
        a, b, pa, pb = events[ji]
        f = 0.0 if b <= a else min(max((ti - a) / (b - a), 0.0), 1.0)
        pos[i] = pa + f * (pb - pa)
    return t, pos, wps[: k + 1]


def emulate(scn: dict, pos_m: np.ndarray, rx_m: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Readings per step and receiver ``(T, M)``: ``toa_s``, ``uwb_field_db``, ``rss_db`` (module docstring)."""
    uwb, mics = section(scn, "uwb"), section(scn, "mics")
    d = np.linalg.norm(pos_m[:, None, :] - rx_m[None, :, :], axis=2)
    eps = float(uwb.get("eps_r", 34.25))
    toa = math.sqrt(eps) * d / C_MPS + rng.normal(0.0, float(uwb.get("sigma_toa_s", 62.5e-12)), d.shape)
    eps_obs = eps * np.exp(rng.normal(0.0, float(uwb.get("sigma_e", 1.23)), d.shape))
    field = field_ratio(d, eps_obs, float(uwb.get("sigma_s_per_m", 2.17)), float(uwb.get("freq_hz", 4.1e9)))
    model = MicsRssiModel(float(mics.get("log10_alpha", -7.5)), float(mics.get("n", 6.65)),
                          float(mics.get("sigma_db", 5.5)))
    rss = model.mean_db(d) + rng.normal(0.0, model.sigma_db, d.shape)
    return {"toa_s": toa, "uwb_field_db": 20.0 * np.log10(field), "rss_db": rss}


def _world(scn: dict, seed: int):
    area = section(scn, "area")
    lo, hi = np.asarray(area.get("min_m", (-0.2, -0.2, -0.1)), float), np.asarray(area.get("max_m", (0.2, 0.2, 0.1)), float)
    ss = np.random.SeedSequence(seed)
    r_path, r_meas = (np.random.default_rng(s) for s in ss.spawn(2))
    t, pos, wps = truth_motion(scn, r_path)
    if np.any(pos < lo) or np.any(pos > hi):
        raise ConfigError("the capsule's path leaves the analysis area: shrink path.box_m")
    rx = _receivers(lo, hi)
    return lo, hi, t, pos, wps, rx, emulate(scn, pos, rx, r_meas)


def simulate_rf_tracking(scn: dict, seed: int, out_dir: str | os.PathLike) -> dict:
    """Write one run as files (module docstring); returns a summary."""
    lo, hi, t, pos, wps, rx, meas = _world(scn, seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = [f"rx{i}" for i in range(len(rx))]
    write_csv(out / "sensors.csv", ["sensor", "x", "y", "z"], [[n, *p] for n, p in zip(names, rx)])
    rows = [[float(t[k]), names[m], float(meas["rss_db"][k, m]), float(meas["toa_s"][k, m]),
             float(meas["uwb_field_db"][k, m])] for k in range(len(t)) for m in range(len(rx))]
    write_csv(out / "rf.csv", ["t", "sensor", "rss_dbm", "toa_s", "uwb_field_db"], rows)
    write_tum(out / "groundtruth.tum", t, pos, _headings(pos))
    write_json(out / "truth.json", {"eps_r": section(scn, "uwb").get("eps_r", 34.25), "waypoints_m": wps.tolist(),
                                    "path_travelled_m": float(simple_distance(pos)[-1])})
    write_json(out / "meta.json", {"scenario": scn.get("name"), "seed": seed, "kind": "rf_tracking",
                                   "interval_s": float(t[1] - t[0]), "n_steps": len(t), "area_min_m": lo.tolist(),
                                   "area_max_m": hi.tolist(), "uwb": section(scn, "uwb"), "mics": section(scn, "mics"),
                                   "units": "SI; rss in dB (003 Eq. 3 model), uwb_field_db = 20 log10(E/E0)"})
    return {"steps": len(t), "path_travelled_m": float(simple_distance(pos)[-1]), "waypoints": len(wps)}


def simulate_scenario(scn: dict, seed: int, out_dir: str | os.PathLike) -> str:
    """``testbed simulate`` for this kind of scenario: the files, and one line saying what was written."""
    s = simulate_rf_tracking(scn, seed, out_dir)
    return (f"{s['steps']} RF readings per receiver; path {s['path_travelled_m'] * 100:.1f} cm through "
            f"{s['waypoints']} waypoints")


def _headings(pos: np.ndarray) -> Rotation:
    d = np.diff(pos, axis=0, append=pos[-1:])
    quats, last = [], Rotation.identity()
    for v in d:
        n = np.linalg.norm(v)
        if n > 1e-12:
            last = Rotation.align_vectors([v / n], [[0.0, 0.0, 1.0]])[0]
        quats.append(last.as_quat())
    return Rotation.from_quat(quats)


def track_settings(scn: dict) -> TrackSettings:
    """The scenario's filter, motion and measurement models as :class:`bodyslam.systems.pf.TrackSettings`. The RSSI
    filter's resampling jitter (``rssi_jitter_m``, 1 mm) was chosen on ito_heading seeds 300-309, which no
    evaluation in the README uses: RSSI constrains a step far less than TOA, and with 0.2 mm the estimate lagged
    centimetres behind a capsule that moves on (mean RMS 42.5 / 5.2 / 7.5 mm for 0.2 / 1 / 2 mm)."""
    flt = section(scn, "filter")
    return TrackSettings.from_tables(section(scn, "uwb"), section(scn, "mics"), flt, section(scn, "motion"),
                                     resample_threshold=float(flt.get("resample_threshold", 0.06)))  # 002's value


def run_algorithm(name: str, scn: dict, lo, hi, t, rx, meas, rng) -> Track:
    """One algorithm on one run (``bodyslam.systems.pf.track``: the testbed only supplies the scenario's settings)."""
    return track(name, t, rx, meas, lo, hi, track_settings(scn), rng)


def _seed_task(args) -> dict:
    from threadpoolctl import threadpool_limits

    scn, seed = args
    with threadpool_limits(1):  # one BLAS thread per worker: spinning BLAS threads of two workers starve both
        return _seed_run(scn, seed)


def _seed_run(scn: dict, seed: int) -> dict:
    lo, hi, t, pos, wps, rx, meas = _world(scn, seed)
    algs = list(section(scn, "filter").get("algorithms", RF_TRACKING_ALGORITHMS))
    out = {"seed": seed, "t": t, "truth": pos, "errors": {}, "estimates": {}, "seconds": {}}
    ss = np.random.SeedSequence([seed, 1])
    for name, s in zip(algs, ss.spawn(len(algs))):
        t0 = time.perf_counter()
        est, eps, spread = run_algorithm(name, scn, lo, hi, t, rx, meas, np.random.default_rng(s))
        out["seconds"][name] = time.perf_counter() - t0
        out["estimates"][name] = est
        out.setdefault("spread", {})[name] = spread
        out["errors"][name] = np.linalg.norm(est - pos, axis=1)
        if eps is not None:
            out["eps_error"] = eps - float(section(scn, "uwb").get("eps_r", 34.25))
    hd = section(scn, "heading")
    if hd:
        name = hd.get("from", "rssi_pf")
        # 003 takes the first estimate as the first waypoint; the filter's first estimate is the mean of particles
        # spread over the whole area (its centre), 3.8-5.8 cm from the capsule on seeds 300-302, and that false
        # first leg went into every distance. The method starts once the cloud has found the capsule: its RMS
        # spread below start_spread_m (1 cm, a third of the waypoint spacing p_thr). The truth is measured from
        # the same step.
        k0 = converged_from(out["spread"][name], float(hd.get("start_spread_m", 0.01)))
        est, p0, t0_ = out["estimates"][name][k0:], pos[k0:], t[k0:]
        l_wp, Q, heads = waypoint_distance(est, int(hd.get("S", 20)), float(hd.get("r_thr_m", 0.003)),
                                           float(hd.get("p_thr_m", 0.03)))
        out["distance"] = {"true_m": float(simple_distance(p0)[-1]), "waypoint_m": float(l_wp[-1]),
                           "simple_m": float(simple_distance(est)[-1]), "start_s": float(t[k0])}
        out["heading_error_rad"] = _heading_errors(Q, est, p0, t0_)
    return out


def _heading_errors(Q: np.ndarray, est: np.ndarray, pos: np.ndarray, t: np.ndarray) -> list[float]:
    """Angle between each estimated leg (consecutive waypoints) and the true displacement over the same time
    (each waypoint's time: the step whose estimate it is)."""
    errs = []
    idx = [int(np.argmin(np.linalg.norm(est - q, axis=1))) for q in Q]
    for i in range(len(Q) - 1):
        a, b = idx[i], idx[i + 1]
        e, g = Q[i + 1] - Q[i], pos[b] - pos[a]
        if b <= a or np.linalg.norm(g) < 1e-6 or np.linalg.norm(e) < 1e-9:
            continue
        c = np.clip(e @ g / (np.linalg.norm(e) * np.linalg.norm(g)), -1.0, 1.0)
        errs.append(float(np.arccos(c)))
    return errs


def evaluate_rf_tracking(scn: dict, seeds: list[int], out_dir: str | os.PathLike, jobs: int | None = None,
                         progress: Callable[[str], None] | None = None) -> dict:
    """Every algorithm of the scenario on the same runs; ``report.json`` (+ html, plots) like Body-SLAM's."""
    from bodyslam.parallel import imap_tasks

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    runs = []
    for r in imap_tasks(_seed_task, [(scn, s) for s in seeds], jobs):
        runs.append(r)
        if progress:
            progress(f"seed {r['seed']} ({len(runs)}/{len(seeds)}): " + ", ".join(
                f"{a} {np.sqrt(np.mean(e[-int(len(e) * 0.1):] ** 2)) * 1000:.2f} mm" for a, e in r["errors"].items()))
    algs = list(runs[0]["errors"])
    tail = max(1, int(len(runs[0]["t"]) * 0.1))
    paper = section(scn, "paper")
    report = {"scenario": scn.get("name"), "seeds": list(seeds), "n_runs": len(seeds),
              "steps_per_run": len(runs[0]["t"]), "duration_s": float(runs[0]["t"][-1]), "algorithms": {},
              "paper": paper, "seconds": {"wall": round(time.perf_counter() - t_start, 2)}}
    for a in algs:
        e = np.concatenate([r["errors"][a] for r in runs]) * 1000
        end = np.concatenate([r["errors"][a][-tail:] for r in runs]) * 1000
        at_end = np.array([r["errors"][a][-1] for r in runs]) * 1000
        report["algorithms"][a] = {
            "mean_error_mm": float(e.mean()), "rmse_mm": float(np.sqrt(np.mean(e**2))),
            "median_error_mm": float(np.median(e)), "p90_error_mm": float(np.percentile(e, 90)),
            "max_error_mm": float(e.max()),
            "rms_last_10pct_mm": float(np.sqrt(np.mean(end**2))),  # the papers' "at 600 s" figures
            "rms_at_end_mm": float(np.sqrt(np.mean(at_end**2))),
            "seconds_per_run": float(np.mean([r["seconds"][a] for r in runs])),
            "steps_per_s": float(len(runs[0]["t"]) / np.mean([r["seconds"][a] for r in runs]))}
    if "eps_error" in runs[0]:
        ee = np.stack([r["eps_error"] for r in runs])
        report["permittivity_rms_error_last_10pct"] = float(np.sqrt(np.mean(ee[:, -tail:] ** 2)))
    if "distance" in runs[0]:
        dl = np.array([[r["distance"]["waypoint_m"] - r["distance"]["true_m"],
                        r["distance"]["simple_m"] - r["distance"]["true_m"]] for r in runs]) * 100
        he = np.concatenate([r["heading_error_rad"] for r in runs]) if any(r["heading_error_rad"] for r in runs) \
            else np.array([np.nan])
        report["moving_distance"] = {"waypoint_mean_error_cm": float(dl[:, 0].mean()),
                                     "waypoint_mean_abs_error_cm": float(np.abs(dl[:, 0]).mean()),
                                     "simple_mean_error_cm": float(dl[:, 1].mean()),
                                     "true_mean_cm": float(np.mean([r["distance"]["true_m"] for r in runs]) * 100),
                                     "start_mean_s": float(np.mean([r["distance"]["start_s"] for r in runs]))}
        report["heading"] = {"rms_error_deg": float(np.degrees(np.sqrt(np.nanmean(he**2)))),
                             "n_legs": int(np.isfinite(he).sum())}
    write_json(out / "report.json", report)
    _plots(out, runs, algs)
    _html(out, report)
    return report


evaluate_scenario = evaluate_rf_tracking  # what ``testbed evaluate`` calls for this kind of scenario


def _plots(out: Path, runs: list[dict], algs: list[str]) -> None:
    cols = [(214, 39, 40), (31, 119, 180), (150, 150, 150)]
    t = runs[0]["t"]
    f = Figure("RMS error over runs against time (Fig. 7)", "time (s)", "RMS error (mm)")
    for a, c in zip(algs, cols):
        e = np.sqrt(np.mean(np.stack([r["errors"][a] for r in runs]) ** 2, axis=0)) * 1000
        f.line(t, e, label=a, colour=c)
    write_image(out / "error_vs_time.png", f.image())
    f = Figure("Error CDF, all runs (Fig. 8)", "error (mm)", "fraction of steps")
    for a, c in zip(algs, cols):
        x = np.sort(np.concatenate([r["errors"][a] for r in runs]) * 1000)
        f.line(x, np.arange(1, len(x) + 1) / len(x), label=a, colour=c, step=True)
    write_image(out / "error_cdf.png", f.image())
    r0 = runs[0]
    f = Figure(f"Trajectories, seed {r0['seed']} (x-z)", "x (cm)", "z (cm)", size=(640, 520), equal=True)
    for a, c in zip(algs, cols):
        f.line(r0["estimates"][a][:, 0] * 100, r0["estimates"][a][:, 2] * 100, label=a, colour=c)
    f.line(r0["truth"][:, 0] * 100, r0["truth"][:, 2] * 100, label="truth", colour=(0, 0, 0))
    write_image(out / "trajectories_xz.png", f.image())


def _html(out: Path, report: dict) -> None:
    paper = report.get("paper", {})
    rows = [[LABELS.get(a, a), f"{v['rms_last_10pct_mm']:.2f}", paper.get(a + "_rms_mm", ""),
             f"{v['mean_error_mm']:.2f}", f"{v['p90_error_mm']:.2f}", f"{v['steps_per_s']:.0f}"]
            for a, v in report["algorithms"].items()]
    body = table(["algorithm", "RMS, last 10% (mm)", "paper (mm)", "mean (mm)", "p90 (mm)", "steps/s"], rows)
    if "moving_distance" in report:
        md, hd = report["moving_distance"], report["heading"]
        body += (f"<p>Moving distance at the end: waypoint method error {md['waypoint_mean_error_cm']:.2f} cm "
                 f"(mean |error| {md['waypoint_mean_abs_error_cm']:.2f}), simple integration "
                 f"{md['simple_mean_error_cm']:.2f} cm, true {md['true_mean_cm']:.1f} cm; heading RMS error "
                 f"{hd['rms_error_deg']:.1f} deg over {hd['n_legs']} legs.</p>")
    write_report_page(out, report["scenario"], f"{report['n_runs']} runs of {report['duration_s']:.0f} s "
                      f"({report['steps_per_run']} steps).", body,
                      ["error_vs_time.png", "error_cdf.png", "trajectories_xz.png"])


def report_line(rep: dict) -> str:
    paper = rep.get("paper", {})
    parts = [f"{a}: RMS {v['rms_last_10pct_mm']:.2f} mm (paper {paper.get(a + '_rms_mm', '-')})"
             for a, v in rep["algorithms"].items()]
    line = f"{rep['n_runs']} runs of {rep['scenario']} ({rep['duration_s']:.0f} s): " + "; ".join(parts)
    if "moving_distance" in rep:
        line += (f"; moving distance error {rep['moving_distance']['waypoint_mean_error_cm']:.2f} cm (simple "
                 f"{rep['moving_distance']['simple_mean_error_cm']:.2f}), heading RMS "
                 f"{rep['heading']['rms_error_deg']:.1f} deg")
    if "permittivity_rms_error_last_10pct" in rep:
        line += f"; permittivity RMS error {rep['permittivity_rms_error_last_10pct']:.2f}"
    return line

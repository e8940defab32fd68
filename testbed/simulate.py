"""Render a scenario into a sequence directory (SPEC.md "Files").

What the pipeline may read (what a capsule gives):
    frames/NNNNNN.png   capsule video, RGB
    meta.json           frame rate, image size, camera model, nominal tube radius, provenance
What only scoring may read (ground truth):
    groundtruth.tum     T_w_c per frame (TUM, readable by evo)
    motion_truth.csv    per-step truth: frame,t,distance_m,roll_rad,pitch_rad,yaw_rad,tilt_rad,label
    labels.csv          per-frame FT/FL label and phase
    centerline.csv      the path's centre line (the "map")
    truth.json          sequence statistics of the truth
    depth/NNNNNN.png    optional: range along each pixel's ray, uint16 in 0.1 mm (0 = no wall): to the wall as it
                        is at that frame's time ([motility] moves it), not to fluid or debris (testbed.content)

``meta.json`` is written last, so a run that was killed leaves no ``meta.json`` and is visibly incomplete.
Frames render in parallel worker processes (``jobs``), each with its own renderer, pinned to its own core and
with OpenMP/BLAS pools limited to one thread (they busy-wait and would steal the renderer's core). Workers are
*spawned*, not forked: the parent already runs Embree's threads, and forking a threaded process can deadlock.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from bodyslam import __version__
from bodyslam.geometry import relative_motion
from bodyslam.io import frame_name, prepare_output_dir, write_csv, write_image, write_json, write_tum
from bodyslam.meta import write_meta
from bodyslam.parallel import available_cores
from testbed.motion import PHASES, CapsuleTrajectory, generate_motion, label_frames
from testbed.render import RANGE_SCALE_M, RaycastRenderer, encode_range, make_renderer
from testbed.scenario import World, build_world

log = logging.getLogger(__name__)

__all__ = ["simulate", "prepare_output_dir", "wall_at", "moving_wall_cast"]

_W: dict = {}  # per-process state of render workers (set before fork / in the initializer)


def _pin_to_one_core() -> None:
    """Pin this worker to one core of those allowed (worker i -> i-th core).

    Embree's TBB worker threads spin after each ray query; unpinned, two render processes steal each other's
    cores and run slower together than one alone (measured: 21.9 vs 26.1 frames/s on 2 cores).
    """
    ident = mp.current_process()._identity
    if not ident or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) > 1:
        os.sched_setaffinity(0, {cores[(ident[0] - 1) % len(cores)]})


def _init_worker(state: dict | None = None) -> None:
    import cv2

    if state is not None:  # a spawned worker receives the world by pickle
        _W.update(state)
        _pin_to_one_core()
        from threadpoolctl import threadpool_limits

        # OpenMP/BLAS pools (numpy's matmul) busy-wait between calls: with one process per core they would only
        # steal that core from the renderer (measured: 2 x 100% CPU per render without this limit)
        threadpool_limits(1)
    cv2.setNumThreads(1)  # one render process per core: OpenCV's own threads would only oversubscribe the cores
    w: World = _W["world"]
    _W["fov"] = w.camera.fov_mask()
    _W["renderer"] = make_renderer(w.render_backend, w.tube, w.texture, w.camera, w.lighting, mesh=_W.get("mesh"))


def rear_extrinsics(baseline_m: float) -> tuple[Rotation, np.ndarray]:
    """``T_front_rear``: the rear lens looks backward (rotated pi about y), ``baseline_m`` behind the front lens."""
    return Rotation.from_rotvec([0.0, np.pi, 0.0]), np.array([0.0, 0.0, -baseline_m])


def wall_at(world: World, traj: CapsuleTrajectory, k: int):
    """The moving wall's mesh around the capsule at frame ``k``'s time (:mod:`testbed.motility`)."""
    mot = world.motility
    s_cap, t_k = float(traj.s_m[k]), float(traj.stamps_s[k])
    return world.tube.mesh_window(s_cap - mot.window_m, s_cap + mot.window_m,
                                  lambda s: mot.radius_factor(s, t_k, s_cap))


def moving_wall_cast(world: World, traj: CapsuleTrajectory, renderer: RaycastRenderer,
                     progress: Callable[[int, int], None] | None = None):
    """The ray caster :func:`testbed.motion.label_frames` gets when the wall moves: it casts the same number of rays
    for each frame, frame after frame, and frame k's rays meet the wall as it is at frame k's time -- the truth's
    FT/FL occlusion test sees a ring that closes the lumen ahead. ``progress(done, total)``: called after each frame
    (one process builds each frame's wall: 0.04-0.06 s a frame; a 10,000-frame `realistic_exam` spent ~9.5 minutes
    here before its first frame rendered)."""

    def cast(origins_w: np.ndarray, dirs_w: np.ndarray):
        n = len(traj.s_m)
        if len(origins_w) % n or not len(origins_w):
            raise ValueError(f"the same number of rays for each of the {n} frames expected, got {len(origins_w)}")
        m = len(origins_w) // n
        range_m = np.full(len(origins_w), np.nan)
        for k in range(n):
            renderer.set_mesh(wall_at(world, traj, k))
            range_m[k * m:(k + 1) * m] = renderer.cast(origins_w[k * m:(k + 1) * m], dirs_w[k * m:(k + 1) * m])[0]
            if progress:
                progress(k + 1, n)
        return (range_m,)

    return cast


def _with_content(res, R_w_c: Rotation, p_w_c: np.ndarray, k: int) -> np.ndarray:
    """A camera's rendered colour with the lumen's fluid and debris drawn in (testbed.content), when there are
    any: in 3-D, in front of or hidden by the wall, lit at that frame's exposure."""
    w: World = _W["world"]
    if w.content is None:
        return res.rgb
    traj: CapsuleTrajectory = _W["traj"]
    return w.content.apply(res.rgb, res.range_m, _W["renderer"], R_w_c.as_matrix(), p_w_c, float(traj.stamps_s[k]),
                           float(traj.s_m[k]), res.exposure)


def _render_one(k: int) -> int:
    w: World = _W["world"]
    traj: CapsuleTrajectory = _W["traj"]
    out: Path = _W["out"]
    R_w_c, p_w_c = traj.rotations_w_c[k], traj.positions_w_m[k]
    if w.motility.active:  # the wall as it is at this frame's time, around the capsule (testbed.motility)
        _W["renderer"].set_mesh(wall_at(w, traj, k))
    res = _W["renderer"].render(R_w_c, p_w_c)
    rng = np.random.default_rng([w.seed, 7919, k])  # per-frame noise stream: same output for any job count
    rgb = _with_content(res, R_w_c, p_w_c, k)
    if w.bubbles.bubble_prob > 0:
        rgb = w.bubbles.apply(rgb, np.random.default_rng([w.seed, 7919, k, 2]), _W["fov"])
    write_image(out / "frames" / frame_name(k), w.optics.apply(w.noise.apply(rgb, rng)))
    if w.write_depth:
        write_image(out / "depth" / frame_name(k), encode_range(res.range_m))
    if w.rear_baseline_m is not None:
        R_c_r, t_c_r = rear_extrinsics(w.rear_baseline_m)
        R_w_r, p_w_r = R_w_c * R_c_r, p_w_c + R_w_c.apply(t_c_r)
        rgb_rear = _with_content(_W["renderer"].render(R_w_r, p_w_r), R_w_r, p_w_r, k)
        rng = np.random.default_rng([w.seed, 7919, k, 1])
        write_image(out / "frames_rear" / frame_name(k), w.optics.apply(w.noise.apply(rgb_rear, rng)))
    return k


SEQUENCE_FILES = ("meta.json", "groundtruth.tum", "motion_truth.csv", "labels.csv", "centerline.csv", "truth.json",
                  "rf.csv", "sensors.csv")
SEQUENCE_FRAME_DIRS = ("frames", "depth", "frames_rear")


def clear_earlier_sequence(out: Path) -> None:
    """Remove what an earlier sequence written into ``out`` left (a run with ``force``): its meta.json first (a run
    killed from here on is visibly incomplete), its truth and RF files, and its frames' PNGs -- a shorter or
    different sequence must not keep the earlier one's frames past its own. Other files are left alone."""
    for name in SEQUENCE_FILES:
        (out / name).unlink(missing_ok=True)
    for sub in SEQUENCE_FRAME_DIRS:
        if (out / sub).is_dir():
            for f in (out / sub).glob("*.png"):
                f.unlink()


# a tube's radius profile whose spread is below this (m) is one radius: the mean of a constant profile differs from
# it by float rounding only (thesis: 0.015000000000000003)
RADIUS_SPREAD_FLOOR_M = 1e-7
# angles around the tube at which the folds' inward bulge is averaged (told_radius)
BULGE_ANGLES = 64


def told_radius(world: World) -> dict:
    """What meta.json tells the pipeline of the lumen radius: ``tube_radius_m``, ``tube_radius_sd_m`` and
    ``tube_radius_source``. A world with a prior ([tube] ``radius_in_meta_m``: the realistic testbed) tells the
    prior and its spread. Otherwise the tube's own (docs/RESULTS.md, "The radius a testbed tube states", session 55):

    - the mean distance of its wall from the centre line, over the tube's length and around it: the centre line's
      radius less the folds' inward bulge (``demo`` 2.0%, ``exam`` 1.7% of it). Told the centre line's radius, the
      tube fit read `exam`'s steps 2-3% long on every seed (0.999-1.006 with the folds taken out);
    - as its 1-sigma, the radius's spread along the tube (the centre line's radius's standard deviation, scaled as
      the mean): the tube estimator takes one radius for every step, and where the tube tapers or its radius varies
      (``demo``, ``exam``: +- 1 mm) the wall a step sees is as far off the mean as that says. The folds' own ridges,
      8 mm apart, average out over the centimetres of wall a step sees, so they are not part of it. Stated 0, the
      steps' 1-sigma was ~3x too narrow there (inside 1-sigma: `exam` 0.28-0.38, the demo 0.14).

    A tube of one radius without folds (``thesis``) says 0: known exactly."""
    if world.radius_in_meta_m is not None:
        return {"tube_radius_m": float(world.radius_in_meta_m), "tube_radius_sd_m": float(world.radius_sd_in_meta_m),
                "tube_radius_source": "population prior (the true radius is hidden)"}
    cl = world.tube.centerline  # sampled at uniform arc length
    r = np.asarray(cl.radius_m, dtype=np.float64)
    phi = np.linspace(0.0, 2.0 * np.pi, BULGE_ANGLES, endpoint=False)
    bulge = world.tube.folds.profile(np.asarray(cl.s_m, dtype=np.float64)[:, None], phi[None, :]).mean(axis=1)
    mean = float(np.mean(r * (1.0 - bulge)))
    sd = float(np.std(r)) * mean / float(np.mean(r))
    if sd < RADIUS_SPREAD_FLOOR_M:
        return {"tube_radius_m": mean, "tube_radius_sd_m": 0.0, "tube_radius_source": "mean of this tube"}
    return {"tube_radius_m": mean, "tube_radius_sd_m": sd,
            "tube_radius_source": "mean of this tube's wall from its centre line (folds included); its 1-sigma is "
                                  "the radius's spread along the tube"}


def simulate(
    scenario: dict,
    seed: int,
    out_dir: str | os.PathLike,
    n_frames: int | None = None,
    jobs: int | None = None,
    force: bool = False,
    progress: Callable[[int, int], None] | None = None,
    label_progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Render ``scenario`` with ``seed`` into ``out_dir``; returns the truth statistics written to truth.json.
    ``progress``: the frames rendered; ``label_progress``: the FT/FL truth's frames where the wall moves (before the
    rendering; :func:`moving_wall_cast`)."""
    out = Path(out_dir)
    world = build_world(scenario, seed, n_frames)
    prepare_output_dir(out, force)
    clear_earlier_sequence(out)
    traj = generate_motion(world.tube, world.n_frames, world.motion, world.rngs["motion"])
    mesh = world.tube.mesh()
    labeller = RaycastRenderer(world.tube, world.texture, world.camera, world.lighting, mesh=mesh)
    cast = moving_wall_cast(world, traj, labeller, label_progress) if world.motility.active else labeller.cast
    labels = label_frames(world.tube, traj, world.camera.fov_deg, cast, world.motion.ft_rule)
    del labeller
    (out / "frames").mkdir(exist_ok=True)
    if world.write_depth:
        (out / "depth").mkdir(exist_ok=True)
    if world.rear_baseline_m is not None:
        (out / "frames_rear").mkdir(exist_ok=True)

    _W.update(world=world, traj=traj, out=out, mesh=mesh)
    n = world.n_frames
    if jobs is None:  # spawning a worker costs ~2 s (imports, world by pickle, BVH): worth it for longer runs
        jobs = available_cores() if n >= 60 else 1
    jobs = max(1, min(int(jobs), n))
    try:
        if jobs == 1:
            _init_worker()
            import cv2

            cv2.setNumThreads(-1)  # restore OpenCV's default in this (the caller's) process
            for k in range(n):
                _render_one(k)
                if progress:
                    progress(k + 1, n)
        else:
            # "spawn", not "fork": this process already runs Embree's (TBB) threads, and a child forked from a
            # threaded parent can deadlock on a lock some thread held at fork time (seen: simulate hung).
            state = dict(world=world, traj=traj, out=out, mesh=mesh)
            with mp.get_context("spawn").Pool(jobs, initializer=_init_worker, initargs=(state,)) as pool:
                for i, _ in enumerate(pool.imap_unordered(_render_one, range(n), chunksize=2)):
                    if progress:
                        progress(i + 1, n)
    finally:
        _W.clear()

    write_tum(out / "groundtruth.tum", traj.stamps_s, traj.positions_w_m, traj.rotations_w_c)
    m = relative_motion(traj.rotations_w_c, traj.positions_w_m)
    rows = [
        [k, traj.stamps_s[k], m["distance_m"][k - 1], m["roll_rad"][k - 1], m["pitch_rad"][k - 1],
         m["yaw_rad"][k - 1], m["tilt_rad"][k - 1], labels[k]]
        for k in range(1, n)
    ]
    write_csv(out / "motion_truth.csv",
              ["frame", "t", "distance_m", "roll_rad", "pitch_rad", "yaw_rad", "tilt_rad", "label"], rows)
    write_csv(out / "labels.csv", ["frame", "t", "label", "phase", "s_m"],
              [[k, traj.stamps_s[k], labels[k], PHASES[traj.phase[k]], traj.s_m[k]] for k in range(n)])
    world.tube.centerline.write_csv(out / "centerline.csv")
    if world.rf is not None:
        from testbed.rf import emulate_rf, write_rf

        meas = emulate_rf(traj.positions_w_m, world.rf["layout"], world.rf["pathloss"], world.rf["toa"],
                          world.rngs["rf"], world.rf["channel"])
        world.rf["layout"].write_csv(out / "sensors.csv")
        write_rf(out / "rf.csv", traj.stamps_s, world.rf["layout"], meas)
    truth = {
        "n_frames": n,
        "n_steps": n - 1,
        "mean_step_cm": float(np.mean(np.abs(m["distance_m"])) * 100),
        "mean_roll_deg": float(np.degrees(np.mean(np.abs(m["roll_rad"])))),
        "mean_tilt_deg": float(np.degrees(np.mean(m["tilt_rad"]))),
        "path_travelled_m": float(np.sum(np.abs(m["distance_m"]))),
        # net progress along the centre line: far below the path travelled where the lateral wobble takes most of
        # the calibrated mean step (a capsule that jitters in place; testbed.motion warns)
        "advance_m": float(traj.s_m[-1] - traj.s_m[0]),
        "n_ft": int(np.sum(labels == "FT")),
        "n_fl": int(np.sum(labels == "FL")),
        "path_length_m": world.tube.centerline.length_m,
    }
    write_json(out / "truth.json", truth)
    cam = world.camera
    meta = {
        "format": "bodyslam-sequence/1",
        "n_frames": n,
        "frame_rate_hz": world.motion.frame_rate_hz,
        "image_width": cam.width,
        "image_height": cam.height,
        "camera": cam.to_dict(),
        # the nominal lumen radius the pipeline is told and its 1-sigma (told_radius)
        **told_radius(world),
        # the lumen's departure from a cylinder as a relative 1-sigma of each step's distance: 0 on a cylinder
        "lumen_shape_sd_rel": float(world.shape_sd_in_meta_rel),
        "frames": {"dir": "frames", "pattern": "{index:06d}.png", "color": "RGB"},
        "depth": (
            {"dir": "depth", "kind": "range_along_ray", "scale_m_per_unit": RANGE_SCALE_M, "invalid_value": 0}
            if world.write_depth else None
        ),
        "units": {"length": "m", "angle": "rad", "time": "s"},
        "source": {"generator": "testbed", "version": __version__, "scenario": scenario.get("name"),
                   "seed": seed},
    }
    if world.rf is not None:  # the RF calibration a real system would have (path-loss model), not ground truth
        from dataclasses import asdict

        meta["rf"] = {"file": "rf.csv", "sensors": "sensors.csv", "pathloss": asdict(world.rf["pathloss"]),
                      "toa": asdict(world.rf["toa"])}
    if world.rear_baseline_m is not None:
        R_c_r, t_c_r = rear_extrinsics(world.rear_baseline_m)
        meta["rear_camera"] = {"camera": cam.to_dict(), "frames": {"dir": "frames_rear"},
                               "T_front_rear": {"q_xyzw": R_c_r.as_quat().tolist(), "t_m": t_c_r.tolist()}}
    write_meta(out, meta)  # validated by the reader every command uses (bodyslam.meta)
    log.info("wrote %d frames to %s", n, out)
    return truth

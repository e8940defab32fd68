"""Rendered frames per second: fisheye 320x320, colour + range, on this machine.

Prints one process's render time per frame (ray cast vs shading), the pyrender backend's, and the throughput of `testbed simulate`'s
parallel renderer with 1 and 2 worker processes (frames rendered, noised and written as PNG).

    .venv/bin/python benchmarks/bench_render.py [--frames 120]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time

import numpy as np

from testbed.motion import generate_motion
from testbed.render import RaycastRenderer
from testbed.scenario import build_world, load_scenario
from testbed.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=120)
    args = ap.parse_args()
    overrides = ["camera.width=320", "camera.height=320"]
    scn = load_scenario("thesis", overrides)
    world = build_world(scn, 0, args.frames)
    traj = generate_motion(world.tube, args.frames, world.motion, world.rngs["motion"])
    t0 = time.perf_counter()
    r = RaycastRenderer(world.tube, world.texture, world.camera, world.lighting)
    setup = time.perf_counter() - t0
    r.render(traj.rotations_w_c[0], traj.positions_w_m[0])  # warm-up
    t_cast = t_all = 0.0
    dirs = r._rays_c
    for k in range(args.frames):
        R, p = traj.rotations_w_c[k], traj.positions_w_m[k]
        a = time.perf_counter()
        r.cast(np.broadcast_to(p, dirs.shape), R.apply(dirs))
        b = time.perf_counter()
        r.render(R, p)
        c = time.perf_counter()
        t_cast += b - a
        t_all += c - b
    n = args.frames
    print(f"mesh {len(r.mesh.faces)} triangles, scene set-up {setup * 1000:.0f} ms")
    print(f"one process: render {t_all / n * 1000:.1f} ms/frame ({n / t_all:.1f} frames/s), "
          f"of which ray cast {t_cast / n * 1000:.1f} ms")
    try:
        from testbed.render_gl import PyrenderRenderer

        g = PyrenderRenderer(world.tube, world.texture, world.camera, world.lighting, mesh=r.mesh)
        g.render(traj.rotations_w_c[0], traj.positions_w_m[0])
        m = min(n, 30)
        a = time.perf_counter()
        for k in range(m):
            g.render(traj.rotations_w_c[k], traj.positions_w_m[k])
        el = time.perf_counter() - a
        print(f"pyrender backend (OpenGL/EGL, {len(g._face_of)} cube faces of {g.face_px} px): "
              f"{el / m * 1000:.1f} ms/frame ({m / el:.1f} frames/s)")
    except Exception as exc:  # noqa: BLE001 - report, do not stop the benchmark
        print(f"pyrender backend unavailable: {exc}")
    for jobs in (1, 2):
        with tempfile.TemporaryDirectory() as d:
            a = time.perf_counter()
            simulate(scn, 0, d, n_frames=n, jobs=jobs, force=True)
            el = time.perf_counter() - a
        print(f"testbed simulate, {jobs} process(es), {n} frames incl. set-up and PNG writing: "
              f"{n / el:.1f} frames/s")
    print(f"cores: {mp.cpu_count()}")


if __name__ == "__main__":
    main()

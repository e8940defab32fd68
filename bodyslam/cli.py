"""The ``bodyslam`` command: the pipeline's stages for users (one subcommand per stage as they land).

Subcommands
-----------
check SEQDIR   read a sequence directory's meta.json and every frame (streamed), report bad frames by name.
"""

from __future__ import annotations

import argparse
import sys

from bodyslam.cliutil import Progress, run_cli


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bodyslam", description="Body-SLAM capsule localization toolkit")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="validate a sequence directory (meta.json, every frame)")
    c.add_argument("seqdir")
    return p


def _check(args) -> int:
    from pathlib import Path

    from bodyslam.camera import camera_from_dict
    from bodyslam.errors import InputError
    from bodyslam.io import frame_name, read_image, read_meta

    seq = Path(args.seqdir)
    meta = read_meta(seq)
    cam = camera_from_dict(meta["camera"])
    n = int(meta["n_frames"])
    frames_dir = seq / meta.get("frames", {}).get("dir", "frames")
    bad = []
    prog = Progress("check")
    for k in range(n):
        path = frames_dir / frame_name(k)
        try:
            img = read_image(path)
            if img.shape[:2] != (cam.height, cam.width):
                raise InputError(f"{path}: size {img.shape[1]}x{img.shape[0]} != camera {cam.width}x{cam.height}")
        except InputError as exc:
            bad.append(str(exc))
        prog(k + 1, n)
    print(f"{seq}: {n} frames, {cam.width}x{cam.height}, camera {meta['camera'].get('model')} "
          f"fov {cam.fov_deg:.1f} deg, {meta['frame_rate_hz']} frames/s; {len(bad)} bad frame(s)")
    for b in bad:
        print(f"  bad: {b}")
    return 1 if bad else 0


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    return {"check": _check}[args.cmd](args)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return run_cli(_main, argv, verbose="-v" in argv or "--verbose" in argv)


if __name__ == "__main__":
    sys.exit(main())

"""How much texture feature matching finds in capsule frames: the testbed's beside real ones.

Feature matching lives on the mucosa's fine texture, and the testbed's texture is a stated choice
(``testbed/texture.py``: grain, vessels, folds). This prints, per source (a frame folder, a sequence directory
with ``frames/``, or single images), statistics of the frames as the matcher sees them: every frame resized to
``--size`` px (default 420, the testbed's; features scale with the image), inside the field of view (detected
from the frames as ``bodyslam`` does, or the non-black pixels eroded by 7 px for fewer than 3 frames), brightness
stretched by the matcher's own 1st-99th percentile rule (a :class:`bodyslam.vision.matching.Matcher`, whose mask
is the field eroded at its rim):

- SIFT keypoints per frame at OpenCV's default contrast threshold 0.04 and at the pipeline's 0.01;
- the median absolute Laplacian (3x3) inside the field: the fine grain's contrast, in grey levels.

Measured (session 34; ``bench_texture.py ../shared/data/real/capsule_colon_imeval/frames
../shared/data/real/capsule_colon_cce S560 L560``, where S560 is ``testbed simulate realistic --seed 560
--frames 100`` and L560 the same with ``--set texture.grain_strength=0.05 --set texture.vessel_strength=0.25``;
docs/RESULTS.md, "The realistic mucosa against real frames"): the four real PillCam COLON 2 frames give ~210
keypoints at 0.04 where the realistic testbed gives ~470-590, and a Laplacian of ~10 against ~18-20.

    .venv/bin/python benchmarks/bench_texture.py SOURCE [SOURCE ...] [--max-frames N] [--size PX]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bodyslam.errors import BodySlamError, InputError  # noqa: E402
from bodyslam.io import read_image  # noqa: E402
from bodyslam.camera import FisheyeCamera  # noqa: E402
from bodyslam.exam.batch import DEFAULT_FOV_DEG  # noqa: E402
from bodyslam.vision.matching import Matcher, detect_fov_mask  # noqa: E402

IMAGE_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def frame_files(src: Path, max_frames: int) -> list[Path]:
    """A source's frames: up to ``max_frames`` spread evenly over its folder (or the one image)."""
    if src.is_file():
        return [src]
    d = src / "frames" if (src / "frames").is_dir() else src
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_EXT)
    if not files:
        raise SystemExit(f"bench_texture: no image files in {d}")
    return [files[i] for i in np.unique(np.linspace(0, len(files) - 1, min(max_frames, len(files))).astype(int))]


def field_of_view(frames: list[np.ndarray]) -> np.ndarray:
    """``uint8`` mask: detected as the pipeline detects it (3+ frames), else the non-black pixels eroded."""
    if len(frames) >= 3:
        try:
            return detect_fov_mask(frames).astype(np.uint8) * 255
        except BodySlamError:
            pass
    g = cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY)
    return cv2.erode((g > 20).astype(np.uint8) * 255, np.ones((15, 15), np.uint8))


def texture_stats(files: list[Path], size: int) -> dict:
    frames = [read_image(f) for f in files]
    odd = [f.name for f, x in zip(files, frames) if x.shape[:2] != frames[0].shape[:2]]
    if odd:  # the field of view is detected over the frames, pixel by pixel: one size per source
        h, w = frames[0].shape[:2]
        raise InputError(f"{len(odd)} frame(s) not {w}x{h} like {files[0].name} (first: {odd[0]}); give one "
                         "camera's frames per source")
    fov = cv2.resize(field_of_view(frames), (size, size), interpolation=cv2.INTER_NEAREST) > 0
    # the matcher itself (its field of view eroded at the rim, its brightness stretch); the lens does not matter
    matcher = Matcher(FisheyeCamera.equidistant(size, size, DEFAULT_FOV_DEG), "fast", mask=fov)
    mask = matcher.mask
    sift = {ct: cv2.SIFT_create(contrastThreshold=ct) for ct in (0.04, 0.01)}
    rows = []
    for rgb in frames:
        g = matcher.features(cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA)).gray
        lap = np.abs(cv2.Laplacian(g.astype(np.float32), cv2.CV_32F, ksize=3))[mask > 0]
        rows.append([len(sift[0.04].detect(g, mask)), len(sift[0.01].detect(g, mask)), float(np.median(lap))])
    a = np.asarray(rows, float)
    return {"frames": len(rows), "sift_004": a[:, 0].mean(), "sift_001": a[:, 1].mean(), "lap": a[:, 2].mean()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sources", nargs="+", type=Path)
    ap.add_argument("--max-frames", type=int, default=20,
                    help="at most N frames a source, spread evenly over it (default 20)")
    ap.add_argument("--size", type=int, default=420, help="frames resized to this many px square (default 420)")
    a = ap.parse_args(argv)
    if a.max_frames < 1 or a.size < 64:
        ap.error("--max-frames must be >= 1, --size >= 64")
    missing = [str(src) for src in a.sources if not src.exists()]
    if missing:
        print(f"bench_texture: not found: {', '.join(missing)}", file=sys.stderr)
        return 2
    cv2.setNumThreads(1)
    print(f"{'source':<60} {'frames':>6} {'SIFT@0.04':>10} {'SIFT@0.01':>10} {'median |Laplacian|':>19}")
    for src in a.sources:
        try:
            s = texture_stats(frame_files(src, a.max_frames), a.size)
        except BodySlamError as exc:
            print(f"bench_texture: {src}: {exc}", file=sys.stderr)
            return 2
        print(f"{str(src)[-60:]:<60} {s['frames']:>6} {s['sift_004']:>10.0f} {s['sift_001']:>10.0f} {s['lap']:>19.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

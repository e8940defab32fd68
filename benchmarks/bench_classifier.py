"""FT/FL classifier: accuracy on unseen seeds and textures (confusion matrix), nine vs rich features, and the
throughput of segmentation + classification.

Training sequences: `classifier` scenario, seeds 1-8, lighting intensity, tube radius and folds varied per seed.
Test sequences: seeds 101-104 (so textures and paths never seen in training), with lighting and radii that
include values not used in training. Labels are the testbed's geometric FT/FL rule (labels.csv).

    .venv/bin/python benchmarks/bench_classifier.py [--save-default]   # --save-default writes the shipped model

Throughput: the whole `bodyslam classify` process on a 200-frame 320x320 sequence, 2 cores.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bodyslam.vision.classify import FEATURES_9, FEATURES_RICH, features_of_frames, train
from bodyslam.io import frame_name
from bodyslam.meta import read_meta
from testbed.scenario import load_scenario
from testbed.simulate import simulate

TRAIN = [(s, {"lighting.intensity": li, "tube.radius_m": r, "tube.fold_depth_frac": fd})
         for s, li, r, fd in [(1, 1.6, 0.015, 0.1), (2, 1.0, 0.0125, 0.0), (3, 2.4, 0.015, 0.1),
                              (4, 0.7, 0.0125, 0.1), (5, 1.6, 0.0125, 0.0), (6, 1.2, 0.015, 0.0),
                              (7, 2.0, 0.0125, 0.1), (8, 0.9, 0.015, 0.1)]]
TEST = [(s, {"lighting.intensity": li, "tube.radius_m": r, "tube.fold_depth_frac": fd})
        for s, li, r, fd in [(101, 1.4, 0.014, 0.05), (102, 0.8, 0.0135, 0.1), (103, 2.2, 0.015, 0.0),
                             (104, 1.1, 0.0125, 0.12)]]


def render(root: Path, items) -> list[Path]:
    out = []
    for seed, sets in items:
        d = root / f"cls_{seed}"
        if not (d / "meta.json").exists():
            scn = load_scenario("classifier", [f"{k}={v}" for k, v in sets.items()])
            simulate(scn, seed, d, force=True)
        out.append(d)
    return out


def dataset(dirs: list[Path]):
    X, y = [], []
    for d in dirs:
        meta = read_meta(d)
        cam = meta.camera_model()
        labels = np.loadtxt(d / "labels.csv", delimiter=",", skiprows=1, usecols=2, dtype=str)
        paths = [d / "frames" / frame_name(k) for k in range(meta.n_frames)]
        for (st, _, f), lab in zip(features_of_frames(paths, cam.fov_mask()), labels):
            if st == "ok":
                X.append(f)
                y.append(lab)
    return np.array(X), np.array(y)


def confusion(y, p) -> str:
    m = {(a, b): int(np.sum((y == a) & (p == b))) for a in ("FT", "FL") for b in ("FT", "FL")}
    return (f"true FT -> FT {m['FT', 'FT']}, FL {m['FT', 'FL']};  true FL -> FT {m['FL', 'FT']}, "
            f"FL {m['FL', 'FL']}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--save-default", action="store_true")
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_cls_"))
    t0 = time.perf_counter()
    tr_dirs, te_dirs = render(root, TRAIN), render(root, TEST)
    print(f"rendered {len(tr_dirs) + len(te_dirs)} sequences in {time.perf_counter() - t0:.0f} s", flush=True)
    Xtr, ytr = dataset(tr_dirs)
    Xte, yte = dataset(te_dirs)
    print(f"train: {len(ytr)} frames ({np.sum(ytr == 'FT')} FT, {np.sum(ytr == 'FL')} FL), seeds "
          f"{[s for s, _ in TRAIN]}; test: {len(yte)} frames ({np.sum(yte == 'FT')} FT, {np.sum(yte == 'FL')} FL), "
          f"seeds {[s for s, _ in TEST]}")
    best = None
    for name, feats in (("nine (dissertation)", FEATURES_9), ("rich (nine + five)", FEATURES_RICH)):
        model = train(Xtr, ytr, feats, info={"trained_on": [f"classifier seed {s} {o}" for s, o in TRAIN]})
        p = model.predict(Xte)
        acc = float(np.mean(p == yte))
        print(f"{name}: cv accuracy {model.info['cv_accuracy']:.4f}, TEST accuracy {acc:.4f}  ({confusion(yte, p)});"
              f" C {model.info['C']:g} gamma {model.gamma:g}, {len(model.support_vectors)} support vectors",
              flush=True)
        if best is None or acc >= best[0]:
            best = (acc, name, model)
    if args.save_default:
        out = Path(__file__).resolve().parents[1] / "bodyslam" / "models" / "tunnel_svm.npz"
        best[2].save(out)
        print(f"saved the {best[1]} model as {out}")
    # throughput of the whole classify process
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "seq"
        simulate(load_scenario("classifier"), 200, d, n_frames=200, force=True)
        model_path = Path(tmp) / "m.npz"
        best[2].save(model_path)
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "bodyslam.cli", "classify", str(d), "--out", str(Path(tmp) / "c.csv"),
                            "--model", str(model_path)], capture_output=True, text=True)
        el = time.perf_counter() - t
        if r.returncode:
            print(r.stderr)
        print(f"bodyslam classify: 200 frames 320x320 in {el:.1f} s = {200 / el:.1f} frames/s (whole process, "
              f"2 cores; SRM at 96 px is the cost)")


if __name__ == "__main__":
    main()

"""Contact sheets: a grid of a sequence's frames with their index (and FT/FL label when the truth is there)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from bodyslam.errors import InputError
from bodyslam.io import frame_name, read_image, read_labels, write_image
from bodyslam.meta import read_meta


def contact_sheet(seq_dir: str | Path, out_png: str | Path, count: int = 24, cols: int = 6,
                  tile_px: int = 200) -> int:
    """Write a PNG grid of ``count`` evenly spaced frames; returns the number of frames shown."""
    seq = Path(seq_dir)
    meta = read_meta(seq)
    n = meta.n_frames
    if count < 1 or cols < 1:
        raise InputError("--count and --cols must be >= 1")
    idx = np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(int))
    lab_path = seq / "labels.csv"
    labels = read_labels(lab_path) if lab_path.exists() else {}
    rows = -(-len(idx) // cols)
    sheet = np.zeros((rows * tile_px, cols * tile_px, 3), np.uint8)
    frames_dir = seq / meta.frames_dir
    for i, k in enumerate(idx):
        img = cv2.resize(read_image(frames_dir / frame_name(int(k))), (tile_px, tile_px),
                         interpolation=cv2.INTER_AREA)
        text = f"{k}" + (f" {labels[k]}" if k in labels else "")
        cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        r, c = divmod(i, cols)
        sheet[r * tile_px : (r + 1) * tile_px, c * tile_px : (c + 1) * tile_px] = img
    write_image(out_png, sheet)
    return len(idx)

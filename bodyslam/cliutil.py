"""Shared CLI plumbing: one-line errors, logging set-up and a progress bar on stderr (CLIs only)."""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import Callable

from bodyslam.errors import BodySlamError
from bodyslam.parallel import return_large_frees


class Progress:
    """A text progress bar on stderr: redrawn in place on a terminal, a line every 10% otherwise. The rate and the
    time left count from the first call: what was done before it (chunks reused from an earlier run, a worker
    pool's start) is shown in the count, not in the rate."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._last_decile = -1
        self._first: tuple[float, int] | None = None  # (time, done) at the first call

    def __call__(self, done: int, total: int) -> None:
        frac = done / max(total, 1)
        now = time.monotonic()
        if self._first is None:
            self._first = (now, done)
        el = now - self._first[0]
        rate = (done - self._first[1]) / el if el > 0 else None  # None: nothing to rate yet
        if self.tty:
            bar = "#" * int(frac * 30)
            eta = (total - done) / rate if rate else 0.0
            tail = "" if rate is None else f" {rate:5.1f}/s eta {eta:4.0f}s"
            self.stream.write(f"\r{self.label} [{bar:<30}] {done}/{total}{tail}")
            if done >= total:
                self.stream.write("\n")
            self.stream.flush()
        else:
            dec = int(frac * 10)
            if dec != self._last_decile or done >= total:
                self._last_decile = dec
                tail = "" if rate is None else f" ({rate:.1f}/s)"
                self.stream.write(f"{self.label}: {done}/{total}{tail}\n")
                self.stream.flush()


def jobs_count(text: str) -> int:
    """``--jobs``' argparse type: a whole number of worker processes, at least 1 (0 or a negative count is refused
    by name instead of read as "one per core")."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a whole number of worker processes, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"give at least 1 worker process, got {n} (leave --jobs out for one per core)")
    return n


def run_cli(main: Callable[[list[str] | None], int], argv: list[str] | None, verbose: bool = False) -> int:
    """Run a CLI body: a :class:`BodySlamError` becomes one line on stderr and exit code 1. Large freed arrays go
    back to the system at once (:func:`bodyslam.parallel.return_large_frees`). FFmpeg's own log lines (OpenCV's video
    reader prints e.g. "moov atom not found" above the command's one-line error) are silenced unless ``-v`` or the
    user sets ``OPENCV_FFMPEG_LOGLEVEL``: a video that cannot be opened or a frame that cannot be decoded is named
    by the command itself (pool workers inherit the setting)."""
    return_large_frees()
    if not verbose:
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; OpenCV reads it when it opens a video
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return main(argv)
    except BodySlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: not an error of ours
        sys.stderr.close()
        return 0

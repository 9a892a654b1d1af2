"""Image decoding in parallel worker threads (cv2 releases the GIL while decoding)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from ..data.validate import decode_bytes

cv2.setNumThreads(1)  # our own pool parallelises; cv2's inner threads would oversubscribe


class ImageReadError(OSError, ValueError):
    """An image file is missing, truncated or cannot be decoded (bad input: the CLI reports
    it in one line)."""


def _decode(path: str | os.PathLike[str], flags: int, what: str) -> np.ndarray:
    """Read and decode one file; truncated PNG/JPEG files are refused, not filled in."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ImageReadError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    img, err = decode_bytes(data, flags)
    if err:
        raise ImageReadError(f"{what} {path}: {err}")
    return img


def read_rgb(path: str | os.PathLike[str]) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    return cv2.cvtColor(_decode(path, cv2.IMREAD_COLOR, "image"), cv2.COLOR_BGR2RGB)


def read_instance_map(path: str | os.PathLike[str]) -> np.ndarray:
    """(H, W) uint16 instance ids from a 16-bit (or 8-bit) single-channel PNG."""
    img = _decode(path, cv2.IMREAD_UNCHANGED, "segmentation")
    if img.ndim != 2:
        raise ImageReadError(f"segmentation {path} has shape {img.shape}; expected one channel of instance ids")
    return img.astype(np.uint16, copy=False)


def _stack(arrays: list[np.ndarray], paths: Sequence[Path], what: str) -> np.ndarray:
    shapes = {a.shape for a in arrays}
    if len(shapes) > 1:
        first = arrays[0].shape
        odd = next(p for p, a in zip(paths, arrays, strict=True) if a.shape != first)
        raise ImageReadError(f"{what} {odd} has shape {[a for a in shapes if a != first][0]}; expected {first}")
    return np.stack(arrays)


class Decoder:
    """A pool of decoding threads. ``images(paths)`` -> (N, H, W, 3) uint8 RGB;
    ``instance_maps(paths)`` -> (N, H, W) uint16. ``submit_*`` return futures so that
    decoding overlaps with the model forward."""

    def __init__(self, workers: int = 2):
        self.workers = max(1, int(workers))
        self.pool = ThreadPoolExecutor(self.workers, thread_name_prefix="uevavd-decode")

    def map_slices(self, fn, n: int) -> list:
        """``[fn(slice) ...]`` over ``n`` items cut into one contiguous slice per worker
        thread, in order (one slice, in this thread, when ``n`` is small)."""
        if n < 2 * self.workers:
            return [fn(slice(0, n))]
        chunk = -(-n // self.workers)
        futures = [self.pool.submit(fn, slice(i, min(i + chunk, n))) for i in range(0, n, chunk)]
        return [f.result() for f in futures]

    def _map(self, fn, paths: Sequence[Path]) -> list[np.ndarray]:
        return [a for part in self.map_slices(lambda s: [fn(p) for p in paths[s]], len(paths)) for a in part]

    def images(self, paths: Sequence[Path]) -> np.ndarray:
        return _stack(self._map(read_rgb, paths), paths, "image")

    def instance_maps(self, paths: Sequence[Path]) -> np.ndarray:
        return _stack(self._map(read_instance_map, paths), paths, "segmentation")

    def submit(self, fn, *args):
        """Run ``fn(*args)`` in a background thread (which may itself use this pool)."""
        return self._bg.submit(fn, *args)

    @property
    def _bg(self) -> ThreadPoolExecutor:
        if not hasattr(self, "_bg_pool"):
            self._bg_pool = ThreadPoolExecutor(1, thread_name_prefix="uevavd-prefetch")
        return self._bg_pool

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        if hasattr(self, "_bg_pool"):
            self._bg_pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Decoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""What ``prepare`` keeps on disk while it works: one shard per scene (written atomically,
so a killed build resumes), and the caches of classifier probabilities and encoder features
per scene, shared between tables that differ only in the other component."""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write, folder_lock, remove_temporaries
from ..data.grid import N_VIEWS
from ..hashing import json_digest

log = logging.getLogger("uevavd.perception.prepare")
SHARD_ARRAYS = ("features", "probs", "boxes", "visible")


def write_shard(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    atomic_write(path, lambda fh: np.savez(fh, **arrays), fsync=True)


def read_shard(path: Path, feature_dim: int, n_classes: int) -> dict[str, np.ndarray] | None:
    """A complete shard's arrays, or None when it is absent or unusable (then redone)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in SHARD_ARRAYS}
    except Exception:  # noqa: BLE001 - anything unreadable is redone
        log.warning("prepare: shard %s unreadable; recomputing it", path)
        return None
    expected = {"features": (N_VIEWS, feature_dim), "probs": (N_VIEWS, n_classes),
                "boxes": (N_VIEWS, 4), "visible": (N_VIEWS,)}
    if any(arrays[k].shape != s for k, s in expected.items()):
        return None
    return arrays


def features_folder(out_dir: Path, parts: Mapping[str, Any]) -> Path:
    """Where encoder features of scenes are cached: keyed by everything that makes them
    (segmenter, decomposition, gray seed, encoder; not the classifier), so the tables of
    several recognizers over the same views encode each view once."""
    keep = {k: parts[k] for k in ("schema_version", "segmenter", "decompose", "gray_seed", "encoder")}
    return out_dir / "features" / json_digest(keep, 16)


def cached_array(path: Path | None, shape: tuple[int, int], dtype) -> np.ndarray | None:
    if path is None or not path.is_file():
        return None
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception:  # noqa: BLE001 - unreadable: recomputed
        return None
    ok = arr.shape == shape and arr.dtype == dtype and bool(np.isfinite(arr).all())
    return arr if ok else None


def cached_probs(path: Path | None, n_classes: int) -> np.ndarray | None:
    return cached_array(path, (N_VIEWS, n_classes), np.float32)


def save_array(path: Path, array: np.ndarray) -> None:
    """``np.save`` written atomically (temp file, then rename)."""
    atomic_write(path, lambda fh: np.save(fh, array))


@contextmanager
def build_lock(out_dir: Path, key: str, usable: Any) -> Iterator[bool]:
    """One build per table key at a time (``atomic.folder_lock`` on the table's folder): a
    second prepare of the same table (another ablation on the same cache) waits, then finds it
    built. Yields True holding the lock, after removing what a killed build of the key left (its
    temporaries; a stale ``KEY.partial`` beside a built table). Where the lock file cannot be
    made (a read-only cache) and ``usable(table folder)`` says the table is built, yields False:
    it is served without the lock; otherwise the OS error stands."""
    with ExitStack() as held:
        try:
            held.enter_context(folder_lock(out_dir / key, busy=RuntimeError, wait=_say_waiting))
        except OSError:
            if not usable(out_dir / key):
                raise
            yield False
            return
        for stale in remove_temporaries(out_dir, key):
            log.info("prepare: removed %s, left by a killed build", stale)
        if (out_dir / f"{key}.partial").is_dir() and usable(out_dir / key):
            shutil.rmtree(out_dir / f"{key}.partial", ignore_errors=True)  # a build killed after the save
        yield True


def _say_waiting(lock_file: str) -> None:
    log.info("prepare: another process builds this table (%s); waiting for it", lock_file)

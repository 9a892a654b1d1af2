"""What ``prepare`` keeps on disk while it works: one shard per scene (written atomically,
so a killed build resumes), and the caches of classifier probabilities and encoder features
per scene, shared between tables that differ only in the other component. Each is an
``.npz`` with the digest of its arrays: a damaged one is computed again, never baked into a
table."""

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
from ..hashing import SEAL, arrays_sha256, json_digest

log = logging.getLogger("uevavd.perception.prepare")
SHARD_ARRAYS = ("features", "probs", "boxes", "visible")


#: The seal of this version's caches: the arrays' digest bound to the file's place (its folder,
#: which names the cache's fingerprint or table, and its name, which names the scene).
SEAL_FORMAT = "v2"


def _place_digest(path: Path, arrays: Mapping[str, np.ndarray]) -> str:
    digest = arrays_sha256(*(arrays[k] for k in sorted(arrays)))
    return f"{SEAL_FORMAT}:{json_digest({'arrays': digest, 'place': f'{path.parent.name}/{path.name}'})}"


def save_sealed_arrays(path: Path, arrays: Mapping[str, np.ndarray], *, fsync: bool = False) -> None:
    """Arrays as one ``.npz``, written atomically, with a digest of their dtypes, shapes and
    bytes and of the file's place (under :data:`~uevavd.hashing.SEAL`), so a reader tells a
    damaged cache, or another scene's or fingerprint's copied in, from a good one."""
    digest = _place_digest(path, arrays)
    atomic_write(path, lambda fh: np.savez(fh, **arrays, **{SEAL: np.array(digest)}), fsync=fsync)


def load_sealed_arrays(path: Path | None, expected: Mapping[str, tuple[tuple[int, ...], Any]]
                       ) -> dict[str, np.ndarray] | None:
    """The arrays of a :func:`save_sealed_arrays` file, or None where it is absent, unreadable,
    of other shapes or dtypes (``expected``: name -> (shape, dtype)), written by an earlier
    version, or damaged, edited or moved since it was written (said in a warning naming it): a
    cache then recomputes."""
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in expected}
            digest = str(z[SEAL])
    except Exception:  # noqa: BLE001 - anything unreadable (or written before caches were sealed) is redone
        log.warning("prepare: %s is unreadable; computing it again", path)
        return None
    if any(arrays[k].shape != shape or arrays[k].dtype != dtype for k, (shape, dtype) in expected.items()):
        return None
    if not digest.startswith(f"{SEAL_FORMAT}:"):  # an earlier version's seal, unbound to its place
        log.info("prepare: %s was written by an earlier version; computing it again", path)
        return None
    if digest != _place_digest(path, arrays):
        log.warning("prepare: %s was damaged, edited or copied from another scene or cache since it was written; "
                    "computing it again", path)
        return None
    return arrays


def write_shard(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    save_sealed_arrays(path, arrays, fsync=True)


def read_shard(path: Path, feature_dim: int, n_classes: int) -> dict[str, np.ndarray] | None:
    """A complete shard's arrays, or None when it is absent or unusable (then redone)."""
    return load_sealed_arrays(path, {"features": ((N_VIEWS, feature_dim), np.float16),
                                     "probs": ((N_VIEWS, n_classes), np.float32),
                                     "boxes": ((N_VIEWS, 4), np.float32), "visible": ((N_VIEWS,), np.float32)})


def features_folder(out_dir: Path, parts: Mapping[str, Any]) -> Path:
    """Where encoder features of scenes are cached: keyed by everything that makes them
    (segmenter, decomposition, gray seed, encoder; not the classifier), so the tables of
    several recognizers over the same views encode each view once."""
    keep = {k: parts[k] for k in ("schema_version", "segmenter", "decompose", "gray_seed", "encoder")}
    return out_dir / "features" / json_digest(keep, 16)


def cached_array(path: Path | None, shape: tuple[int, int], dtype) -> np.ndarray | None:
    """A per-scene cache (:func:`save_array`) of that shape and dtype, or None (then computed)."""
    arrays = load_sealed_arrays(path, {"array": (shape, np.dtype(dtype))})
    return arrays["array"] if arrays is not None and np.isfinite(arrays["array"]).all() else None


def cached_probs(path: Path | None, n_classes: int) -> np.ndarray | None:
    return cached_array(path, (N_VIEWS, n_classes), np.float32)


def save_array(path: Path, array: np.ndarray) -> None:
    """One array as a per-scene cache: :func:`save_sealed_arrays`."""
    save_sealed_arrays(path, {"array": array})


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

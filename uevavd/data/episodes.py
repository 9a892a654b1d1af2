"""Episodes of a Minari HDF5 file read as a few concatenated arrays, fast.

Minari's own reader builds each episode whole (its infos and every space decoded, ~8 ms an
episode on 2 cores); a learner of flat arrays needs five of them. This module reads those
through h5py's low-level calls, spread over processes for large datasets, and imports
nothing heavier than numpy and h5py, so that a spawned worker starts in a fraction of a second.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime import WorkerPool, usable_cores

#: Episodes a worker process reads at least: starting one costs about as much as reading these.
EPISODES_PER_WORKER = 1000
STEP_KEYS = ("actions", "rewards", "terminations", "truncations")


def read_hdf5_episodes(path: str | os.PathLike[str], indices: Any, observation_keys: tuple[str, ...], *,
                       workers: int | None = None) -> dict[str, np.ndarray]:
    """The episodes ``indices`` of Minari's ``main_data.hdf5`` at ``path``, one after another:
    each observation entry in ``observation_keys`` (the observations each action was taken
    on: an episode's last is dropped) and the :data:`STEP_KEYS`, concatenated over episodes.
    ``workers``: processes (default: one per :data:`EPISODES_PER_WORKER` episodes, at most the
    cores and 4); the result is the same for any number."""
    indices = np.asarray(indices, np.int64).reshape(-1)
    if workers is None:
        workers = min(usable_cores(), 4, len(indices) // EPISODES_PER_WORKER)
    if workers <= 1:
        return _read(Path(path), indices, observation_keys)
    with WorkerPool(workers) as pool:
        futures = [pool.submit(_read, Path(path), part, observation_keys)
                   for part in np.array_split(indices, 2 * workers)]
        parts = [f.result() for f in futures]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _read(path: Path, indices: np.ndarray, observation_keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    import h5py

    def read(parent: Any, name: str) -> np.ndarray:
        data = h5py.h5d.open(parent, name.encode())
        out = np.empty(data.shape, data.dtype)
        data.read(h5py.h5s.ALL, h5py.h5s.ALL, out)
        return out

    out: dict[str, list[np.ndarray]] = {k: [] for k in (*observation_keys, *STEP_KEYS)}
    with h5py.File(path, "r") as file:
        for i in indices:
            group = h5py.h5g.open(file.id, f"episode_{int(i)}".encode())
            steps = {k: read(group, k) for k in STEP_KEYS}
            n = len(steps["rewards"])
            obs = h5py.h5g.open(group, b"observations")
            for k in observation_keys:
                out[k].append(read(obs, k)[:n])
            for k, v in steps.items():
                out[k].append(v)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}

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
#: The action types (move x 6, stop) an action's first index names (uevavd.data.grid.N_TYPES).
N_ACTION_TYPES = 7


class EpisodeError(ValueError):
    """An episode a flat view cannot use; the message names the file (or dataset), the episode
    and the key, and what was expected."""


def check_workers(workers: Any) -> int | None:
    """``workers`` as given, when it is None or an integer >= 1; else a ValueError naming it."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int | np.integer)
                                or workers < 1):
        raise ValueError(f"workers={workers!r}: expected an integer >= 1 (processes reading the file), or None for "
                         "one per 1,000 episodes")
    return None if workers is None else int(workers)


def check_episode(arrays: dict[str, np.ndarray], where: str, spec: dict[str, tuple[Any, tuple[int, ...]]] | None
                  = None) -> None:
    """Refuse an episode whose arrays a flat view would misread: ``arrays`` holds its observation
    entries (n + 1 rows: Minari keeps the last observation) and the :data:`STEP_KEYS` (n rows);
    actions integral (type, range) pairs within the action space the mask's last axis gives;
    rewards finite; observation entries of ``spec``'s dtype and per-row shape where given.
    ``where`` names the file or dataset and the episode."""
    rewards = np.asarray(arrays["rewards"])
    if rewards.ndim != 1 or rewards.dtype.kind not in "fiu":
        raise EpisodeError(f"{where}, key rewards: {rewards.dtype} of shape {rewards.shape}; expected (n,) numbers")
    n = len(rewards)
    if not np.isfinite(rewards).all():
        raise EpisodeError(f"{where}, key rewards: holds NaN or inf at step {int(np.flatnonzero(~np.isfinite(rewards))[0])}"
                           "; expected finite rewards")
    for key in ("actions", "terminations", "truncations"):
        if len(arrays[key]) != n:
            raise EpisodeError(f"{where}, key {key}: {len(arrays[key])} rows where rewards has {n}; expected one per "
                               "step (a truncated or edited episode?)")
    for key, value in arrays.items():
        if key not in STEP_KEYS and len(value) != n + 1:
            raise EpisodeError(f"{where}, key observations/{key}: {len(value)} rows for {n} steps; expected {n + 1} "
                               "(each step's observation and the last one)")
        if key not in STEP_KEYS and spec and key in spec:
            dtype, shape = spec[key]
            if np.dtype(value.dtype) != np.dtype(dtype) or tuple(value.shape[1:]) != tuple(shape):
                raise EpisodeError(f"{where}, key observations/{key}: {value.dtype} {tuple(value.shape[1:])} per row; "
                                   f"the dataset's observation space records {np.dtype(dtype)} {tuple(shape)}")
    actions = np.asarray(arrays["actions"]).reshape(n, -1) if n else np.zeros((0, 2), np.int64)
    if actions.shape[1] != 2 or actions.dtype.kind not in "fiu" or (
            actions.dtype.kind == "f" and not np.array_equal(actions, np.round(actions))):
        raise EpisodeError(f"{where}, key actions: {actions.dtype} {actions.shape[1:]} per step; expected integral "
                           "(type, range) pairs of MultiDiscrete([7, A])")
    ranges = np.asarray(arrays["action_mask"]).shape[-1] if "action_mask" in arrays else None
    bad = (actions[:, 0] < 0) | (actions[:, 0] >= N_ACTION_TYPES) | (actions[:, 1] < 0)
    if ranges is not None:
        bad |= actions[:, 1] >= ranges
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise EpisodeError(f"{where}, key actions: step {i} is {actions[i].tolist()}; expected a type in 0..6 and a "
                           f"range in 0..{(ranges or 0) - 1 if ranges else 'A-1'}")


def read_hdf5_episodes(path: str | os.PathLike[str], indices: Any, observation_keys: tuple[str, ...], *,
                       workers: int | None = None,
                       spec: dict[str, tuple[Any, tuple[int, ...]]] | None = None) -> dict[str, np.ndarray]:
    """The episodes ``indices`` of Minari's ``main_data.hdf5`` at ``path``, one after another:
    each observation entry in ``observation_keys`` (the observations each action was taken
    on: an episode's last is dropped) and the :data:`STEP_KEYS`, concatenated over episodes,
    each episode checked by :func:`check_episode` (against ``spec``: key -> (dtype, per-row
    shape) of the dataset's observation space). ``workers``: processes (default: one per
    :data:`EPISODES_PER_WORKER` episodes, at most the cores and 4); the result is the same for
    any number. A damaged, foreign or missing episode is an :class:`EpisodeError` naming the
    file, the episode and the key."""
    workers = check_workers(workers)
    indices = np.asarray(indices, np.int64).reshape(-1)
    if workers is None:
        workers = min(usable_cores(), 4, len(indices) // EPISODES_PER_WORKER)
    if workers <= 1:
        return _read(Path(path), indices, observation_keys, spec)
    with WorkerPool(workers) as pool:
        futures = [pool.submit(_read, Path(path), part, observation_keys, spec)
                   for part in np.array_split(indices, 2 * workers)]
        parts = [f.result() for f in futures]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _read(path: Path, indices: np.ndarray, observation_keys: tuple[str, ...],
          spec: dict[str, tuple[Any, tuple[int, ...]]] | None = None) -> dict[str, np.ndarray]:
    import h5py

    def read(parent: Any, name: str, where: str) -> np.ndarray:
        try:
            data = h5py.h5d.open(parent, name.encode())
            out = np.empty(data.shape, data.dtype)
            data.read(h5py.h5s.ALL, h5py.h5s.ALL, out)
        except (KeyError, OSError, ValueError, TypeError) as exc:
            raise EpisodeError(f"{where}, key {name}: cannot be read ({exc}); expected the array `uevavd "
                               "export-minari` writes: export the dataset again") from None
        return out

    out: dict[str, list[np.ndarray]] = {k: [] for k in (*observation_keys, *STEP_KEYS)}
    try:
        file = h5py.File(path, "r")
    except OSError as exc:
        raise EpisodeError(f"{path}: cannot be opened as HDF5 ({exc}); expected the main_data.hdf5 Minari "
                           "writes: export the dataset again") from None
    with file:
        for i in indices:
            where = f"{path}, episode_{int(i)}"
            try:
                group = h5py.h5g.open(file.id, f"episode_{int(i)}".encode())
                obs = h5py.h5g.open(group, b"observations")
            except (KeyError, OSError, ValueError) as exc:
                raise EpisodeError(f"{where}: no such episode group with observations ({exc}); the file holds "
                                   "other episodes than its dataset lists: export the dataset again") from None
            arrays = {k: read(group, k, where) for k in STEP_KEYS}
            arrays.update({k: read(obs, k, f"{where}, observations") for k in observation_keys})
            check_episode(arrays, where, spec)
            n = len(arrays["rewards"])
            for k in observation_keys:
                out[k].append(arrays[k][:n])
            for k in STEP_KEYS:
                out[k].append(arrays[k])
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}

"""The flat view of the env's data for offline-RL libraries (d3rlpy, CORL-style scripts).

Offline-RL libraries take a ``Box`` observation and a ``Discrete`` action; the env's
observation is a ``Dict`` and its action ``MultiDiscrete([7, A])``. One call turns an
exported dataset (:mod:`uevavd.policy.minari_export`) into flat arrays, and one class turns a
flat policy back into one the evaluation runs::

    flat = flat_dataset(minari.load_dataset("uevavd/quick-train-oracle-v0"))
    data = d3rlpy.dataset.MDPDataset(flat.observations, flat.actions[:, None], flat.rewards, flat.terminals,
                                     timeouts=flat.timeouts, action_space=d3rlpy.constants.ActionSpace.DISCRETE,
                                     action_size=flat.n_actions)
    bc = d3rlpy.algos.DiscreteBCConfig().create(device="cpu:0")
    bc.fit(data, n_steps=2000)
    evaluate_policy(table, "hard", flat.policy(bc.predict))  # FlatPolicy on the dataset's layout

The flat observation is ``[features (D), box (4), t (1), action_mask (7 * A)]`` as float32
(:func:`flat_observation`), with the pose (3, metres) after the box where the data has it
(``EnvConfig.pose``): the mask rides in the observation, so a learner sees which moves
would be clamped, and :attr:`FlatTransitions.masks` holds it apart (bool) for a learner that
masks its own outputs; :class:`FlatPolicy` keeps to it when it acts (by default). The flat action is ``type * A + range``, as the env's ``actions="flat"``
form and :class:`~uevavd.env.wrappers.DiscreteActions`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from ..data.episodes import STEP_KEYS, EpisodeError, check_episode, check_workers, read_hdf5_episodes
from ..data.grid import N_TYPES
from .aod_env import integral_actions
from .gate import fit_to_mask
from .spaces import FLAT_PARTS, OPTIONAL_PARTS, flatten_observation, parts_mismatch, present_parts


def flat_observation(obs: dict[str, Any]) -> np.ndarray:
    """The flat observation of one observation or a batch of them (the env's keys, or the
    batched interface's, whose mask is ``mask``; numpy or torch): ``[features, box, (pose,)
    t, action_mask]`` as float32, one row each; the pose where the observation has one."""
    return flatten_observation({k: v.cpu().numpy() if isinstance(v, torch.Tensor) else v for k, v in obs.items()})


@dataclass(frozen=True)
class FlatTransitions:
    """A dataset's steps as flat arrays, one row per decision: ``observations`` (N, D + 5 + 7A,
    and + 3 with the pose) float32, ``actions`` (N,) int64 flat indices, ``rewards`` (N,) float32, ``terminals`` and
    ``timeouts`` (N,) bool (the env's episodes end by termination, never truncation), ``masks``
    (N, 7A) bool (the allowed moves; stop is always allowed)."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray
    masks: np.ndarray
    max_range: int
    #: the observation parts the rows hold (:data:`~uevavd.env.spaces.FLAT_PARTS` with or without the pose)
    parts: tuple[str, ...] = tuple(k for k in FLAT_PARTS if k not in OPTIONAL_PARTS)

    @property
    def n_actions(self) -> int:
        return N_TYPES * self.max_range

    def policy(self, act: Callable[[np.ndarray], Any], *, masked: bool = True) -> FlatPolicy:
        """``act`` (a learner's ``predict``, or a network's scores) as a :class:`FlatPolicy` on
        these rows' layout: their action space, and their width, checked against the env it is
        evaluated on (a policy learnt with the pose refused on an env without it, by name)."""
        return FlatPolicy(act, max_range=self.max_range, masked=masked, width=self.observations.shape[1])


def flat_dataset(*datasets: Iterable[Any], workers: int | None = None) -> FlatTransitions:
    """Flatten Minari datasets (or iterables of their ``EpisodeData``) written by ``uevavd
    export-minari``, one after another: each episode's decisions, the observation each was
    taken on (not the last one, which no action follows). Datasets of different action spaces
    (``max_range``) or observation parts are refused. A Minari dataset stored in HDF5 (the
    exporter's format) is read straight from its file, only the arrays the flat view needs,
    by ``workers`` processes (default: one per 1,000 episodes, at most the cores and 4). Every
    episode is checked first (:func:`uevavd.data.episodes.check_episode`): a damaged or foreign
    one is an error naming the file, the episode and the key."""
    check_workers(workers)
    chunks = [(name, c) for d in datasets for name in [_name(d)] if (c := _arrays(d, name, workers)) is not None]
    if not chunks:
        raise ValueError("the dataset holds no episodes")
    first, ref = chunks[0]
    max_range = ref["action_mask"].shape[-1]
    for name, c in chunks[1:]:
        if c["action_mask"].shape[-1] != max_range:
            raise ValueError(f"dataset {name} has {c['action_mask'].shape[-1]} ranges where dataset {first} has "
                             f"{max_range}: flatten datasets of one action space together")
        if set(c) != set(ref):
            raise ValueError(f"dataset {name} holds the observation parts {sorted(set(c) & set(FLAT_PARTS))} where "
                             f"dataset {first} holds {sorted(set(ref) & set(FLAT_PARTS))}: flatten datasets of one "
                             "env config together")
    data = {k: np.concatenate([c[k] for _, c in chunks]) for k in ref}
    observations = flat_observation({k: data[k] for k in FLAT_PARTS if k in data})
    a = data["actions"].reshape(-1, 2).astype(np.int64)
    return FlatTransitions(observations, a[:, 0] * max_range + a[:, 1], data["rewards"].astype(np.float32),
                           data["terminations"].astype(bool), data["truncations"].astype(bool),
                           observations[:, -N_TYPES * max_range:] > 0, int(max_range),
                           tuple(k for k in FLAT_PARTS if k in data))


def _arrays(dataset: Any, name: str, workers: int | None) -> dict[str, np.ndarray] | None:
    """One dataset's observation parts (without each episode's last observation) and step
    arrays, concatenated over its episodes; None where it holds none. From its HDF5 file
    where it is a Minari dataset of a Dict observation stored so (:mod:`uevavd.data.episodes`),
    else episode by episode (``iterate_episodes``, or the iterable itself)."""
    storage = getattr(dataset, "storage", None)
    indices = getattr(dataset, "episode_indices", None)
    space = getattr(storage, "observation_space", None)
    keys = tuple(space.spaces) if isinstance(space, spaces.Dict) else ()
    path = Path(storage.data_path) / "main_data.hdf5" if storage is not None else None
    if path is not None and path.is_file() and indices is not None and storage.metadata.get("data_format") == "hdf5":
        _check_parts(keys, name)
        if len(indices) == 0:
            return None
        spec = {k: (s.dtype, s.shape) for k, s in space.spaces.items() if k in FLAT_PARTS}
        return read_hdf5_episodes(path, indices, tuple(k for k in FLAT_PARTS if k in keys), workers=workers,
                                  spec=spec)
    out: dict[str, list[np.ndarray]] = {}
    for i, ep in enumerate(getattr(dataset, "iterate_episodes", lambda: dataset)()):
        if not all(hasattr(ep, k) for k in ("observations", "rewards")):
            raise EpisodeError(f"dataset {name}, episode {i}: a {type(ep).__name__}, not an episode; expected Minari's "
                               f"EpisodeData (or an object with observations, {', '.join(STEP_KEYS)})")
        n = len(ep.rewards)
        _check_parts(tuple(ep.observations) if isinstance(ep.observations, dict) else type(ep.observations).__name__,
                     name)
        missing = [k for k in STEP_KEYS if not hasattr(ep, k)]
        if missing:
            raise EpisodeError(f"dataset {name}, episode {i}: no {', '.join(missing)}; expected Minari's EpisodeData")
        check_episode({**{k: np.asarray(ep.observations[k]) for k in FLAT_PARTS if k in ep.observations},
                       **{k: np.asarray(getattr(ep, k)) for k in STEP_KEYS}}, f"dataset {name}, episode {i}")
        for key in FLAT_PARTS:
            if key in ep.observations:
                out.setdefault(key, []).append(np.asarray(ep.observations[key])[:n])
        for key in STEP_KEYS:
            out.setdefault(key, []).append(np.asarray(getattr(ep, key)).reshape(n, -1) if key == "actions"
                                           else np.asarray(getattr(ep, key)))
    if not out:
        return None
    return {k: np.concatenate(v) for k, v in out.items()}


def _check_parts(keys: Any, name: str) -> None:
    need = set(FLAT_PARTS) - {"pose"}
    if isinstance(keys, str) or not need <= set(keys):
        raise ValueError(f"dataset {name} is not one `uevavd export-minari` wrote: its observations hold "
                         f"{keys if isinstance(keys, str) else sorted(keys)}, not the env's {sorted(need)}")


def _name(dataset: Any) -> str:
    return getattr(getattr(dataset, "spec", None), "dataset_id", None) or type(dataset).__name__


class FlatPolicy:
    """A policy over flat observations as a policy the evaluation and the exporter run
    (:func:`~uevavd.env.evaluate.evaluate_policy`). ``act(flat_obs (n, F))`` returns flat action
    indices (n,) (a d3rlpy algorithm's ``predict``) or scores (n, 7 * A) (logits, Q-values).

    With ``masked`` (the default) it keeps to the observation's action mask, as the env's own
    agents do: from scores, the best allowed action; an index of a move the mask forbids (one
    the grid's edge would clamp) becomes the longest allowed range of its type, or stop where
    none is allowed (the scripted box gate's edge rule). ``masked=False`` takes the indices as
    they are (clamped moves are legal, and cost their requested range).

    ``width``, the flat observation's length the policy was built on (an int, or the
    observation space: ``envs.single_observation_space``, Tianshou's ``["obs"]``), refuses an
    env of another layout by name before the policy acts (a network trained with the pose on
    an env without it: "evaluate with EnvConfig(pose=True)"); :meth:`FlatTransitions.policy`
    sets it."""

    needs_features = True

    def __init__(self, act: Callable[[np.ndarray], Any], *, max_range: int, masked: bool = True,
                 width: int | spaces.Space | None = None) -> None:
        if isinstance(max_range, bool) or not isinstance(max_range, int | np.integer) or max_range < 1:
            raise ValueError(f"FlatPolicy(max_range={max_range!r}): expected the dataset's number of ranges, an "
                             "integer >= 1 (flat_dataset(...).max_range)")
        self._act = act
        self.max_range = int(max_range)
        self.masked = bool(masked)
        if isinstance(width, spaces.Space):
            width = int(np.prod(width.shape))
        if width is not None and (isinstance(width, bool) or not isinstance(width, int | np.integer) or width < 1):
            raise ValueError(f"FlatPolicy(width={width!r}): expected the flat observation's length, an integer >= 1 "
                             "(or its observation space)")
        self.width = None if width is None else int(width)

    def reset(self, n: int) -> None:
        """Nothing to clear: the flat policy has no memory."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Flatten the observations, call the wrapped ``act``, and return its (masked) actions
        as (type, range) indices."""
        mask = obs["mask"] if "mask" in obs else obs["action_mask"]
        if mask.shape[-1] != self.max_range:  # every index would be split by the wrong A
            raise ValueError(f"FlatPolicy(max_range={self.max_range}) on an env whose actions have "
                             f"{mask.shape[-1]} ranges: use the max_range of the dataset it learned from, on a table "
                             "and env config of the same action space")
        n, k = len(obs["t"]), N_TYPES * self.max_range
        allowed = torch.as_tensor(mask).cpu().numpy().astype(bool).reshape(n, N_TYPES, self.max_range)
        flat_obs = flat_observation(obs)
        if self.width is not None:
            problem = parts_mismatch("the flat policy", self.width, flat_obs.shape[-1], present_parts(obs))
            if problem:
                raise ValueError(problem)
        raw = self._act(flat_obs)
        if np.ndim(raw) == 2 and np.shape(raw) == (n, k):  # scores: the best (allowed) action
            scores = np.array(raw, dtype=np.float64)
            if self.masked:
                scores[~allowed.reshape(n, k)] = -np.inf
            flat = scores.argmax(1)
        else:
            flat = integral_actions(raw)  # the env's rule: integers, or floats equal to them
            if flat is None or flat.reshape(-1).shape != (n,):
                raise ValueError(f"the flat policy returned {np.asarray(raw).reshape(-1)[:8].tolist()} (shape "
                                 f"{np.shape(raw)}): expected ({n},) integer indices of Discrete({k}), or ({n}, {k}) "
                                 "scores")
            flat = flat.reshape(-1)
            if bool(((flat < 0) | (flat >= k)).any()):
                raise ValueError(f"the flat policy returned {flat[:8].tolist()} (shape {flat.shape}): expected "
                                 f"({n},) indices of Discrete({k})")
        a_type, a_range = (torch.as_tensor(a) for a in np.divmod(flat, self.max_range))
        if self.masked:
            a_type, a_range = fit_to_mask(torch.as_tensor(allowed), a_type, a_range)
        device = obs["t"].device
        return a_type.to(device), a_range.to(device)

"""The batched environment behind the standard vector interfaces.

:class:`AODVectorEnv` is :class:`~uevavd.env.batched.BatchedAODEnv` as a Gymnasium
``VectorEnv`` (numpy in and out, same-step autoreset), what
``gymnasium.make_vec("uevavd/AOD-v0", num_envs=N, vectorization_mode="vector_entry_point",
table=..., split=...)`` returns. :class:`SB3VecEnv` adapts it to Stable-Baselines3's
``VecEnv`` (SB3 has no adapter for Gymnasium vector envs). With ``actions="flat"`` the
action is one index ``type * A + range`` of ``Discrete(7 * A)`` and the observation's
``action_mask`` is flattened the same way, as :class:`~uevavd.env.wrappers.DiscreteActions`
does for the single env (what SB3's DQN and sb3-contrib's MaskablePPO need).

Observations are those of :class:`~uevavd.env.aod_env.AODEnv` batched: ``features`` (N, D)
float32, ``box`` (N, 4) float32, ``action_mask`` (N, 7, A) int8 (or (N, 7 * A)), ``t`` (N,)
int64. An episode always ends by termination (stop or T_max), never truncation; where it
ends, the returned observation is the next episode's first and ``infos["final_obs"]`` holds
the last one (Gymnasium's same-step convention), beside the ``final_*`` fields of
``BatchedAODEnv`` (``final_return``, ``final_recognized``, ...), each with its ``_key`` mask.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from ..data.grid import N_TYPES, STOP
from .aod_env import AODEnv
from .batched import BatchedAODEnv
from .config import EnvConfig, make_config

ACTION_FORMS = ("multi", "flat")


class AODVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` AOD episodes in lockstep (see the module doc)."""

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, table: Any, split: str = "train", config: EnvConfig | dict[str, Any] | None = None, *,
                 num_envs: int = 1, actions: str = "multi", device: str | torch.device = "cpu",
                 contexts: Any = None, **overrides: Any) -> None:
        if actions not in ACTION_FORMS:
            raise ValueError(f"actions={actions!r}: expected one of {ACTION_FORMS}")
        cfg = make_config(config, **overrides)
        self._batched = BatchedAODEnv(table, split, num_envs, cfg, device=device, contexts=contexts)
        single = AODEnv(self._batched.table, split, cfg, contexts=contexts)  # the spaces, one definition
        self.num_envs = num_envs
        self.actions = actions
        self._a = cfg.max_range
        obs_space = single.observation_space
        if actions == "flat":
            obs_space = spaces.Dict({**obs_space.spaces,
                                     "action_mask": spaces.Box(0, 1, (N_TYPES * self._a,), np.int8)})
            self.single_action_space = spaces.Discrete(N_TYPES * self._a)
        else:
            self.single_action_space = single.action_space
        self.single_observation_space = obs_space
        self.observation_space = batch_space(obs_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.config = cfg
        self.table = self._batched.table
        self._obs: dict[str, torch.Tensor] | None = None

    # -- gymnasium API ------------------------------------------------------------------------
    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        """New episodes everywhere. ``seed`` reseeds the start sampler (an int, or a list whose
        first entry is used: the envs share one generator); ``options`` may give ``scenes``
        (table scene indices) and ``views`` (N,) as BatchedAODEnv.reset does."""
        self._check_open("reset")
        if seed is not None:
            first = seed[0] if isinstance(seed, list | tuple) else seed
            if first is not None:
                self._batched.generator.manual_seed(int(first))
        options = dict(options or {})
        unknown = sorted(set(options) - {"scenes", "views"})
        if unknown:
            raise ValueError(f"reset options {unknown}: accepted are 'scenes' and 'views'")
        self._obs = self._batched.reset(**options)
        return self._numpy(self._obs), {}

    def step(self, actions: Any):
        self._check_open("step")
        a_type, a_range = self._split_actions(actions)
        obs, reward, done, info = self._batched.step(a_type, a_range)
        self._obs = obs
        infos: dict[str, Any] = {}
        if bool(done.any()):
            mask = done.cpu().numpy()
            for key, value in info.items():
                infos[key] = value.cpu().numpy()
                infos["_" + key] = mask
            infos["final_obs"] = self._final_obs(info, mask)
            infos["_final_obs"] = mask
        terminated = done.cpu().numpy()
        return (self._numpy(obs), reward.cpu().numpy(), terminated, np.zeros_like(terminated), infos)

    def action_masks(self) -> np.ndarray:
        """The allowed actions at every env's current view, shaped for the action space:
        (N, 7 * A) joint masks for ``actions="flat"`` (sb3-contrib's MaskablePPO), else the
        per-dimension (N, 7 + A) masks MaskablePPO uses for MultiDiscrete (a type where any
        range is allowed; every range, since the joint rule cannot be split)."""
        if self._obs is None:
            raise RuntimeError("action_masks() before reset()")
        return action_masks(self._obs["mask"].cpu().numpy(), self.actions)

    @property
    def autoreset_mode(self) -> gym.vector.AutoresetMode:
        """Same-step autoreset (``metadata["autoreset_mode"]``), as an attribute too: TorchRL's
        GymWrapper reads it there."""
        return self.metadata["autoreset_mode"]

    def close(self, **kwargs: Any) -> None:
        """Release the episode state; ``closed`` is True after it and a later ``step`` or
        ``reset`` is an error (Gymnasium's vector envs behave so)."""
        self._obs = None
        self.closed = True

    # -- helpers --------------------------------------------------------------------------------
    def _check_open(self, what: str) -> None:
        if getattr(self, "closed", False):
            raise RuntimeError(f"{what}() on a closed AODVectorEnv: make a new one")

    def _split_actions(self, actions: Any) -> tuple[torch.Tensor, torch.Tensor]:
        a = np.asarray(actions)
        n = self.num_envs
        if a.dtype.kind not in "iu":
            raise ValueError(f"actions of dtype {a.dtype}: expected integers")
        if self.actions == "flat":
            if a.shape != (n,) or bool(((a < 0) | (a >= N_TYPES * self._a)).any()):
                raise ValueError(f"actions {a.tolist()[:8]} (shape {a.shape}): expected ({n},) indices of "
                                 f"Discrete({N_TYPES * self._a})")
            a_type, a_range = np.divmod(a.astype(np.int64), self._a)  # type-major, as grid.flat_action
            return torch.as_tensor(a_type), torch.as_tensor(a_range)
        if a.shape != (n, 2):
            raise ValueError(f"actions of shape {a.shape}: expected ({n}, 2) (type, range index) pairs")
        return torch.as_tensor(a[:, 0].astype(np.int64)), torch.as_tensor(a[:, 1].astype(np.int64))

    def _numpy(self, obs: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        mask = obs["mask"].to(torch.int8).cpu().numpy()
        if self.actions == "flat":
            mask = mask.reshape(self.num_envs, -1)
        return {"features": obs["features"].cpu().numpy(), "box": obs["box"].cpu().numpy(),
                "action_mask": mask, "t": obs["t"].cpu().numpy()}

    def _final_obs(self, info: dict[str, torch.Tensor], done: np.ndarray) -> np.ndarray:
        tb = self._batched.tensors
        scene = tb.local.index_select(0, info["final_scene"])
        last = self._numpy(tb.observe(scene, info["final_view"], info["final_decisions"]))
        out = np.empty(self.num_envs, dtype=object)
        for i in np.flatnonzero(done):
            out[i] = {k: v[i] for k, v in last.items()}
        return out


def action_masks(mask: np.ndarray, actions: str) -> np.ndarray:
    """(N, 7, A) allowed-action masks -> the form of the action space (see AODVectorEnv)."""
    mask = np.asarray(mask, dtype=bool)
    if actions == "flat":
        return mask.reshape(mask.shape[0], -1)
    types = mask.any(-1)
    types[:, STOP] = True
    return np.concatenate([types, np.ones((mask.shape[0], mask.shape[-1]), bool)], axis=1)


def make_vector_env(table: Any, split: str = "train", config: EnvConfig | dict[str, Any] | None = None, *,
                    num_envs: int = 64, actions: str = "multi", device: str | torch.device = "cpu",
                    **overrides: Any) -> AODVectorEnv:
    """The vector entry point of ``uevavd/AOD-v0`` (``gymnasium.make_vec``)."""
    return AODVectorEnv(table, split, config, num_envs=num_envs, actions=actions, device=device, **overrides)

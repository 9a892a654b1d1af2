"""Wrappers of :class:`~uevavd.env.aod_env.AODEnv` for libraries with other conventions."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..data.grid import N_TYPES, unflat_action
from .spaces import action_masks, flat_space, flatten_observation


class DiscreteActions(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """``MultiDiscrete([7, A])`` -> ``Discrete(7 * A)`` for libraries that need one action
    index (Stable-Baselines3's DQN). Index ``a = type * A + range`` (type-major, as
    :func:`uevavd.data.grid.flat_action`); stop is ``6 * A + r`` for any ``r``.

    The observation's ``"action_mask"`` is flattened to (7 * A,) int8 in the same order,
    so ``mask[a]`` answers for joint action ``a``. Everything else passes through.
    """

    def __init__(self, env: gym.Env) -> None:
        # recorded so that env.spec.make() (and with it gymnasium's check_env) rebuilds the stack
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)
        nvec = np.asarray(env.action_space.nvec)
        if nvec.shape != (2,) or int(nvec[0]) != N_TYPES:
            raise ValueError(f"DiscreteActions wraps a MultiDiscrete([7, A]) env, got {env.action_space}")
        self._a = int(nvec[1])
        self.action_space = spaces.Discrete(N_TYPES * self._a)
        inner = env.observation_space
        self.observation_space = spaces.Dict(
            {**inner.spaces, "action_mask": spaces.Box(0, 1, (N_TYPES * self._a,), np.int8)}
        )

    def _flat_obs(self, obs: dict[str, Any]) -> dict[str, Any]:
        return {**obs, "action_mask": obs["action_mask"].reshape(-1)}

    def reset(self, **kwargs: Any):
        """The wrapped env's reset, its mask flattened to the joint actions."""
        obs, info = self.env.reset(**kwargs)
        return self._flat_obs(obs), info

    def action_masks(self) -> np.ndarray:
        """(7 * A,) bool: the joint actions allowed at the current view (sb3-contrib's MaskablePPO)."""
        env = self.env.unwrapped
        return action_masks(env._tr.mask[env._view][None], "flat")[0]

    def step(self, action: Any):
        """Take joint action ``type * A + range`` (an int in 0..7A-1)."""
        if not self.action_space.contains(action) and not (
            np.ndim(action) == 0 and float(action) == int(action) and 0 <= int(action) < N_TYPES * self._a
        ):
            raise ValueError(f"action {action!r} is outside Discrete({N_TYPES * self._a})")
        a_type, a_range = unflat_action(int(action), self._a)
        obs, reward, terminated, truncated, info = self.env.step(np.array([a_type, a_range], np.int64))
        return self._flat_obs(obs), reward, terminated, truncated, info


class MaskedFlatObservation(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """The observation as ``{"obs": flat float32 vector, "mask": (7 * A,) bool}`` over one
    action index (:class:`DiscreteActions` is applied where the env has the joint action):
    the convention of libraries that read an action mask from ``obs.mask`` (Tianshou's DQN
    family masks its Q-values and its exploration with it). ``"obs"`` is every flat route's
    vector, ``[features, box, (pose,) t, action_mask]`` (:func:`~uevavd.env.spaces.flatten_observation`:
    the env's ``observation="flat"``, :func:`~uevavd.env.offline.flat_dataset` and
    :class:`~uevavd.env.offline.FlatPolicy`), so a network trained here scores through any of them."""

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        if isinstance(env.action_space, spaces.MultiDiscrete):
            env = DiscreteActions(env)
        gym.ObservationWrapper.__init__(self, env)
        self.observation_space = spaces.Dict({
            "obs": flat_space(env.observation_space),
            "mask": spaces.MultiBinary(int(env.action_space.n)),
        })

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        """The env's dict observation -> ``{"obs": float32 vector, "mask": bool action mask}``."""
        return {"obs": flatten_observation(observation),
                "mask": np.asarray(observation["action_mask"], dtype=bool).reshape(-1)}

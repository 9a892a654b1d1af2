"""Stable-Baselines3 ``VecEnv`` over :class:`~uevavd.env.vector.AODVectorEnv`.

SB3 (2.x) steps its own ``VecEnv`` class and has no adapter for Gymnasium's ``VectorEnv``,
so the library ships this small one::

    from uevavd.env.sb3 import SB3VecEnv
    venv = SB3VecEnv(gymnasium.make_vec("uevavd/AOD-v0", num_envs=64, vectorization_mode="vector_entry_point",
                                        table=path, actions="flat"))
    DQN("MultiInputPolicy", venv).learn(20_000)

Episodes that end report SB3's ``terminal_observation`` (never ``TimeLimit.truncated``: the
AOD episode always terminates) and the ``final_*`` fields of the batched env;
``env_method("action_masks")`` gives each env's mask, so sb3-contrib's MaskablePPO works.
Wrap it in SB3's ``VecMonitor`` for episode statistics.

:class:`SB3Policy` goes the other way: a trained SB3 model (on ``DiscreteActions(AODEnv)``)
as a policy for :func:`uevavd.env.evaluate.evaluate_policy`'s exhaustive evaluation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

from .spaces import parts_differ, present_parts
from .vector import AODVectorEnv


class SB3VecEnv(VecEnv):
    """SB3's ``VecEnv`` interface around one :class:`AODVectorEnv` (all envs in one process)."""

    def __init__(self, venv: AODVectorEnv) -> None:
        venv = getattr(venv, "unwrapped", venv)
        if not isinstance(venv, AODVectorEnv):
            raise TypeError(f"SB3VecEnv wraps an AODVectorEnv (gymnasium.make_vec of uevavd/AOD-v0), got {type(venv)}")
        if venv._next_step:  # SB3's convention: the last observation in terminal_observation, the next one returned
            try:
                venv.use_autoreset_mode("same_step")
            except RuntimeError:
                raise ValueError("SB3VecEnv needs the vector env's same-step autoreset (SB3's VecEnv convention), and "
                                 "this one was reset in next-step mode already: wrap it before its first reset, or make "
                                 "it with autoreset_mode='same_step'") from None
        self.venv = venv
        self.render_mode = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self):
        """New episodes everywhere, with the seeds SB3's ``seed()`` set (env i: seed + i); returns the observations."""
        # SB3's seed(s) gives env i the seed s + i, as Gymnasium's vector envs do with reset(seed=s)
        obs, _ = self.venv.reset(seed=list(self._seeds))
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        """Keep the actions for :meth:`step_wait` (SB3's two-part step)."""
        self._actions = np.asarray(actions)

    def step_wait(self):
        """Step every env: (observations, float32 rewards, dones, one info dict per env with the ended episodes' ``terminal_observation`` and ``final_*`` fields)."""
        obs, reward, terminated, truncated, infos = self.venv.step(self._actions)
        done = terminated | truncated
        out: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        final = {k: v for k, v in infos.items() if k.startswith("final_") and k not in ("final_obs", "final_info")}
        for i in np.flatnonzero(done):
            row = {k: v[i] for k, v in final.items()}
            row.update((k, v[i]) for k, v in infos["final_info"].items() if not k.startswith("_"))
            row["terminal_observation"] = infos["final_obs"][i]
            row["TimeLimit.truncated"] = bool(truncated[i])
            out[i] = row
        return obs, reward.astype(np.float32), done, out

    def close(self) -> None:
        """Close the vector env."""
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The vector env's attribute, once per env asked for."""
        value = getattr(self.venv, attr_name)  # AttributeError where absent, as SB3 expects
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set the attribute on the vector env (all envs share it)."""
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        """A per-env answer: an array with one row per env (``action_masks``) is split by row."""
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        idx = list(self._get_indices(indices))
        if isinstance(result, np.ndarray) and result.shape[:1] == (self.num_envs,):
            return [result[i] for i in idx]
        return [result for _ in idx]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """False for every env: the vector env is not a stack of wrapped single envs."""
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """No images (one None per env): render with the vector env's ``render()``."""
        return [None for _ in range(self.num_envs)]


class SB3Policy:
    """A Stable-Baselines3 model trained on ``DiscreteActions(AODEnv)`` as a uevavd evaluation
    policy: the batched observations become the ones it was trained on (flat mask, ``t``)
    and it acts deterministically. A recurrent model (sb3-contrib's RecurrentPPO) keeps its
    state per row and restarts it where ``t == 0``."""

    def __init__(self, model: Any, max_range: int, *, recurrent: bool | None = None) -> None:
        self.model, self.a = model, int(max_range)
        self.recurrent = type(model).__name__.startswith("Recurrent") if recurrent is None else recurrent
        self.state = None

    def reset(self, n: int) -> None:
        """Forget a recurrent model's state for ``n`` new episodes."""
        self.state = None

    def act(self, obs: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's deterministic action per episode, on the observations it was trained on; a model of another env config (the pose) is refused by name."""
        t = torch.as_tensor(obs["t"]).cpu()
        n = len(t)
        sb3_obs = {"features": torch.as_tensor(obs["features"]).float().cpu().numpy(),
                   "box": torch.as_tensor(obs["box"]).float().cpu().numpy(),
                   "action_mask": torch.as_tensor(obs["mask"]).reshape(n, -1).to(torch.int8).cpu().numpy(),
                   "t": t.numpy()}
        if "pose" in obs:  # a model trained with EnvConfig.pose
            sb3_obs["pose"] = torch.as_tensor(obs["pose"]).float().cpu().numpy()
        space = getattr(self.model, "observation_space", None)
        if isinstance(space, gym.spaces.Dict):  # a model of another env config: refused by name, not by SB3's shapes
            problem = parts_differ("the SB3 model", present_parts(space.spaces), present_parts(sb3_obs))
            if problem:
                raise ValueError(problem)
        if self.recurrent:
            flat, self.state = self.model.predict(sb3_obs, state=self.state, episode_start=(t == 0).numpy(),
                                                  deterministic=True)
        else:
            flat, _ = self.model.predict(sb3_obs, deterministic=True)
        flat = torch.as_tensor(np.asarray(flat), dtype=torch.int64).reshape(-1)
        return flat // self.a, flat % self.a


def silent_logger() -> Any:
    """An SB3 logger that writes nowhere. SB3 gives a model without one (``verbose=0``, no
    ``tensorboard_log``) a logger that creates an empty ``SB3-<date>`` folder in the temp
    directory on every ``learn()``; ``model.set_logger(silent_logger())`` avoids that litter."""
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])

"""The batched environment behind the standard vector interfaces.

:class:`AODVectorEnv` is :class:`~uevavd.env.batched.BatchedAODEnv` as a Gymnasium
``VectorEnv`` (numpy in and out, next-step autoreset by default, as Gymnasium's own), what
``gymnasium.make_vec("uevavd/AOD-v0", num_envs=N, vectorization_mode="vector_entry_point",
table=..., split=...)`` returns. :class:`SB3VecEnv` adapts it to Stable-Baselines3's
``VecEnv`` (SB3 has no adapter for Gymnasium vector envs). With ``actions="flat"`` the
action is one index ``type * A + range`` of ``Discrete(7 * A)`` and the observation's
``action_mask`` is flattened the same way, as :class:`~uevavd.env.wrappers.DiscreteActions`
does for the single env (what SB3's DQN and sb3-contrib's MaskablePPO need).

Observations are those of :class:`~uevavd.env.aod_env.AODEnv` batched: ``features`` (N, D)
float32, ``box`` (N, 4) float32, ``action_mask`` (N, 7, A) int8 (or (N, 7 * A)), with
``EnvConfig.pose`` ``pose`` (N, 3) float32 metres, ``t`` (N,)
int64. An episode always ends by termination (stop or T_max), never truncation. Where it ends,
with ``autoreset_mode="next_step"`` (the default, Gymnasium's own vector envs' and what its vector
wrappers and CleanRL's scripts assume) the step returns its last observation and the env's next
step starts the next episode (reward 0, its action ignored); with ``"same_step"`` (SB3's
convention, which :class:`SB3VecEnv` asks for itself) the returned observation is the next
episode's first and ``infos["final_obs"]`` holds the last one, ``infos["final_info"]`` its step
info. Either way the ending step's info has the ``final_*`` fields of ``BatchedAODEnv``
(``final_return``, ``final_recognized``, ...), each with its ``_key`` mask; the envs going on get
the single env's step info at the top level.
Rewards are float64 and float actions equal to integers are taken, as the single env does.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector.utils import batch_space

from ..data.grid import N_TYPES, N_VIEWS, STOP
from .aod_env import integral_actions
from .batched import BatchedAODEnv
from .config import EnvConfig, make_config
from .render import render_frame
from .spaces import (
    action_masks,
    action_space,
    check_forms,
    form_space,
    in_form,
)

#: ``next_step`` (the default): where an episode ends, the step returns its last observation, and
#: the env's next step starts the next episode (reward 0, its action ignored), as Gymnasium's own
#: vector envs and its vector wrappers expect; ``same_step`` (SB3's convention): the step returns
#: the next episode's first observation and the last one in ``infos["final_obs"]``.
AUTORESET_MODES = ("same_step", "next_step")
#: The single env's per-step info keys the vector env reports at every step (``info[key]`` of
#: the envs going on, ``info["final_info"][key]`` of those whose episode ended), and the
#: BatchedAODEnv field each is read from.
STEP_INFO = {"view": "final_view", "scene": "final_scene", "t": "final_decisions", "recognized": "final_recognized",
             "correct": "final_correct", "stopped": "final_stopped", "return": "final_return",
             "steps": "final_steps", "distance_m": "final_distance_m"}


def env_seeds(seed: Any, n: int) -> list[int | None] | None:
    """Each env's seed from ``reset(seed=...)``, Gymnasium's convention (its ``SyncVectorEnv``):
    an int ``s`` gives env ``i`` the seed ``s + i``, a list of ``n`` ints (or Nones) one each;
    None where none is given."""
    if seed is None:
        return None
    seeds = list(seed) if isinstance(seed, list | tuple | np.ndarray) else None
    if seeds is None:
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"reset(seed={seed!r}): expected an int >= 0, or a list of {n} of them")
        return [int(seed) + i for i in range(n)]
    if len(seeds) != n or not all(s is None or (isinstance(s, int | np.integer) and not isinstance(s, bool)
                                                and s >= 0) for s in seeds):
        raise ValueError(f"reset(seed={seeds!r}): expected an int >= 0, or a list of {n} of them (or Nones)")
    return [None if s is None else int(s) for s in seeds]


def _autoreset_mode(mode: Any) -> str:
    """``"same_step"`` or ``"next_step"`` from either name or Gymnasium's ``AutoresetMode``."""
    name = {"SameStep": "same_step", "NextStep": "next_step"}.get(getattr(mode, "value", None), mode)
    if name not in AUTORESET_MODES:
        raise ValueError(f"autoreset_mode={mode!r}: expected one of {AUTORESET_MODES} (or gymnasium.vector."
                         "AutoresetMode.SAME_STEP / NEXT_STEP)")
    return name


class AODVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` AOD episodes in lockstep (see the module doc)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, table: Any, split: str = "train", config: EnvConfig | dict[str, Any] | None = None, *,
                 num_envs: int = 1, actions: str = "multi", observation: str = "dict",
                 device: str | torch.device = "cpu", contexts: Any = None, render_mode: str | None = None,
                 autoreset_mode: Any = "next_step", **overrides: Any) -> None:
        check_forms(actions, observation)
        self.metadata = dict(type(self).metadata)
        self._obs = None
        self.use_autoreset_mode(autoreset_mode)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode={render_mode!r}: expected None or one of {self.metadata['render_modes']}")
        self.render_mode = render_mode
        cfg = make_config(config, **overrides)
        self._batched = BatchedAODEnv(table, split, num_envs, cfg, device=device, contexts=contexts)
        self.num_envs = num_envs
        self.actions, self.observation = actions, observation
        self._a = cfg.max_range
        self.single_action_space = action_space(cfg, actions=actions)
        self.single_observation_space = form_space(self._batched.table.feature_dim, cfg, actions=actions,
                                                   observation=observation)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.config = cfg
        self.table = self._batched.table
        self._obs: dict[str, torch.Tensor] | None = None
        self._rngs: list[np.random.Generator] | None = None  # one per env, as the single env's np_random
        self._batched.start_sampler = self._draw_starts
        self._held = np.zeros(num_envs, bool)  # next-step: the envs whose next step is their reset

    # -- gymnasium API ------------------------------------------------------------------------
    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        """New episodes everywhere. Each env draws its starts from its own generator, as the
        single env does, seeded by Gymnasium's convention: ``seed=s`` gives env ``i`` the seed
        ``s + i`` (it then starts, and restarts after each episode, as ``gym.make(...)`` reset
        with ``seed=s + i`` and then without one), a list of ``num_envs`` seeds one each.
        Without a seed the first reset seeds them from the OS's entropy, as Gymnasium's envs
        do. ``options`` may give ``scenes`` (table scene indices) and ``views`` (N,) as
        BatchedAODEnv.reset does."""
        self._check_open("reset")
        seeds = env_seeds(seed, self.num_envs) or [None] * self.num_envs
        if self._rngs is None:  # the first reset: from the OS's entropy where no seed is given
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        else:  # a seed reseeds its env; None keeps the env's generator going, as the single env's reset()
            self._rngs = [rng if s is None else seeding.np_random(s)[0] for rng, s in zip(self._rngs, seeds, strict=True)]
        options = dict(options or {})
        unknown = sorted(set(options) - {"scenes", "views"})
        if unknown:
            raise ValueError(f"reset options {unknown}: accepted are 'scenes' and 'views'")
        self._obs = self._batched.reset(**options)
        self._held[:] = False
        return self._numpy(self._obs), {}

    def _draw_starts(self, where: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """New episodes' starts, drawn as the single env draws them (a scene of the split, then
        a view unless ``config.start_view`` fixes it), each env from its own generator, only
        for the envs that start one: env ``i`` then follows ``gym.make`` seeded with its seed.
        Not for the envs held for a next-step reset: their episode was drawn when the last one
        ended, and the stop they take in its place is put back."""
        n = self.num_envs
        starting = range(n) if where is None else np.flatnonzero(where.cpu().numpy() & ~self._held)
        scene, view = np.zeros(n, np.int64), np.zeros(n, np.int64)
        fixed = self.config.start_view
        for i in starting:
            rng = self._rngs[i]
            scene[i] = rng.integers(len(self._batched.tensors.scenes))
            view[i] = fixed if fixed is not None else rng.integers(N_VIEWS)
        dev = self._batched.device
        return torch.as_tensor(scene, device=dev), torch.as_tensor(view, device=dev)

    def step(self, actions: Any):
        """One (type, range) action per env, (num_envs, 2) int; returns the batched (observations,
        rewards, terminations, truncations, infos), ended episodes restarting by the env's
        ``autoreset_mode`` (next-step by default, as Gymnasium's own vector envs)."""
        self._check_open("step")
        a_type, a_range = self._split_actions(actions)
        held = self._held.copy()
        if held.any():  # next-step autoreset: these envs start their next episode, their action ignored
            h = torch.as_tensor(held)
            a_type, a_range = torch.where(h, STOP, a_type), torch.where(h, 0, a_range)
            started = self._batched.episodes()
        obs, _, done, info = self._batched.step(a_type, a_range)
        if held.any():
            self._batched.hold(h, started)
            obs = self._batched.observe()
        self._obs = obs
        reward = info.pop("reward64").cpu().numpy()  # float64, as Gymnasium's sync mode gives it
        reward[held] = 0.0
        terminated = done.cpu().numpy() & ~held
        # the single env's per-step info, for the envs whose step counts: in same-step mode those
        # whose episode goes on (where one ended, the observation is the next episode's first:
        # its step info is in final_info); in next-step mode every env but those resetting
        step_info = {key: info[field].cpu().numpy() for key, field in STEP_INFO.items()}
        shown = ~held if self._next_step else ~terminated
        infos: dict[str, Any] = {}
        if shown.any():
            for key, value in step_info.items():
                infos[key], infos["_" + key] = value, shown
        numpy_obs = self._numpy(obs)
        if terminated.any():
            for key, value in info.items():  # the final_* fields, as before
                infos[key] = value.cpu().numpy()
                infos["_" + key] = terminated
            last = self._last_obs(info)
            if self._next_step:  # the episode's last observation, in place; its reset comes next step
                if isinstance(numpy_obs, np.ndarray):  # observation="flat"
                    numpy_obs[terminated] = last[terminated]
                for key, value in (numpy_obs.items() if isinstance(numpy_obs, dict) else ()):
                    value[terminated] = last[key][terminated]  # the Dict and the "masked" forms
                self._held = terminated.copy()  # not the array returned
            else:
                infos["final_obs"] = self._final_obs(last, terminated)
                infos["_final_obs"] = terminated
                infos["final_info"] = {**step_info, **{"_" + k: terminated for k in step_info}}
                infos["_final_info"] = terminated
        else:
            self._held[:] = False
        return (numpy_obs, reward, terminated, np.zeros_like(terminated), infos)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """With ``render_mode="rgb_array"``: one frame per env (:func:`~uevavd.env.render.render_frame`
        of its current view; the vector env keeps no path, so each map shows the current view
        only). Otherwise None."""
        if self.render_mode != "rgb_array":
            return None
        if self._obs is None:
            raise RuntimeError("render() before reset()")
        b = self._batched
        scenes = b.tensors.scenes[b._scene].tolist()
        views, ts = b._view.tolist(), b._t.tolist()
        return tuple(render_frame(self.table, s, [v], t) for s, v, t in zip(scenes, views, ts, strict=True))

    def action_masks(self) -> np.ndarray:
        """The allowed actions at every env's current view, shaped for the action space:
        (N, 7 * A) joint masks for ``actions="flat"`` (sb3-contrib's MaskablePPO), else the
        per-dimension (N, 7 + A) masks MaskablePPO uses for MultiDiscrete (a type where any
        range is allowed; every range, since the joint rule cannot be split)."""
        if self._obs is None:
            raise RuntimeError("action_masks() before reset()")
        return action_masks(self._obs["mask"].cpu().numpy(), self.actions)

    def use_autoreset_mode(self, mode: Any) -> None:
        """Set the autoreset mode (``"next_step"``, Gymnasium's default, or ``"same_step"``, SB3's
        convention, which :class:`~uevavd.env.sb3.SB3VecEnv` asks for), before the first reset."""
        if getattr(self, "_obs", None) is not None:
            raise RuntimeError("use_autoreset_mode() after reset(): set the autoreset mode before the first reset")
        self._next_step = _autoreset_mode(mode) == "next_step"
        modes = getattr(gym.vector, "AutoresetMode", None)  # Gymnasium 1.1 on; 1.0's wrappers assume next-step
        if modes:
            self.metadata["autoreset_mode"] = modes.NEXT_STEP if self._next_step else modes.SAME_STEP

    @property
    def autoreset_mode(self) -> Any:
        """The autoreset mode (``metadata["autoreset_mode"]``, Gymnasium's ``AutoresetMode``), as
        an attribute too: TorchRL's GymWrapper reads it there."""
        return self.metadata.get("autoreset_mode", "next_step" if self._next_step else "same_step")

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
        a = integral_actions(actions)  # integers, or floats equal to them, as the single env
        n = self.num_envs
        if a is None:
            raise ValueError(f"actions of dtype {np.asarray(actions).dtype}: expected integers (or floats equal to them)")
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
        out = {"features": obs["features"].cpu().numpy(), "box": obs["box"].cpu().numpy(),
               "action_mask": mask, "t": obs["t"].cpu().numpy()}
        if "pose" in obs:  # EnvConfig.pose
            out["pose"] = obs["pose"].cpu().numpy()
        return in_form(out, self.observation)

    def _last_obs(self, info: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Every env's observation at the end of its step (before any autoreset)."""
        tb = self._batched.tensors
        scene = tb.local.index_select(0, info["final_scene"])
        return self._numpy(tb.observe(scene, info["final_view"], info["final_decisions"]))

    def _final_obs(self, last: dict[str, np.ndarray] | np.ndarray, done: np.ndarray) -> np.ndarray:
        out = np.empty(self.num_envs, dtype=object)
        for i in np.flatnonzero(done):
            out[i] = last[i] if isinstance(last, np.ndarray) else {k: v[i] for k, v in last.items()}
        return out


def make_vector_env(table: Any, split: str = "train", config: EnvConfig | dict[str, Any] | None = None, *,
                    num_envs: int = 64, actions: str = "multi", observation: str = "dict",
                    device: str | torch.device = "cpu", autoreset_mode: Any = "next_step",
                    **overrides: Any) -> AODVectorEnv:
    """The vector entry point of ``uevavd/AOD-v0`` (``gymnasium.make_vec``)."""
    return AODVectorEnv(table, split, config, num_envs=num_envs, actions=actions, observation=observation,
                        device=device, autoreset_mode=autoreset_mode, **overrides)

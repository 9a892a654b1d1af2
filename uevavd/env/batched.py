"""``BatchedAODEnv``: N AOD episodes in lockstep as torch tensors, on CPU or GPU.

Same semantics as :class:`~uevavd.env.aod_env.AODEnv` (docs/environment.md), with automatic
reset. Every step is a handful of tensor gathers over precomputed tensors; there is no
Python loop over environments. API (stable; the DQN trainer builds on it)::

    env = BatchedAODEnv(table, "train", n_envs=1024, config=EnvConfig(), device="cpu", seed=0)
    obs = env.reset()                        # or reset(scenes=..., views=...) explicit starts
    obs, reward, done, info = env.step(a_type, a_range)   # (N,) int64 each

``obs``: ``"features"`` (N, D) float32, ``"box"`` (N, 4) float32 XYXY in [0, 1],
``"mask"`` (N, 7, A) bool (True = allowed without clamping; stop always True), ``"t"``
(N,) int64 decisions taken in the current episode, ``"scene"`` (N,) int64 *table* scene
index, ``"view"`` (N,) int64; with ``EnvConfig.pose``, ``"pose"`` (N, 3) float32, the
viewpoint's (x, y, z) in metres relative to the target. ``reward`` (N,) float32, ``done`` (N,) bool (stop or T_max;
always a termination, never a truncation: do not bootstrap past it).

For done envs ``obs`` already shows the first view of the next episode; ``info`` holds
``final_view``, ``final_scene``, ``final_recognized``, ``final_correct``, ``final_return``
(discounted), ``final_distance_m``, ``final_steps`` (grid steps), ``final_decisions``,
``final_stopped``, each (N,) and meaningful where ``done``. ``state_dict()`` /
``load_state_dict()`` capture the RNG and the running episodes so training resumes exactly.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..data.grid import N_TYPES, N_VIEWS, STEP_M, STOP, transitions, view_coords
from ..table import ObservationTable, load_table
from .config import EnvConfig, make_config


class EnvTensors:
    """The device tensors of one (table, split, config) on a device.

    ``features`` (S', 605, D) float32 or float16, ``boxes`` (S', 605, 4) float32,
    ``reco`` / ``acc`` (S', 605) bool, ``next_view`` / ``steps`` (605, 7, A) int64,
    ``mask`` (605, 7, A) bool; ``scenes`` (S',) int64 table indices of the local scenes
    and ``local`` (S,) int64 mapping a table index to its local one (-1 if absent);
    ``contexts`` (S',) numpy context ids. ``with_features=False`` keeps a (S', 605, 0)
    placeholder (for policies that never read features).
    """

    def __init__(
        self,
        table: ObservationTable,
        split: str,
        config: EnvConfig,
        *,
        device: str | torch.device = "cpu",
        contexts: Any = None,
        features_dtype: torch.dtype = torch.float32,
        with_features: bool = True,
    ) -> None:
        dev = torch.device(device)
        self.device = dev
        self.config = config
        self.table_key = table.key
        sel = table.select(split, contexts, train_per_block=config.train_per_block,
                           holdout_block=config.holdout_block)
        self.scenes = torch.as_tensor(sel, dtype=torch.int64, device=dev)
        local = np.full(len(table), -1, np.int64)
        local[sel] = np.arange(len(sel))
        self.local = torch.as_tensor(local, device=dev)
        if with_features:
            feats = np.asarray(table.features[sel])
            self.features = torch.as_tensor(feats, device=dev).to(features_dtype)
        else:
            self.features = torch.zeros((len(sel), N_VIEWS, 0), dtype=features_dtype, device=dev)
        self.feature_dim = table.feature_dim
        self.boxes = torch.as_tensor(np.asarray(table.boxes[sel]), dtype=torch.float32, device=dev)
        self.reco = torch.as_tensor(config.recognized(table.true_class_probs())[sel], device=dev)
        self.acc = torch.as_tensor(table.argmax_correct()[sel], device=dev)
        self.targets = torch.as_tensor(table.targets[sel], device=dev)
        self.contexts = np.asarray(table.contexts[sel], np.int64)  # (S',) context ids
        self.visible = np.asarray(table.visible[sel], np.float64)  # (S', 605) visible fractions (NaN: unknown)
        self.class_names = table.class_names
        self.split = split
        tr = transitions(config.max_range)
        self.next_view = torch.as_tensor(np.array(tr.next_view), device=dev)
        self.steps = torch.as_tensor(np.array(tr.steps), device=dev)
        self.mask = torch.as_tensor(np.array(tr.mask), device=dev)
        #: (605, 3) float32 every view's (x, y, z) in metres, target at the origin
        self.pose = torch.as_tensor(view_coords(np.arange(N_VIEWS)), dtype=torch.float32, device=dev)
        # flat views of the same memory for fast gathers
        self._features_flat = self.features.reshape(len(sel) * N_VIEWS, self.features.shape[2])
        self._boxes_flat = self.boxes.reshape(-1, 4)
        self._reco_flat = self.reco.reshape(-1)
        self._acc_flat = self.acc.reshape(-1)
        self._mask_flat = self.mask.reshape(N_VIEWS, -1)
        self._next_flat = self.next_view.reshape(-1)
        self._steps_flat = self.steps.reshape(-1)

    def observe(self, local_scene: torch.Tensor, view: torch.Tensor, t: torch.Tensor) -> dict[str, torch.Tensor]:
        """Observation dict (see module doc) of envs at (local scene, view) after t decisions."""
        # index_select on flattened tensors: several times faster than 2-D advanced indexing
        flat = local_scene * N_VIEWS + view
        a = self.config.max_range
        obs = {
            "features": self._features_flat.index_select(0, flat).float(),
            "box": self._boxes_flat.index_select(0, flat),
            "mask": self._mask_flat.index_select(0, view).view(-1, N_TYPES, a),
            "t": t,
            "scene": self.scenes.index_select(0, local_scene),
            "view": view,
        }
        if self.config.pose:
            obs["pose"] = self.pose.index_select(0, view)
        return obs

    def check_actions(self, a_type: torch.Tensor, a_range: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(a_type, a_range)`` as (n,) int64 tensors on this device, or a ValueError naming the shape, dtype or value the env refuses."""
        a_type = torch.as_tensor(a_type, device=self.device)
        a_range = torch.as_tensor(a_range, device=self.device)
        if a_type.shape != (n,) or a_range.shape != (n,):
            raise ValueError(
                f"actions have shapes {tuple(a_type.shape)} and {tuple(a_range.shape)}; expected ({n},) each"
            )
        if a_type.is_floating_point() or a_range.is_floating_point():
            raise ValueError("actions must be integer tensors (type index, range index)")
        a = self.config.max_range
        bad = (a_type < 0) | (a_type > STOP) | (a_range < 0) | (a_range >= a)
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0, 0])
            raise ValueError(
                f"action ({int(a_type[i])}, {int(a_range[i])}) of env {i} is outside MultiDiscrete([7, {a}]): "
                f"type 0..6 (stop = {STOP}), range index 0..{a - 1}"
            )
        return a_type.long(), a_range.long()

    def transition(
        self, local_scene: torch.Tensor, view: torch.Tensor, t: torch.Tensor, a_type: torch.Tensor, a_range: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """One decision for every env: ``next_view``, ``reward`` (float64), ``final`` (bool),
        ``steps`` flown (int64), ``stopped``, ``recognized`` and ``correct`` at the next view."""
        cfg = self.config
        act = (view * 7 + a_type) * cfg.max_range + a_range  # flat (view, type, range)
        nv = self._next_flat.index_select(0, act)  # stop stays (grid table)
        stopped = a_type == STOP
        final = stopped | (t >= cfg.t_max - 1)
        at = local_scene * N_VIEWS + nv
        reco = self._reco_flat.index_select(0, at)
        # EnvConfig's rule in float64, so rewards and returns agree exactly with AODEnv's
        cost = torch.where(stopped, 0.0, cfg.move_cost(a_range.double()))
        reward = cfg.reward(final, reco, cost)
        return {
            "next_view": nv,
            "reward": reward,
            "final": final,
            "steps": self._steps_flat.index_select(0, act),
            "stopped": stopped,
            "recognized": reco,
            "correct": self._acc_flat.index_select(0, at),
        }


class BatchedAODEnv:
    """N AOD episodes in parallel with auto-reset (see the module doc for the API)."""

    def __init__(
        self,
        table: ObservationTable | str | os.PathLike[str],
        split: str,
        n_envs: int,
        config: EnvConfig | dict[str, Any] | None = None,
        *,
        device: str | torch.device = "cpu",
        seed: int = 0,
        contexts: Any = None,
        features_dtype: torch.dtype = torch.float32,
    ) -> None:
        if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
            raise ValueError(f"n_envs={n_envs!r}: expected an integer >= 1")
        self.table = load_table(table)
        self.config = make_config(config)
        self.split = split
        self.n_envs = n_envs
        self.tensors = EnvTensors(
            self.table, split, self.config, device=device, contexts=contexts, features_dtype=features_dtype
        )
        self.device = self.tensors.device
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(int(seed))
        self._discounts = torch.tensor(
            [self.config.gamma**k for k in range(self.config.t_max)], dtype=torch.float64, device=self.device
        )
        z = torch.zeros(n_envs, dtype=torch.int64, device=self.device)
        self._scene, self._view, self._t, self._steps = z.clone(), z.clone(), z.clone(), z.clone()
        self._return = torch.zeros(n_envs, dtype=torch.float64, device=self.device)
        self._started = False
        #: (S',) probabilities of the split's scenes for new episodes (None: uniform); a
        #: context sampler (train.context_sampling) sets it before each step
        self.scene_weights: torch.Tensor | None = None
        #: draws new episodes' starts instead of :attr:`generator` where set: called with the
        #: (N,) bool envs that start one (None: all, at reset), it returns (N,) local scene
        #: indices and views (those of other envs are not read). The vector env's per-env
        #: generators, Gymnasium's seeding convention.
        self.start_sampler: Callable[[torch.Tensor | None], tuple[torch.Tensor, torch.Tensor]] | None = None

    # -- starts -----------------------------------------------------------------------------
    def _sample_starts(self, where: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        if self.start_sampler is not None:
            return self.start_sampler(where)
        n, g, dev = self.n_envs, self.generator, self.device
        if self.scene_weights is None:
            scene = torch.randint(len(self.tensors.scenes), (n,), generator=g, device=dev)
        else:
            scene = torch.multinomial(self.scene_weights, n, replacement=True, generator=g)
        fixed = self.config.start_view
        if fixed is None:
            view = torch.randint(N_VIEWS, (n,), generator=g, device=dev)
        else:
            view = torch.full((n,), fixed, dtype=torch.int64, device=dev)
        return scene, view

    def _obs(self) -> dict[str, torch.Tensor]:
        return self.tensors.observe(self._scene, self._view, self._t.clone())

    def reset(self, *, scenes: Any = None, views: Any = None) -> dict[str, torch.Tensor]:
        """Start new episodes in all envs; ``scenes`` (table indices in the split) and
        ``views`` (N,) override the random starts (either or both)."""
        scene, view = self._sample_starts()
        if scenes is not None:
            s = torch.as_tensor(scenes, dtype=torch.int64, device=self.device).expand(self.n_envs)
            if bool(((s < 0) | (s >= len(self.tensors.local))).any()) or bool((self.tensors.local[s.clamp(0, len(self.tensors.local) - 1)] < 0).any()):
                raise ValueError(
                    f"reset scenes {s.unique().tolist()}: expected table scene indices of split "
                    f"{self.split!r}, i.e. among {self.tensors.scenes.tolist()}"
                )
            scene = self.tensors.local[s]
        if views is not None:
            v = torch.as_tensor(views, dtype=torch.int64, device=self.device).expand(self.n_envs)
            if bool(((v < 0) | (v >= N_VIEWS)).any()):
                raise ValueError(f"reset views must be view indices 0..{N_VIEWS - 1}")
            view = v.clone()
        self._scene, self._view = scene, view
        self._t.zero_()
        self._steps.zero_()
        self._return.zero_()
        self._started = True
        return self._obs()

    # -- stepping ---------------------------------------------------------------------------
    def step(self, a_type: torch.Tensor, a_range: torch.Tensor):
        """Advance all envs by one decision; returns ``(obs, reward, done, info)``."""
        if not self._started:
            raise RuntimeError("BatchedAODEnv.step() before reset()")
        tb = self.tensors
        a_type, a_range = tb.check_actions(a_type, a_range, self.n_envs)
        out = tb.transition(self._scene, self._view, self._t, a_type, a_range)
        reward, done = out["reward"], out["final"]
        self._return += self._discounts[self._t] * reward
        reward = reward.float()
        self._steps += out["steps"]
        self._view = out["next_view"]
        self._t = self._t + 1
        info = {
            "final_view": self._view,
            "final_scene": tb.scenes[self._scene],
            "final_recognized": out["recognized"],
            "final_correct": out["correct"],
            "final_return": self._return.clone(),
            "final_distance_m": self._steps.double() * STEP_M,
            "final_steps": self._steps.clone(),
            "final_decisions": self._t.clone(),
            "final_stopped": out["stopped"],
            "reward64": out["reward"],  # the reward before the float32 cast (the vector env's, as sync mode's)
        }
        # auto-reset: sample for all (keeps RNG use independent of `done`), keep where not done
        scene, view = self._sample_starts(done)
        self._scene = torch.where(done, scene, self._scene)
        self._view = torch.where(done, view, self._view)
        self._t = torch.where(done, 0, self._t)
        self._steps = torch.where(done, 0, self._steps)
        self._return = torch.where(done, 0.0, self._return)
        return self._obs(), reward, done, info

    def episodes(self) -> tuple[torch.Tensor, ...]:
        """The running episodes (scene, view, decisions, steps walked, return so far), cloned:
        what :meth:`hold` puts back."""
        return tuple(x.clone() for x in (self._scene, self._view, self._t, self._steps, self._return))

    def hold(self, where: torch.Tensor, episodes: tuple[torch.Tensor, ...]) -> None:
        """Put back ``episodes`` (from :meth:`episodes`) in the envs ``where`` is true: a step
        they took does not count (the vector env's next-step autoreset, whose reset step
        ignores the action)."""
        now = (self._scene, self._view, self._t, self._steps, self._return)
        self._scene, self._view, self._t, self._steps, self._return = (
            torch.where(where.to(self.device), then, cur) for then, cur in zip(episodes, now, strict=True))

    # -- resume -----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """RNG state and running episodes (CPU tensors) for exact resumption."""
        return {
            "rng": self.generator.get_state(),
            "scene": self._scene.cpu(),
            "view": self._view.cpu(),
            "t": self._t.cpu(),
            "steps": self._steps.cpu(),
            "return": self._return.cpu(),
            "started": self._started,
            "n_envs": self.n_envs,
            "config": self.config.to_dict(),
            "split": self.split,
            "scenes": self.tensors.scenes.tolist(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; refuses a state of another n_envs, split, scenes or config."""
        mine_all = (
            ("n_envs", self.n_envs),
            ("split", self.split),
            ("config", self.config.to_dict()),
            ("scenes", self.tensors.scenes.tolist()),
        )
        for key, mine in mine_all:
            if state.get(key) != mine:
                raise ValueError(f"env state has {key}={state.get(key)!r} but this env has {mine!r}")
        self.generator.set_state(state["rng"])
        dev = self.device
        self._scene = state["scene"].to(dev)
        self._view = state["view"].to(dev)
        self._t = state["t"].to(dev)
        self._steps = state["steps"].to(dev)
        self._return = state["return"].to(dev)
        self._started = bool(state["started"])

    def observe(self) -> dict[str, torch.Tensor]:
        """The current observation without stepping."""
        return self._obs()

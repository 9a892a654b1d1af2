"""``AODEnv``: the AOD CMDP over an observation table as a ``gymnasium.Env`` (docs/environment.md).

One episode: start at a view of a context (scene) of the chosen split and observe it. At
decision ``t = 0..T_max-1`` choose ``(type, range)``. ``stop`` ends the episode at the
current view (reward ``+-xi1``); a move flies (clamped to the grid) and observes the new
view; the move at ``t = T_max-1`` ends the episode at the new view (reward
``+-xi1 - C*r``); any other move earns ``-xi2 - C*r``. ``r`` = requested grid steps.

Both ends set ``terminated=True`` and ``truncated`` is always False: the reaching of
T_max is part of the task's definition (its reward is the terminal one, Eq. 2), not a
time limit imposed from outside, so learners must not bootstrap past it.

Observation (``Dict``):

* ``"features"`` (D,) float32: the table's encoder features of the current view
* ``"box"`` (4,) float32: target box XYXY normalised to [0, 1] (zeros = fully occluded)
* ``"action_mask"`` (7, A) int8: 1 where the action is allowed without clamping
  (stop always 1); use it or ignore it - clamped moves are legal
* ``"t"`` Discrete(T_max + 1): decisions taken so far
* ``"pose"`` (3,) float32, only with ``pose=True`` (:attr:`EnvConfig.pose`): the viewpoint's
  (x, y, z) in metres relative to the target (target at the origin, z the height above it)

``info``, the same keys and types at every step: ``view`` (index), ``xyz`` (metres),
``probs`` (K,) float32, ``visible`` (fraction; -1.0 where the table does not know it: a NaN
would break Gymnasium's determinism check, NaN != NaN), ``distance_m`` and ``steps`` flown so
far, ``context``, ``scene`` (table index), ``target`` (class index), ``t``, ``recognized`` and
``correct`` (argmax == target) of the current view, ``stopped`` (this step chose stop) and
``return`` (discounted, so far; at the end, the episode's).
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ..data.grid import N_TYPES, N_VIEWS, STOP, transitions, unflat_action, view_coords
from ..paths import tables_dir
from ..table import ObservationTable, load_table
from . import ENV_ID  # noqa: F401  (defined once, in uevavd.env; importable from here as before)
from .config import EnvConfig, make_config
from .render import render_frame
from .spaces import (  # noqa: F401 (F16_MAX: importable from here as before)
    F16_MAX,
    action_masks,
    action_space,
    check_forms,
    form_space,
    in_form,
)

#: ``info["visible"]`` where the data has no visible fraction (the real release).
NO_VISIBLE = -1.0


def integral_actions(action: Any) -> np.ndarray | None:
    """``action`` as an int64 array where it holds integers, or floats equal to integers (a
    library's float action buffer); None where it holds anything else. The single and the
    vector env read actions through this one rule."""
    a = np.asarray(action)
    if a.dtype.kind in "iu":
        return a.astype(np.int64, copy=False)
    try:
        f = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if not np.all(np.isfinite(f)) or not np.all(f == np.round(f)):
        return None
    return f.astype(np.int64)


def _int_option(options: dict[str, Any], name: str) -> int:
    """A reset option that must be an integer (a Python or numpy int, not a bool, not a float
    that would be truncated), as an int; anything else is a ValueError naming the option."""
    value = options[name]
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise ValueError(f"reset option {name}={value!r}: expected an integer")
    return int(value)


class AODEnv(gym.Env):
    """The AOD environment over an observation table, one episode at a time.

    ``AODEnv(table, split="train", config=None, *, contexts=None, **overrides)`` where
    ``overrides`` are :class:`EnvConfig` fields (``t_max=3``). Action: ``MultiDiscrete([7,
    A])`` = (type, range index); use :class:`uevavd.env.wrappers.DiscreteActions` for
    ``Discrete(7*A)``. ``reset(seed=..., options={"context": id or "scene": index,
    "view": index})``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}
    _spec: gym.envs.registration.EnvSpec | None = None

    @property
    def spec(self) -> gym.envs.registration.EnvSpec | None:
        return self._spec

    @spec.setter
    def spec(self, value: gym.envs.registration.EnvSpec | None) -> None:
        """``gym.make`` records its arguments here, and Minari's DataCollector stores them with
        a dataset: a table given as a folder of the table cache is recorded by its key, which
        every machine whose cache holds the table resolves; another folder stays (a warning
        says the spec then works on this machine only)."""
        given = (value.kwargs or {}).get("table") if value is not None else None
        if isinstance(given, ObservationTable):
            given = given.path
        if isinstance(given, str | os.PathLike) and os.fspath(given) != self.table.key:  # a folder
            key, folder = self.table.key, self.table.path
            if key and folder is not None and Path(folder).resolve() == (tables_dir() / key).resolve():
                value = dataclasses.replace(value, kwargs={**value.kwargs, "table": key})
            else:
                warnings.warn(f"{ENV_ID}'s spec names table {os.fspath(given)} by its path, which exists on this "
                              "machine only (a dataset recorded from this env keeps it): put the table in the table "
                              f"cache ({tables_dir()}) and pass table={key or '<its key>'!r} for a portable spec",
                              stacklevel=2)
        self._spec = value

    def __init__(
        self,
        table: ObservationTable | str | os.PathLike[str],
        split: str = "train",
        config: EnvConfig | dict[str, Any] | None = None,
        *,
        contexts: Any = None,
        render_mode: str | None = None,
        actions: str = "multi",
        observation: str = "dict",
        **overrides: Any,
    ) -> None:
        fields = {f.name for f in dataclasses.fields(EnvConfig)}
        unexpected = sorted(set(overrides) - fields)
        if unexpected:  # Python's own error for a bad keyword: clients (TorchRL's frameskip) retry without it
            near = difflib.get_close_matches(unexpected[0], sorted(fields), n=1)
            raise TypeError(f"AODEnv() got an unexpected keyword argument {unexpected[0]!r}"
                            + (f" (did you mean {near[0]!r}?)" if near else "") + "; its keywords are table, split, "
                            f"config, contexts, render_mode, actions, observation and the EnvConfig fields {sorted(fields)}")
        check_forms(actions, observation)
        self.actions, self.observation = actions, observation
        self.table = load_table(table)
        self.config = cfg = make_config(config, **overrides)
        self.split = split
        self.scenes = self.table.select(split, contexts, train_per_block=cfg.train_per_block,
                                        holdout_block=cfg.holdout_block)
        self._tr = transitions(cfg.max_range)
        self._mask_i8 = self._tr.mask.astype(np.int8)
        self._coords = view_coords(np.arange(N_VIEWS))  # (605, 3) float64 metres
        self._reco = cfg.recognized(self.table.true_class_probs())  # (S, 605) bool
        self._acc = self.table.argmax_correct()
        self.observation_space = form_space(self.table.feature_dim, cfg, actions=actions, observation=observation)
        self.action_space = action_space(cfg, actions=actions)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode={render_mode!r}: expected None or one of {self.metadata['render_modes']}")
        self.render_mode = render_mode
        self._path: list[int] = []
        self._scene = -1
        self._view = -1
        self._t = 0
        self._done = True

    # -- helpers ----------------------------------------------------------------------------
    def _obs(self) -> dict[str, Any] | np.ndarray:
        """The observation in the env's form (:data:`~uevavd.env.spaces.OBSERVATION_FORMS`):
        the Dict, its mask joint for ``actions="flat"``, or the flat vector (alone, or beside
        the mask)."""
        s, v = self._scene, self._view
        obs = {
            "features": np.array(self.table.features[s, v], dtype=np.float32),
            "box": np.array(self.table.boxes[s, v], dtype=np.float32),
            "action_mask": self._mask_i8[v].copy() if self.actions == "multi" else self._mask_i8[v].reshape(-1),
            "t": np.int64(self._t),  # as Discrete(t_max + 1).sample() gives it
        }
        if self.config.pose:
            obs["pose"] = self._coords[v].astype(np.float32)
        return in_form(obs, self.observation)

    def _info(self, stopped: bool = False) -> dict[str, Any]:
        """The same keys with the same types at every step (Minari's ``record_infos`` and
        Gymnasium's vector envs stack them): ``recognized`` / ``correct`` of the current view,
        ``stopped`` (this step chose stop), ``return`` (discounted, so far; the episode's at
        its end) and ``visible`` (-1.0 where the data has no visible fraction: not NaN, which
        is unequal to itself and fails Gymnasium's determinism check)."""
        s, v = self._scene, self._view
        visible = float(self.table.visible[s, v])
        return {
            "view": int(v),
            "xyz": self._coords[v].copy(),
            "probs": np.array(self.table.probs[s, v], dtype=np.float32),
            "visible": NO_VISIBLE if np.isnan(visible) else visible,
            "distance_m": float(self._dist),
            "steps": int(self._steps),
            "context": int(self.table.contexts[s]),
            "scene": int(s),
            "target": int(self.table.targets[s]),
            "t": int(self._t),
            "recognized": bool(self._reco[s, v]),
            "correct": bool(self._acc[s, v]),
            "stopped": bool(stopped),
            "return": float(self._return),
        }

    def _start_scene(self, options: dict[str, Any]) -> int:
        if "scene" in options and "context" in options:
            raise ValueError("reset options: give 'context' (id) or 'scene' (table index), not both")
        if "context" in options:
            c = _int_option(options, "context")
            hits = self.scenes[self.table.contexts[self.scenes] == c]
            if hits.size == 0:
                raise ValueError(
                    f"reset option context={c} is not among this env's contexts "
                    f"{sorted(int(x) for x in self.table.contexts[self.scenes])}"
                )
            return int(hits[0])
        if "scene" in options:
            s = _int_option(options, "scene")
            if s not in set(self.scenes.tolist()):
                raise ValueError(
                    f"reset option scene={s} is not a scene of split {self.split!r}: "
                    f"expected one of {self.scenes.tolist()}"
                )
            return s
        return int(self.scenes[self.np_random.integers(len(self.scenes))])

    # -- gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode at a random (context, view) of the split, or at the ones ``options``
        names (``{"context": 26, "view": 302}``); returns (observation, info)."""
        super().reset(seed=seed)
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"reset options {options!r}: expected a dict such as {{'context': 26, 'view': 302}}")
        options = dict(options or {})
        unknown = sorted(set(options) - {"context", "scene", "view"})
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}: expected 'context', 'scene', 'view'")
        self._scene = self._start_scene(options)
        if options.get("view") is not None:
            v = _int_option(options, "view")
            if not 0 <= v < N_VIEWS:
                raise ValueError(f"reset option view={v}: expected a view index 0..{N_VIEWS - 1}")
        else:
            fixed = self.config.start_view
            v = fixed if fixed is not None else int(self.np_random.integers(N_VIEWS))
        self._view = v
        self._path = [v]
        self._t = 0
        self._dist = 0.0
        self._steps = 0
        self._return = 0.0
        self._done = False
        return self._obs(), self._info()

    def step(self, action: Any):
        """Take one (type, range) action; returns Gymnasium's (observation, reward, terminated,
        truncated, info). Stop, or the T_max-th decision, ends the episode with the terminal reward."""
        if self._done:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        a = integral_actions(action)
        if a is None:
            a = np.zeros(0)
        if a.shape == () and 0 <= int(a) < N_TYPES * self.config.max_range:
            # the flat Discrete(7 * A) index (type-major, as grid.flat_action), for libraries
            # that turn a MultiDiscrete space into one categorical (TorchRL's GymWrapper)
            a = np.array(unflat_action(int(a), self.config.max_range))
        if a.shape != (2,):
            raise ValueError(
                f"action {action!r}: expected (type, range index) in MultiDiscrete([7, {self.config.max_range}]) "
                f"or a flat index 0..{N_TYPES * self.config.max_range - 1}"
            )
        a_type, a_range = int(a[0]), int(a[1])
        if not (0 <= a_type <= STOP and 0 <= a_range < self.config.max_range):
            raise ValueError(
                f"action ({a_type}, {a_range}) is outside MultiDiscrete([7, {self.config.max_range}]): "
                f"type 0..6 (stop = {STOP}), range index 0..{self.config.max_range - 1}"
            )
        cfg = self.config
        t = self._t
        if a_type == STOP:
            final, cost = True, 0.0
        else:
            prev = self._view
            self._view = int(self._tr.next_view[prev, a_type, a_range])
            self._path.append(self._view)
            self._steps += int(self._tr.steps[prev, a_type, a_range])
            self._dist += float(self._tr.metres[prev, a_type, a_range])
            final, cost = t == cfg.t_max - 1, cfg.move_cost(a_range)
        self._t = t + 1
        reward = cfg.reward(final, bool(self._reco[self._scene, self._view]), cost)
        self._return += cfg.gamma**t * reward
        self._done = final
        return self._obs(), float(reward), bool(final), False, self._info(stopped=a_type == STOP)

    def render(self) -> np.ndarray | None:
        """With ``render_mode="rgb_array"``: the current view (read from the table's dataset
        folder where it records one) beside a top-down map of the path so far, (256, 512, 3)
        uint8; see :mod:`uevavd.env.render`. Otherwise None."""
        if self.render_mode != "rgb_array":
            return None
        if not self._path:
            raise RuntimeError("render() before reset()")

        return render_frame(self.table, self._scene, self._path, self._t)

    def action_masks(self) -> np.ndarray:
        """Allowed actions at the current view for sb3-contrib's MaskablePPO, in the form of the
        action space: with ``actions="flat"`` the joint mask (7 x A,); in the MultiDiscrete form
        (7 + A,) bool, a type where any of its ranges is allowed, then every range (the joint
        (type, range) rule cannot be split per dimension; ``actions="flat"`` gives it exactly)."""
        if self._done:
            raise RuntimeError("action_masks() on a finished episode: call reset() first")
        return action_masks(self._tr.mask[self._view][None], self.actions)[0]

"""Exhaustive evaluation: every context of a split x every one of the 605 start views.

All ``n = contexts * 605`` episodes run in lockstep (no auto-reset, at most T_max
steps) through the same transition code as :class:`~uevavd.env.batched.BatchedAODEnv`.

Policy protocol (any object with these two methods)::

    policy.reset(n: int) -> None          # before the first step of n new episodes
    policy.act(obs: dict[str, Tensor]) -> (a_type LongTensor (n,), a_range LongTensor (n,))

``act`` is called once per step with the observations of *all* n episodes (keys as in
the batched env: features, box, mask, t, scene, view, plus ``"done"`` (n,) bool marking
episodes that already ended; their actions are ignored, so a policy may skip computing
them and return any valid action there, as :class:`~uevavd.policy.acting.GreedyPolicy`
does). A policy whose attribute ``needs_features`` is False gets ``features`` of width 0
(faster). Recurrent policies keep their hidden state per episode index between calls.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch

from ..atomic import atomic_write, json_text
from ..data.grid import N_VIEWS, STEP_M
from ..table import ObservationTable, load_table
from .batched import EnvTensors
from .config import EnvConfig, make_config
from .gate import StopGate, box_visible


class Policy(Protocol):
    """What :func:`evaluate_policy` and the baselines' registry (``register_baselines``) take:
    a policy that acts on batches of observations. An optional ``needs_features = False``
    attribute lets the harness skip the features (scripted rules and oracles)."""

    def reset(self, n: int) -> None:
        """Start ``n`` new episodes (clear any memory); called before the first ``act``."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Batched observations (the env's keys, each (n, ...) on one device) -> the actions'
        (type, range) indices, each (n,) int64 on that device."""


@dataclass
class EvalResult:
    """Per-episode results of an exhaustive evaluation; each array has shape (n,).

    ``ret`` float64 discounted return, ``recognized`` / ``correct`` / ``stopped`` bool,
    ``metres`` float64 and ``steps`` int64 actually flown, ``decisions`` int64 (1..T_max),
    ``scene`` int64 table scene index, ``context`` int64 id, ``target`` int64 class,
    ``start_view`` / ``final_view`` int64; ``trajectories`` (n, T_max + 1) int64 views
    visited, padded with -1 after the end; ``start_box`` bool, the observed target box at the
    start view is non-empty (:func:`uevavd.env.gate.box_visible`); ``start_recognized`` bool,
    the recognizer recognises the start view.
    """

    ret: np.ndarray
    recognized: np.ndarray
    correct: np.ndarray
    metres: np.ndarray
    steps: np.ndarray
    decisions: np.ndarray
    stopped: np.ndarray
    scene: np.ndarray
    context: np.ndarray
    target: np.ndarray
    start_view: np.ndarray
    final_view: np.ndarray
    trajectories: np.ndarray
    start_box: np.ndarray
    start_recognized: np.ndarray
    split: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    class_names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.ret)

    @staticmethod
    def _stats(r: EvalResult | Any, idx: np.ndarray | slice = slice(None)) -> dict[str, float]:
        box, moved = r.start_box[idx], r.trajectories[idx, 1] >= 0
        lost = ~r.recognized[idx]
        return {
            "episodes": int(np.size(r.ret[idx])),
            "mean_return": float(np.mean(r.ret[idx])),
            "accuracy": float(np.mean(r.correct[idx])),
            "recognition_rate": float(np.mean(r.recognized[idx])),
            "path_m": float(np.mean(r.metres[idx])),
            "path_steps": float(np.mean(r.steps[idx])),
            "stop_rate": float(np.mean(r.stopped[idx])),
            "steps_per_episode": float(np.mean(r.decisions[idx])),
            # the stopping diagnosis: where the target is in view at the start, does the policy fly
            # away from it, and does that lose a recognition the start view had?
            "box_start": float(np.mean(box)),
            "moved_if_box": float(np.mean(moved[box])) if box.any() else float("nan"),
            "box_lost": float(np.mean(box & moved & lost)),
            "reco_lost": float(np.mean(r.start_recognized[idx] & lost)),
            # where the room is: the mean return of the starts with the box in view, and of those without
            "box_return": float(np.mean(r.ret[idx][box])) if box.any() else float("nan"),
            "hidden_return": float(np.mean(r.ret[idx][~box])) if (~box).any() else float("nan"),
        }

    def summary(self) -> dict[str, float]:
        """Means over all episodes: mean_return, accuracy (argmax), recognition_rate (thre),
        path_m, path_steps, stop_rate (ended by stop, not T_max), steps_per_episode; and the
        stopping diagnosis: box_start (share of starts whose observed box is non-empty),
        moved_if_box (of those, the share where the first decision is a move; NaN without
        any), box_lost (share of all episodes that start with the box non-empty, move, and end
        unrecognised), reco_lost (share of all episodes that start recognised and end not); and
        box_return / hidden_return, the mean return of the starts whose observed box is non-empty
        / empty (NaN without any)."""
        return self._stats(self)

    def _grouped(self, key: np.ndarray, name: str, label: Any) -> Any:
        import pandas as pd

        rows = []
        for k in np.unique(key):
            rows.append({name: label(k), **self._stats(self, np.flatnonzero(key == k))})
        return pd.DataFrame(rows)

    def per_context(self) -> Any:
        """pandas DataFrame, one row per context (context, target, scene + the summary's columns)."""
        df = self._grouped(self.scene, "scene", int)
        _, first = np.unique(self.scene, return_index=True)  # same (sorted) order as the rows
        df.insert(0, "context", self.context[first].tolist())
        df.insert(1, "target", [self._target_name(int(k)) for k in self.target[first]])
        return df

    def per_target(self) -> Any:
        """pandas DataFrame, one row per target class (the summary's columns)."""
        return self._grouped(self.target, "target", lambda k: self._target_name(int(k)))

    def _target_name(self, k: int) -> str:
        return self.class_names[k] if k < len(self.class_names) else str(k)

    def to_dict(self) -> dict[str, Any]:
        """The split, the env config, the summary and the per-episode arrays as lists (JSON-ready)."""
        return {
            "split": self.split,
            "config": self.config,
            "summary": self.summary(),
            "per_context": self.per_context().to_dict(orient="records"),
            "per_target": self.per_target().to_dict(orient="records"),
        }

    def to_json(self, path: str | os.PathLike[str] | None = None) -> str:
        """Summary and breakdowns as JSON; written atomically to ``path`` when given."""
        text = json_text(self.to_dict())
        if path is not None:
            atomic_write(path, text)
        return text


@torch.no_grad()
def evaluate_policy(
    table: ObservationTable | str | os.PathLike[str] | EnvTensors,
    split: str,
    policy: Policy,
    config: EnvConfig | dict[str, Any] | None = None,
    *,
    device: str | torch.device = "cpu",
    contexts: Any = None,
) -> EvalResult:
    """Run ``policy`` greedily from every (context, start view) pair of ``split``.

    Starts are exhaustive, so ``config.start`` is ignored here; every other constant applies.

    ``table`` may also be a prepared :class:`~uevavd.env.batched.EnvTensors` (reuse it
    across epochs to skip the copy to the device; ``split``/``config``/``contexts`` then
    come from it). Returns an :class:`EvalResult`.
    """
    if isinstance(table, EnvTensors):
        tb = table
        cfg = tb.config
        _check_features_key(policy, tb.table_key)
    else:
        obs_table = load_table(table)
        _check_features_key(policy, obs_table.key)
        cfg = make_config(config)
        tb = EnvTensors(
            obs_table, split, cfg, device=device, contexts=contexts,
            with_features=getattr(policy, "needs_features", True),
        )
    dev = tb.device
    n_sc = len(tb.scenes)
    n = n_sc * N_VIEWS
    scene = torch.arange(n_sc, device=dev).repeat_interleave(N_VIEWS)
    view = torch.arange(N_VIEWS, device=dev).repeat(n_sc)
    start = view.clone()
    t = torch.zeros(n, dtype=torch.int64, device=dev)
    done = torch.zeros(n, dtype=torch.bool, device=dev)
    ret = torch.zeros(n, dtype=torch.float64, device=dev)
    steps = torch.zeros(n, dtype=torch.int64, device=dev)
    stopped = torch.zeros(n, dtype=torch.bool, device=dev)
    traj = torch.full((n, cfg.t_max + 1), -1, dtype=torch.int64, device=dev)
    traj[:, 0] = view
    policy.reset(n)
    for k in range(cfg.t_max):
        obs = tb.observe(scene, view, t)
        obs["done"] = done.clone()
        a_type, a_range = policy.act(obs)
        a_type, a_range = tb.check_actions(a_type, a_range, n)
        out = tb.transition(scene, view, t, a_type, a_range)
        live = ~done
        ret += torch.where(live, cfg.gamma**k * out["reward"], 0.0)
        steps += torch.where(live, out["steps"], 0)
        moved_view = torch.where(live, out["next_view"], view)
        traj[:, k + 1] = torch.where(live & ~out["stopped"], moved_view, -1)
        stopped |= live & out["stopped"]
        view = moved_view
        t = torch.where(live, t + 1, t)
        done = done | out["final"]
        if bool(done.all()):
            break
    reco = tb.reco[scene, view]
    acc = tb.acc[scene, view]
    start_box = box_visible(tb.boxes[scene, start])
    start_reco = tb.reco[scene, start]
    table_scene = tb.scenes[scene]

    def np_(x: torch.Tensor) -> np.ndarray:
        return x.cpu().numpy()

    return EvalResult(
        ret=np_(ret),
        recognized=np_(reco),
        correct=np_(acc),
        metres=np_(steps).astype(np.float64) * STEP_M,
        steps=np_(steps),
        decisions=np_(t),
        stopped=np_(stopped),
        scene=np_(table_scene),
        context=tb.contexts[np_(scene)],
        target=np_(tb.targets[scene]),
        start_view=np_(start),
        final_view=np_(view),
        trajectories=np_(traj),
        start_box=np_(start_box),
        start_recognized=np_(start_reco),
        split=tb.split,
        config=cfg.to_dict(),
        class_names=tuple(tb.class_names),
    )


def _check_features_key(policy: Policy, key: str) -> None:
    mine = getattr(policy, "features_key", None)
    if mine is not None and mine != key:
        raise ValueError(f"the policy reads the features of table {mine}, but the evaluation is on table {key}: "
                         "it would act on the other table's features; load it for this table (load_policy(run, "
                         "table=...), uevavd.load_run(run).policy(table=...) or load_policy_file(file, table=...))")


def evaluate_gated(table: ObservationTable | str | os.PathLike[str] | EnvTensors, split: str, policy: Policy,
                   config: EnvConfig | dict[str, Any] | None = None, *, device: str | torch.device = "cpu",
                   contexts: Any = None) -> tuple[EvalResult, EvalResult]:
    """``(result, gated)``: :func:`evaluate_policy` of ``policy`` and of the same policy behind
    the stop gate (:class:`~uevavd.env.gate.StopGate`), on the same episodes. The gated
    result's mean return is the diagnosis's ``gated_return``."""
    res = evaluate_policy(table, split, policy, config, device=device, contexts=contexts)
    gated = evaluate_policy(table, split, StopGate(policy), config, device=device, contexts=contexts)
    return res, gated


def stopping_summary(res: EvalResult, gated: EvalResult) -> dict[str, float]:
    """``res.summary()`` with ``gated_return``, the mean return behind the stop gate."""
    return {**res.summary(), "gated_return": float(np.mean(gated.ret))}

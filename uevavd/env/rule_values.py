"""The exact values of a scripted rule on a table, and what departing from it can gain.

A memoryless rule that reads only the observation (``pose_seek``, ``box_gate``) is
deterministic, so its return is exact on the table: dynamic programming over (scene, view,
steps left k), as :mod:`uevavd.env.oracle` does for the best policy, but following the rule::

    Q(v, k, a) = stop(v)                                    a = stop
               = term(next) - C*r                           k == 1
               = -xi2 - C*r + gamma * V(next, k - 1)        otherwise
    V(v, k)    = Q(v, k, rule(v, k))

with ``next = next_view[v, a, r]``. ``Q(v, k, a) - V(v, k)`` is the advantage of departing
once from the rule (take ``a`` now, follow the rule after): a label an observation-only policy
can learn, unlike the oracles' values, which assume what no observation holds.

:func:`departure_ceiling` bounds what any rule-anchored method can gain: the best return of a
policy that follows the rule but may depart from it ``departures`` times, choosing each
departure with the exact values of its context (a privileged diagnostic, like the oracles).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..data.grid import N_TYPES, N_VIEWS, STOP
from ..table import ObservationTable
from .batched import EnvTensors
from .config import EnvConfig, make_config
from .oracle import move_values


@dataclass(frozen=True)
class RuleSolution:
    """A rule's exact values on a split's scenes (``scenes``: table indices, as
    :class:`~uevavd.env.batched.EnvTensors` orders them) under ``config``. ``value``
    (S, T_max + 1, 605) float64: V(view, k), the rule's return with k decisions left (k = 0
    unused, zeros); ``q`` (S, T_max + 1, 605, 7, A) float64: the return of each (type, range)
    taken now and the rule followed after; ``rule_type`` / ``rule_range`` (S, T_max + 1, 605)
    int64: the rule's action with k decisions left; ``reco`` (S, 605) bool: where the
    recognizer recognises the view; ``next_view`` (605, 7, A): each action's next view."""

    scenes: np.ndarray
    config: EnvConfig
    value: np.ndarray
    q: np.ndarray
    rule_type: np.ndarray
    rule_range: np.ndarray
    reco: np.ndarray
    next_view: np.ndarray

    def advantage(self) -> np.ndarray:
        """``q - value``: what departing once from the rule with each action gains."""
        return self.q - self.value[..., None, None]


def rule_actions(tb: EnvTensors, rule: Any) -> tuple[np.ndarray, np.ndarray]:
    """The rule's (type, range) at every (scene, k decisions left, view) of ``tb``:
    (S, T_max + 1, 605) int64 each (k = 0 unused). The rule is asked once per k for every
    (scene, view) at once, reset before each ask: it must be memoryless, its action a function
    of the observation alone (``pose_seek``, ``box_gate``; not a policy with a state)."""
    cfg = tb.config
    s = len(tb.scenes)
    scene = torch.arange(s, device=tb.device).repeat_interleave(N_VIEWS)
    view = torch.arange(N_VIEWS, device=tb.device).repeat(s)
    types = np.zeros((s, cfg.t_max + 1, N_VIEWS), np.int64)
    ranges = np.zeros_like(types)
    for k in range(1, cfg.t_max + 1):
        obs = tb.observe(scene, view, torch.full_like(view, cfg.t_max - k))
        obs["done"] = torch.zeros_like(view, dtype=torch.bool)
        rule.reset(len(view))
        a_type, a_range = tb.check_actions(*rule.act(obs), len(view))
        types[:, k] = a_type.cpu().numpy().reshape(s, N_VIEWS)
        ranges[:, k] = a_range.cpu().numpy().reshape(s, N_VIEWS)
    return types, ranges


def rule_values(table: ObservationTable | EnvTensors, split: str, rule: Any,
                config: EnvConfig | dict | None = None) -> RuleSolution:
    """Solve the rule's values on ``split`` of ``table`` (or on a prepared
    :class:`~uevavd.env.batched.EnvTensors`, whose split and config then count): every
    (scene, view, k) at once. ``value[:, T_max, v]`` is the return
    :func:`~uevavd.env.evaluate.evaluate_policy` measures for the rule from start ``v``."""
    if isinstance(table, EnvTensors):
        tb = table
    else:
        tb = EnvTensors(table, split, make_config(config), with_features=getattr(rule, "needs_features", True))
    cfg = tb.config
    types, ranges = rule_actions(tb, rule)
    reco = tb.reco.cpu().numpy().astype(bool)
    nxt = tb.next_view.cpu().numpy()  # (V, 7, A)
    s = reco.shape[0]
    term = cfg.terminal_reward(reco).astype(np.float64)[:, :, None]  # (S, V, 1): stop, whatever its range
    value = np.zeros((s, cfg.t_max + 1, N_VIEWS))
    q = np.zeros((s, cfg.t_max + 1, N_VIEWS, N_TYPES, cfg.max_range))
    rows, cols = np.arange(s)[:, None], np.arange(N_VIEWS)[None, :]
    for k in range(1, cfg.t_max + 1):
        q[:, k, :, :STOP] = move_values(cfg, reco, nxt, value[:, k - 1], k)
        q[:, k, :, STOP] = term
        value[:, k] = q[rows, k, cols, types[:, k], ranges[:, k]]
    return RuleSolution(tb.scenes.cpu().numpy(), cfg, value, q, types, ranges, reco, nxt)


@dataclass(frozen=True)
class DepartureLayer:
    """The best use of ``d`` departures from the rule, at every (scene, k decisions left, view):
    ``value`` (S, T_max + 1, 605) float64 the return with ``d`` departures left; ``depart``
    (S, T_max + 1, 605) bool whether to depart now (where following the rule is not as good),
    with ``a_type`` / ``a_range`` the departure's action (stop: range 0)."""

    value: np.ndarray
    depart: np.ndarray
    a_type: np.ndarray
    a_range: np.ndarray


def departure_layers(sol: RuleSolution, departures: int = 1) -> list[DepartureLayer]:
    """``[layer with 1 departure left, ..., with departures left]`` (:class:`DepartureLayer`):
    the dynamic programme of :func:`departure_ceiling`, with the choices that reach it (a tie
    follows the rule; among departures, stop, then the lowest move index)."""
    if isinstance(departures, bool) or not isinstance(departures, int) or departures < 0:
        raise ValueError(f"departures={departures!r}: expected an integer >= 0")
    cfg = sol.config
    term = cfg.terminal_reward(sol.reco).astype(np.float64)  # (S, V)
    rows, cols = np.arange(len(sol.scenes))[:, None], np.arange(N_VIEWS)[None, :]
    layers: list[DepartureLayer] = []
    fewer = sol.value  # with one departure fewer left (none: the rule's values)
    for _ in range(departures):
        more = np.zeros_like(fewer)
        depart = np.zeros(more.shape, bool)
        a_type = np.full(more.shape, STOP, np.int64)
        a_range = np.zeros(more.shape, np.int64)
        for k in range(1, cfg.t_max + 1):
            stay = move_values(cfg, sol.reco, sol.next_view, more[:, k - 1], k)  # the rule's move, as many left
            moves = move_values(cfg, sol.reco, sol.next_view, fewer[:, k - 1], k).reshape(*term.shape, -1)
            t, r = sol.rule_type[:, k], sol.rule_range[:, k]  # any move, one fewer left
            follow = np.where(t == STOP, term, stay[rows, cols, np.minimum(t, STOP - 1), r])
            best = moves.argmax(-1)
            best_move = np.take_along_axis(moves, best[..., None], -1)[..., 0]
            more[:, k] = np.maximum.reduce([follow, term, best_move])
            depart[:, k] = more[:, k] > follow
            by_move = depart[:, k] & (best_move > term)
            a_type[:, k] = np.where(by_move, best // cfg.max_range, STOP)
            a_range[:, k] = np.where(by_move, best % cfg.max_range, 0)
        layers.append(DepartureLayer(more, depart, a_type, a_range))
        fewer = more
    return layers


def departure_ceiling(sol: RuleSolution, departures: int = 1) -> np.ndarray:
    """(S, 605) float64: from every start, the best return of a policy that follows the rule
    but may depart from it up to ``departures`` times (any action, stop included), each
    departure chosen with the context's exact values (privileged: it bounds what a
    rule-anchored method can gain; 0 departures is the rule's own return, ``T_max`` the
    oracle's). :class:`DepartureCeilingPolicy` flies it."""
    layers = departure_layers(sol, departures)
    return (layers[-1].value if layers else sol.value)[:, sol.config.t_max]


class DepartureCeilingPolicy:
    """The departure ceiling as a policy under the evaluation protocol (privileged, like the
    oracles: reads ``obs["scene"]``, ``obs["view"]`` and ``obs["t"]``): ``rule`` (memoryless,
    :func:`rule_actions`) followed from every start, departed from at most ``departures`` times
    where the context's exact values say a departure gains (:func:`departure_layers`). Its
    return from a start is :func:`departure_ceiling`'s. The values are solved for the scenes it
    is first asked about, by their split, and kept."""

    needs_features = False

    def __init__(self, table: ObservationTable, config: EnvConfig | dict | None, rule: Any,
                 departures: int = 1) -> None:
        self.table, self.rule, self.departures = table, rule, int(departures)
        self.config = make_config(config)
        # the values do not depend on which training contexts a run keeps: every scene asked about is solved
        self._solve_cfg = replace(self.config, train_per_block=0, holdout_block=0)
        shape = (len(table), self.config.t_max + 1, N_VIEWS)
        self._solved = np.zeros(len(table), bool)
        self._rule = (np.zeros(shape, np.int64), np.zeros(shape, np.int64))
        self._layers = [(np.zeros(shape, bool), np.zeros(shape, np.int64), np.zeros(shape, np.int64))
                        for _ in range(self.departures)]
        self._tensors: tuple | None = None
        self._left: torch.Tensor | None = None

    def _solve(self, scenes: np.ndarray) -> None:
        todo = np.unique(scenes[~self._solved[scenes]])
        splits = np.asarray(self.table.splits)
        for split in sorted(set(splits[todo])):
            pick = todo[splits[todo] == split]
            tb = EnvTensors(self.table, split, self._solve_cfg, contexts=self.table.contexts[pick],
                            with_features=getattr(self.rule, "needs_features", True))
            sol = rule_values(tb, split, self.rule)
            self._rule[0][sol.scenes], self._rule[1][sol.scenes] = sol.rule_type, sol.rule_range
            for (depart, a_type, a_range), layer in zip(self._layers, departure_layers(sol, self.departures),
                                                        strict=True):
                depart[sol.scenes], a_type[sol.scenes], a_range[sol.scenes] = layer.depart, layer.a_type, layer.a_range
            self._solved[sol.scenes] = True
        self._tensors = None

    def reset(self, n: int) -> None:
        """Every episode starts with all its departures left."""
        self._left = None

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The rule's action, or the departure its context's exact values choose."""
        view, t, scene = obs["view"], obs["t"], obs["scene"]
        here = scene.cpu().numpy()
        if not self._solved[here].all():
            self._solve(here)
        if self._tensors is None or self._tensors[0].device != view.device:
            self._tensors = tuple(torch.as_tensor(a, device=view.device) for a in (*self._rule, *(
                x for layer in self._layers for x in layer)))
        rule_type, rule_range, *per_layer = self._tensors
        full = torch.full_like(t, self.departures)
        self._left = full if self._left is None else torch.where(t == 0, full, self._left)
        k = (self.config.t_max - t).clamp(1, self.config.t_max)
        a_type, a_range = rule_type[scene, k, view], rule_range[scene, k, view]
        departed = torch.zeros_like(t, dtype=torch.bool)
        for d in range(1, self.departures + 1):
            depart, d_type, d_range = per_layer[3 * (d - 1):3 * d]
            now = (self._left == d) & depart[scene, k, view]
            a_type = torch.where(now, d_type[scene, k, view], a_type)
            a_range = torch.where(now, d_range[scene, k, view], a_range)
            departed |= now
        self._left = self._left - departed.long()
        return a_type, a_range

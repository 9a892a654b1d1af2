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

from dataclasses import dataclass
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


def departure_ceiling(sol: RuleSolution, departures: int = 1) -> np.ndarray:
    """(S, 605) float64: from every start, the best return of a policy that follows the rule
    but may depart from it up to ``departures`` times (any action, stop included), each
    departure chosen with the context's exact values (privileged: it bounds what a
    rule-anchored method can gain; 0 departures is the rule's own return, ``T_max`` the
    oracle's)."""
    if isinstance(departures, bool) or not isinstance(departures, int) or departures < 0:
        raise ValueError(f"departures={departures!r}: expected an integer >= 0")
    cfg = sol.config
    term = cfg.terminal_reward(sol.reco).astype(np.float64)  # (S, V)
    rows, cols = np.arange(len(sol.scenes))[:, None], np.arange(N_VIEWS)[None, :]
    fewer = sol.value  # with one departure fewer left (none: the rule's values)
    for _ in range(departures):
        more = np.zeros_like(fewer)
        for k in range(1, cfg.t_max + 1):
            stay = move_values(cfg, sol.reco, sol.next_view, more[:, k - 1], k)  # the rule's move, as many left
            depart = move_values(cfg, sol.reco, sol.next_view, fewer[:, k - 1], k)  # any move, one fewer left
            t, r = sol.rule_type[:, k], sol.rule_range[:, k]
            follow = np.where(t == STOP, term, stay[rows, cols, np.minimum(t, STOP - 1), r])
            more[:, k] = np.maximum.reduce([follow, term, depart.reshape(*term.shape, -1).max(-1)])
        fewer = more
    return fewer[:, cfg.t_max]

"""The oracle: the best achievable return given the classifier table (an upper bound).

Dynamic programming over (scene, view, steps left k), for every scene of the table::

    stop(v)       = +xi1 if reco[v] else -xi1
    move(v, a, r) = term(next) - C*r                         if k == 1
                  = -xi2 - C*r + gamma * V(next, k - 1)       otherwise
    V(v, k)       = max(stop(v), max_{a, r} move(v, a, r))

with ``term = stop`` and ``next = next_view[v, a, r]`` (clamped). An episode starting at
``v`` has ``k = T_max`` steps left, so ``V(v, T_max)`` is the best return from ``v``; no
policy can beat it, because it sees the true class's probability at every view. Ties go
to stop, then to the lowest (type, range) index.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..data.grid import N_TYPES, STOP, transitions
from ..table import ObservationTable
from .config import EnvConfig, make_config


@dataclass(frozen=True)
class OracleSolution:
    """``value`` (S, T_max + 1, 605) float64: V(view, k) (k = 0 unused, zeros);
    ``q`` (S, T_max + 1, 605, 7, A) float64 action values (None unless asked for:
    it is 28x the size of ``value``); ``best_type`` / ``best_range``
    (S, T_max + 1, 605) int64: the optimal action with k steps left."""

    value: np.ndarray
    q: np.ndarray | None
    best_type: np.ndarray
    best_range: np.ndarray


def oracle_values(
    table: ObservationTable, config: EnvConfig | dict | None = None, *, with_q: bool = False
) -> OracleSolution:
    """Solve the DP for every scene of ``table`` (vectorised over scenes and views)."""
    cfg = make_config(config)
    return solve_oracle(cfg.recognized(table.true_class_probs()), cfg, with_q=with_q)


def move_values(config: EnvConfig, reco: np.ndarray, next_view: np.ndarray, after: np.ndarray, k: int) -> np.ndarray:
    """(S, V, 6, A): the return of every move with ``k`` decisions left, ``after`` (S, V)
    being the value of the view it reaches with ``k - 1`` left (unread where ``k == 1``: the
    move ends the episode, recognised or not at its view). The recursion of the oracle, of a
    rule's values and of their mixtures (:mod:`uevavd.env.rule_values`)."""
    nxt = next_view[:, :STOP, :]  # (V, 6, A)
    cost = config.move_cost(np.arange(config.max_range, dtype=np.float64))  # (A,)
    if k == 1:  # the last decision: every move ends the episode
        return config.reward(True, reco[:, nxt], cost)
    return config.reward(False, False, cost) + config.gamma * after[:, nxt]


def solve_oracle(reco: np.ndarray, config: EnvConfig, *, with_q: bool = False) -> OracleSolution:
    """The DP of :func:`oracle_values` on ``reco`` (S, 605) bool, whether the recognizer
    recognises each view of each scene."""
    cfg = config
    tr = transitions(cfg.max_range)
    reco = np.asarray(reco, bool)
    s, v = reco.shape
    a = cfg.max_range
    term = cfg.terminal_reward(reco).astype(np.float64)  # (S, V)
    value = np.zeros((s, cfg.t_max + 1, v))
    q = np.zeros((s, cfg.t_max + 1, v, N_TYPES, a)) if with_q else None
    best_type = np.zeros((s, cfg.t_max + 1, v), np.int64)
    best_range = np.zeros((s, cfg.t_max + 1, v), np.int64)
    for k in range(1, cfg.t_max + 1):
        moves = move_values(cfg, reco, tr.next_view, value[:, k - 1], k)  # (S, V, 6, A)
        if q is not None:
            q[:, k, :, :STOP, :] = moves
            q[:, k, :, STOP, :] = term[:, :, None]
        flat = moves.reshape(s, v, -1)
        i = flat.argmax(-1)
        best_move = np.take_along_axis(flat, i[..., None], -1)[..., 0]
        stop_better = term >= best_move
        value[:, k] = np.where(stop_better, term, best_move)
        best_type[:, k] = np.where(stop_better, STOP, i // a)
        best_range[:, k] = np.where(stop_better, 0, i % a)
    return OracleSolution(value, q, best_type, best_range)


def flight_pays(reco: np.ndarray, config: EnvConfig) -> np.ndarray:
    """(T_max, S, 605) bool: whether, with k + 1 decisions left (index k), the best return
    reachable from each view beats stopping there (the oracle's value above the stop
    reward; ``reco`` (S, 605) as in :func:`solve_oracle`)."""
    sol = solve_oracle(reco, config)
    term = config.terminal_reward(np.asarray(reco, bool)).astype(np.float64)
    return np.moveaxis(sol.value[:, 1:], 1, 0) > term[None]


class OraclePolicy:
    """Acts optimally given the scene, view and step index of each episode (reads
    ``obs["scene"]``, ``obs["view"]``, ``obs["t"]``; never features). Build it on the same
    table and config the evaluation uses."""

    needs_features = False

    def __init__(self, table: ObservationTable, config: EnvConfig | dict | None = None) -> None:
        self.config = make_config(config)
        self.solution = oracle_values(table, self.config)
        self._dev: torch.device | None = None

    def _on(self, dev: torch.device) -> None:
        if self._dev != dev:
            self._type = torch.as_tensor(self.solution.best_type, device=dev)
            self._range = torch.as_tensor(self.solution.best_range, device=dev)
            self._dev = dev

    def reset(self, n: int) -> None:
        """Nothing to clear: the oracle reads the step index from the observation."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The DP's optimal action for each episode's (scene, view, steps left)."""
        view = obs["view"]
        self._on(view.device)
        k = (self.config.t_max - obs["t"]).clamp(1, self.config.t_max)
        return self._type[obs["scene"], k, view], self._range[obs["scene"], k, view]

    def value(self, scene: int, view: int) -> float:
        """The optimal return from ``view`` of table scene ``scene`` at t = 0."""
        return float(self.solution.value[scene, self.config.t_max, view])

"""The visibility oracle: a baseline that knows how much of the target every view shows,
but not what the classifier says about any view.

From each start view it flies the cheapest path to the reachable view that shows the most
of the target, then stops. It is what a policy could reach by *finding* the target alone
(no image-only policy sees the visible fraction, so it is not an upper bound either way: a
more visible view need not be recognised, and a less visible one may be). Exactly:

* reachable: views reached from the start with at most ``T_max`` moves (the last of them
  may be the ``T_max``-th decision, which ends the episode without a stop);
* a path's cost: Eq. 2's movement costs, ``xi2 + C * r`` for each move of range ``r``;
* the goal: the reachable view with the largest visible fraction; ties go to the cheapest
  path to it (costs compared to 1e-9), then to the fewest moves, then to the lowest view
  index; the path to it: the cheapest, then fewest moves, then at each step back from the
  goal the lowest (action type, range, previous view);
* it flies that path and stops at the goal (no stop when the path has ``T_max`` moves; the
  start itself is the goal when nothing reachable shows more).

The paths do not depend on the scene (only the grid and the costs), so they are solved
once per config; the goal is chosen per scene from the table's ``visible`` array. Tables
without visible fractions (the real release) cannot have this baseline.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from ..data.grid import N_VIEWS, STOP, transitions
from ..table import ObservationTable
from .config import EnvConfig, make_config

_COST_DECIMALS = 9


def cheapest_paths(config: EnvConfig) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Searched once per (max_range, xi2, C): see :func:`_cheapest_paths`."""
    return _cheapest_paths(config.max_range, config.t_max, float(config.xi2), float(config.C))


def _cheapest_paths(max_range: int, t_max: int, xi2: float, c: float):
    """``(cost, moves, preds, edges)``: ``cost`` (V, V) float64 the cheapest cost from a start
    (row) to a view (column) within ``T_max`` moves (inf: unreachable), ``moves`` (V, V) int64
    the number of moves of that path, ``preds[k - 1]`` (V, V) int64 the last edge of the
    cheapest path with exactly k moves, ``edges`` (E, 4) int64 rows (from view, type, range
    index, to view), sorted by (to, type, range, from). The answer for ``T_max`` = k is the
    first k moves' search of any longer one: a search runs once per (range, costs), as far as
    asked so far (DAgger's labels ask for every T_max up to the env's)."""
    search = _search(max_range, xi2, c)
    search.extend(t_max)
    return search.best[t_max], search.moves[t_max], search.preds[:t_max], search.edges


class _Search:
    """The cheapest-path search of :func:`_cheapest_paths` over moves 1, 2, ...: ``best[k]``,
    ``moves[k]`` within k moves, ``preds[k - 1]`` of exactly k moves (all read-only)."""

    def __init__(self, max_range: int, xi2: float, c: float) -> None:
        tr = transitions(max_range)
        u, t, r = np.meshgrid(np.arange(N_VIEWS), np.arange(STOP), np.arange(max_range), indexing="ij")
        u, t, r = u.ravel(), t.ravel(), r.ravel()
        dst = tr.next_view[u, t, r]
        order = np.lexsort((u, r, t, dst))
        self.edges = np.stack([u[order], t[order], r[order], dst[order]], axis=1)
        rule = EnvConfig(max_range=max_range, xi2=xi2, C=c)
        self.step_cost = -rule.reward(False, False, rule.move_cost(self.edges[:, 2]))  # xi2 + C r: Eq. 2's
        self.starts = np.flatnonzero(np.r_[True, self.edges[1:, 3] != self.edges[:-1, 3]])  # first edge per 'to'
        self.counts = np.diff(np.r_[self.starts, len(self.edges)])
        self.index = np.arange(len(self.edges))
        self.prev = np.full((N_VIEWS, N_VIEWS), np.inf)  # the cheapest cost with exactly k moves
        np.fill_diagonal(self.prev, 0.0)
        self.best, self.moves, self.preds = [self.prev.copy()], [np.zeros((N_VIEWS, N_VIEWS), np.int64)], []
        self.edges.setflags(write=False)

    def extend(self, t_max: int) -> None:
        edges, n_edges = self.edges, len(self.edges)
        while len(self.preds) < t_max:
            k = len(self.preds) + 1
            cand = self.prev[:, edges[:, 0]] + self.step_cost  # (V starts, E)
            cost_k = np.minimum.reduceat(cand, self.starts, axis=1)  # (V, V): every view is some edge's 'to'
            hit = np.where(cand == np.repeat(cost_k, self.counts, axis=1), self.index, n_edges)
            self.preds.append(np.minimum.reduceat(hit, self.starts, axis=1))
            best = self.best[-1]
            better = np.round(cost_k, _COST_DECIMALS) < np.round(best, _COST_DECIMALS)
            self.best.append(np.where(better, cost_k, best))
            self.moves.append(np.where(better, k, self.moves[-1]))
            for arr in (self.preds[-1], self.best[-1], self.moves[-1]):
                arr.setflags(write=False)
            self.prev = cost_k


@functools.lru_cache(maxsize=8)
def _search(max_range: int, xi2: float, c: float) -> _Search:
    return _Search(max_range, xi2, c)


def visibility_plans(visible: np.ndarray, config: EnvConfig | dict | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a_type, a_range, goal)`` for every (scene, start view): ``a_type`` / ``a_range``
    (S, V, T_max) int64 the action at each decision, ``goal`` (S, V) int64 the goal view.
    ``visible``: (S, V) visible fractions; NaN is an error (the baseline needs them)."""
    cfg = make_config(config)
    vis = np.asarray(visible, np.float64)
    if vis.ndim != 2 or vis.shape[1] != N_VIEWS:
        raise ValueError(f"visible: expected (scenes, {N_VIEWS}), got {vis.shape}")
    if np.isnan(vis).any():
        raise ValueError("the visibility oracle needs every view's visible fraction; this table has NaN "
                         "(a dataset without visible fractions, such as the real release)")
    cost, moves, preds, edges = cheapest_paths(cfg)
    reach = np.isfinite(cost)
    rcost = np.round(np.where(reach, cost, np.inf), _COST_DECIMALS)
    s_n = len(vis)
    a_type = np.full((s_n, N_VIEWS, cfg.t_max), STOP, np.int64)
    a_range = np.zeros((s_n, N_VIEWS, cfg.t_max), np.int64)
    goals = np.zeros((s_n, N_VIEWS), np.int64)
    starts = np.arange(N_VIEWS)
    for s in range(s_n):
        score = np.where(reach, vis[s][None, :], -np.inf)
        cand = score == score.max(1, keepdims=True)
        c = np.where(cand, rcost, np.inf)
        cand &= c == c.min(1, keepdims=True)
        m = np.where(cand, moves, np.iinfo(np.int64).max)
        cand &= m == m.min(1, keepdims=True)
        goal = cand.argmax(1)  # the lowest view index among the ties
        goals[s] = goal
        k = moves[starts, goal]
        view = goal.copy()
        for j in range(int(k.max()), 0, -1):
            on = k >= j  # episodes whose path has a j-th move
            e = preds[j - 1][starts[on], view[on]]
            a_type[s, on, j - 1] = edges[e, 1]
            a_range[s, on, j - 1] = edges[e, 2]
            view[on] = edges[e, 0]
        if not np.array_equal(view, starts):
            raise AssertionError("visibility oracle: a reconstructed path does not lead back to its start")
    return a_type, a_range, goals


class VisibilityOraclePolicy:
    """The visibility oracle under the evaluation protocol (reads ``obs["scene"]``,
    ``obs["view"]`` and ``obs["t"]``; never features). Build it on the table and config the
    evaluation uses."""

    needs_features = False

    def __init__(self, table: ObservationTable, config: EnvConfig | dict | None = None) -> None:
        self.config = make_config(config)
        self.a_type, self.a_range, self.goal = visibility_plans(table.visible, self.config)
        self._dev: torch.device | None = None
        self._start: torch.Tensor | None = None

    def reset(self, n: int) -> None:
        """Forget the episodes' starts: the next act plans from the views it is given."""
        self._start = None

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The next action of each episode's plan from its start (:func:`visibility_plans`)."""
        view, t, scene = obs["view"], obs["t"], obs["scene"]
        if self._dev != view.device:
            self._type_t = torch.as_tensor(self.a_type, device=view.device)
            self._range_t = torch.as_tensor(self.a_range, device=view.device)
            self._dev = view.device
        self._start = view.clone() if self._start is None else torch.where(t == 0, view, self._start)
        k = t.clamp(0, self.config.t_max - 1)
        return self._type_t[scene, self._start, k], self._range_t[scene, self._start, k]

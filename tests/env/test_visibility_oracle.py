"""The visibility oracle: flies the cheapest path to the most visible reachable view, then
stops; checked against brute force over every action sequence."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from uevavd.data.grid import N_VIEWS, STOP, transitions
from uevavd.env.config import make_config
from uevavd.env.evaluate import evaluate_policy
from uevavd.env.visibility_oracle import VisibilityOraclePolicy, visibility_plans


def _brute(vis: np.ndarray, start: int, cfg) -> tuple[float, float, int, int]:
    """(best visible, cheapest cost to it, fewest moves, lowest goal view) over every
    sequence of up to t_max moves."""
    tr = transitions(cfg.max_range)
    best = (-1.0, 0.0, 0, 0)
    moves = [(t, r) for t in range(STOP) for r in range(cfg.max_range)]
    for k in range(cfg.t_max + 1):
        for seq in itertools.product(moves, repeat=k):
            v, cost = start, 0.0
            for t, r in seq:
                v = int(tr.next_view[v, t, r])
                cost += cfg.xi2 + cfg.C * (r + 1)
            key = (vis[v], -round(cost, 9), -k, -v)
            if key > (best[0], -round(best[1], 9), -best[2], -best[3]):
                best = (float(vis[v]), cost, k, v)
    return best


def test_plans_reach_the_most_visible_reachable_view_at_the_least_cost():
    cfg = make_config({"t_max": 2})
    rng = np.random.default_rng(3)
    vis = rng.integers(0, 6, size=(2, N_VIEWS)) / 5.0  # many ties, as at visible = 1.0
    a_type, a_range, goal = visibility_plans(vis, cfg)
    tr = transitions(cfg.max_range)
    for s in range(2):
        for start in rng.choice(N_VIEWS, 12, replace=False):
            want_vis, want_cost, want_k, want_goal = _brute(vis[s], int(start), cfg)
            v, cost, k = int(start), 0.0, 0
            for j in range(cfg.t_max):
                if a_type[s, start, j] == STOP:
                    break
                v = int(tr.next_view[v, a_type[s, start, j], a_range[s, start, j]])
                cost += cfg.xi2 + cfg.C * (a_range[s, start, j] + 1)
                k += 1
            assert v == goal[s, start] == want_goal
            assert vis[s, v] == want_vis and cost == pytest.approx(want_cost) and k == want_k


def test_evaluated_like_every_policy_it_ends_on_its_goal(table):
    cfg = make_config(None)
    policy = VisibilityOraclePolicy(table, cfg)
    res = evaluate_policy(table, "train", policy, cfg)
    assert np.array_equal(res.final_view, policy.goal[res.scene, res.start_view])
    moved = res.final_view != res.start_view
    assert moved.any() and (res.steps[~moved] == 0).all()
    vis = table.visible[res.scene]
    assert (vis[np.arange(len(res)), res.final_view] >= vis[np.arange(len(res)), res.start_view]).all()
    # it stops at its goal unless the path used every decision
    assert (res.stopped | (res.decisions == cfg.t_max)).all()


def test_needs_visible_fractions():
    vis = np.full((1, N_VIEWS), np.nan)
    with pytest.raises(ValueError, match="visible fraction"):
        visibility_plans(vis, None)

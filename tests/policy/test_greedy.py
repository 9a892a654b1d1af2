"""GreedyPolicy's fast paths (cached input gates, live rows only) act exactly like nn.GRU on
gathered features for every episode."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from uevavd.data.grid import N_VIEWS, STOP
from uevavd.env.evaluate import evaluate_policy
from uevavd.policy.acting import GreedyPolicy
from uevavd.policy.heads import build_branching_dueling, build_joint_dueling
from uevavd.policy.network import QNetwork
from uevavd.state.gru import build_gru
from uevavd.state.single_view import build_single_view


class AllRowsPolicy:
    """The reference: ``net.step`` on the gathered features of all n episodes every step,
    done or not (GreedyPolicy's generic path before it skipped ended episodes)."""

    needs_features = True

    def __init__(self, net: QNetwork) -> None:
        self.net = net.eval()

    def reset(self, n: int) -> None:
        self.hidden = self.net.initial_hidden(n)

    @torch.no_grad()
    def act(self, obs):
        hidden = self.hidden * (obs["t"] != 0)[:, None].float()
        q, self.hidden = self.net.step(obs["features"], obs["box"], hidden)
        return self.net.head.greedy(q, obs["mask"])


def stopping_net(kind: str) -> QNetwork:
    """A small random network whose stop advantage is raised so that episodes end after
    1, 2, ... or T_max decisions (the bias was chosen by looking at the spread)."""
    torch.manual_seed(0)
    if kind == "gru":
        net = QNetwork(build_gru(feature_dim=8, input_dim=24, box_dim=8, state_dim=16),
                       build_branching_dueling(state_dim=16, hidden=16))
        with torch.no_grad():
            net.head.adv_type[2].bias[STOP] += 0.25
    else:
        net = QNetwork(build_single_view(feature_dim=8, input_dim=24, box_dim=8, state_dim=16),
                       build_joint_dueling(state_dim=16, hidden=16))
        with torch.no_grad():
            net.head.advantage[2].bias[STOP * 4] += 0.2
    return net


def assert_same(a, b) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)


@pytest.mark.parametrize("kind", ["gru", "single_view"])
def test_fast_paths_act_like_the_all_rows_reference(table, kind):
    net = stopping_net(kind)
    features = torch.from_numpy(table.features)
    ref = evaluate_policy(table, "hard", AllRowsPolicy(net))
    # episodes end at different steps, so skipping ended rows is exercised
    assert len(np.unique(ref.decisions)) >= 4, np.bincount(ref.decisions)
    assert ref.stopped.any() and not ref.stopped.all()
    fast = GreedyPolicy(net, features=features)
    assert not fast.needs_features and fast._gru == (kind == "gru")
    assert_same(evaluate_policy(table, "hard", fast), ref)
    assert_same(evaluate_policy(table, "hard", GreedyPolicy(net)), ref)  # gathered features
    # the cache survives a second evaluation with the same policy object
    assert_same(evaluate_policy(table, "hard", fast), ref)


def test_epsilon_greedy_draws_do_not_depend_on_the_path(table):
    net = stopping_net("gru")
    features = torch.from_numpy(table.features)
    a = evaluate_policy(table, "hard", GreedyPolicy(net, epsilon=0.3, seed=5, features=features))
    b = evaluate_policy(table, "hard", GreedyPolicy(net, epsilon=0.3, seed=5))
    assert_same(a, b)


def test_cached_gates_follow_the_observed_box(table):
    """A (scene, view) seen again with another box is recomputed, not read stale."""
    net = stopping_net("gru")
    fast = GreedyPolicy(net, features=torch.from_numpy(table.features))
    slow = GreedyPolicy(net)
    n = 64
    g = torch.Generator().manual_seed(1)
    scene = torch.randint(0, len(table), (n,), generator=g)
    view = torch.randint(0, N_VIEWS, (n,), generator=g)
    for pol in (fast, slow):
        pol.reset(n)
    for step in range(3):
        boxes = torch.rand(n, 4, generator=g)  # new boxes at the same views every step
        obs = {
            "features": torch.from_numpy(table.features)[scene, view].float(), "box": boxes,
            "mask": torch.ones(n, 7, 4, dtype=torch.bool), "t": torch.full((n,), step),
            "scene": scene, "view": view,
        }
        for x, y in zip(fast.act(obs), slow.act(obs), strict=True):
            assert torch.equal(x, y)
        assert torch.equal(fast.hidden, slow.hidden)

"""A scripted rule's exact values on a table (uevavd.env.rule_values), against rollouts through
the evaluation: the rule's return from every start, each first action followed by the rule, and
the ceiling of departing from it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.data.grid import N_VIEWS, STOP
from uevavd.env import EnvConfig, evaluate_policy
from uevavd.env.baselines import BoxGatePolicy, PoseSeekPolicy, evaluate_beside_baselines
from uevavd.env.oracle import oracle_values
from uevavd.env.rule_values import DepartureCeilingPolicy, departure_ceiling, rule_values
from uevavd.table import ObservationTable

CFG = EnvConfig(t_max=4)


@pytest.fixture(scope="module")
def table() -> ObservationTable:
    """Boxes empty on about 60 % of the views (the rules fly there), probabilities peaked."""
    rng = np.random.default_rng(3)
    n = 4
    logits = rng.normal(0, 2.0, (n, N_VIEWS, 5))
    probs = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    lo = rng.uniform(0, 0.5, (n, N_VIEWS, 2))
    boxes = np.concatenate([lo, lo + rng.uniform(0.05, 0.5, lo.shape)], -1)
    boxes[rng.random((n, N_VIEWS)) < 0.6] = 0.0
    return ObservationTable.from_arrays(rng.normal(size=(n, N_VIEWS, 4)), probs, boxes.astype(np.float32),
                                        scenes=[f"{i + 1:03d}" for i in range(n)], contexts=list(range(1, n + 1)),
                                        targets=[i % 5 for i in range(n)], splits=["train", "train", "hard", "hard"])


class FirstThenRule:
    """Takes (a_type, a_range) at the first decision, then follows ``rule``."""

    needs_features = False

    def __init__(self, rule, a_type: int, a_range: int) -> None:
        self.rule, self.a = rule, (a_type, a_range)

    def reset(self, n: int) -> None:
        self.rule.reset(n)

    def act(self, obs):
        a_type, a_range = (torch.as_tensor(x) for x in self.rule.act(obs))
        first = obs["t"] == 0
        return torch.where(first, self.a[0], a_type), torch.where(first, self.a[1], a_range)


@pytest.mark.parametrize("rule", [PoseSeekPolicy(2, 4), PoseSeekPolicy(4, 4), BoxGatePolicy(0, 1)],
                         ids=["pose_seek-2", "pose_seek-4", "box_gate"])
@pytest.mark.parametrize("split", ["train", "hard"])
def test_the_rules_values_are_the_returns_of_its_rollouts(table, rule, split):
    sol = rule_values(table, split, rule, CFG)
    rollout = evaluate_policy(table, split, rule, CFG)
    np.testing.assert_allclose(sol.value[:, CFG.t_max].reshape(-1), rollout.ret, rtol=0, atol=1e-12)
    flies = (sol.rule_type[:, CFG.t_max] != STOP).mean()
    assert 0 < flies < 1, flies  # the check covers both the rule's stops and its moves
    for a_type, a_range in [(STOP, 0), (0, 0), (3, 2), (5, 3)]:  # a first action, then the rule
        first = evaluate_policy(table, split, FirstThenRule(rule, a_type, a_range), CFG)
        np.testing.assert_allclose(sol.q[:, CFG.t_max, :, a_type, a_range].reshape(-1), first.ret, rtol=0,
                                   atol=1e-12)
    adv = sol.advantage()[:, CFG.t_max]
    own = adv[np.arange(adv.shape[0])[:, None], np.arange(N_VIEWS)[None], sol.rule_type[:, CFG.t_max],
              sol.rule_range[:, CFG.t_max]]
    assert np.abs(own).max() < 1e-12  # the rule's own action has no advantage over itself


def test_the_departure_ceiling_runs_from_the_rule_to_the_oracle(table):
    """0 departures is the rule; each one more can only add; departing at every decision is the
    unconstrained best policy, the oracle's value."""
    rule = PoseSeekPolicy(2, 4)
    sol = rule_values(table, "hard", rule, CFG)
    ceilings = [departure_ceiling(sol, d) for d in range(CFG.t_max + 1)]
    np.testing.assert_array_equal(ceilings[0], sol.value[:, CFG.t_max])
    for lower, upper in zip(ceilings, ceilings[1:], strict=False):
        assert (upper >= lower - 1e-12).all()
    assert ceilings[1].mean() > ceilings[0].mean()  # one departure pays somewhere
    oracle = oracle_values(table, CFG).value[sol.scenes, CFG.t_max]
    np.testing.assert_allclose(ceilings[CFG.t_max], oracle, rtol=0, atol=1e-12)
    assert (ceilings[1] <= oracle + 1e-12).all()
    with pytest.raises(ValueError, match="departures=-1"):
        departure_ceiling(sol, -1)


@pytest.mark.parametrize("departures", [1, 2])
@pytest.mark.parametrize("split", ["train", "hard"])
def test_the_departure_ceiling_policy_flies_the_ceiling(table, departures, split):
    """Rolled out through the evaluation, the policy's return from every start is the ceiling's
    value: its departures are the ones the values count, and never more than allowed."""
    rule = PoseSeekPolicy(2, 4)
    sol = rule_values(table, split, rule, CFG)
    policy = DepartureCeilingPolicy(table, CFG, rule, departures)
    rollout = evaluate_policy(table, split, policy, CFG)
    np.testing.assert_allclose(rollout.ret, departure_ceiling(sol, departures).reshape(-1), rtol=0, atol=1e-12)
    assert rollout.ret.mean() > sol.value[:, CFG.t_max].mean()  # it departs, and gains


def test_the_departure_ceiling_is_a_baseline_of_every_evaluation(table):
    frame, _ = evaluate_beside_baselines(table, "hard", PoseSeekPolicy(2, 4), "rule", CFG)
    ret = frame["mean_return"]
    assert ret["rule"] <= ret["departure_ceiling"] <= ret["departure_ceiling2"] <= ret["oracle"] + 1e-12
    assert ret["departure_ceiling"] > ret["pose_seek"]

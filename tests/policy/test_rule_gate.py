"""The rule gate (``train.stop_gate = "rule"``): the pose rule's action wherever the box is
hidden, in training and in acting; where it is visible, stop unless departing from the rule
pays (the rule's exact advantage in training, a probe's answer in acting)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.config import ConfigError
from uevavd.data.grid import STOP
from uevavd.env import evaluate_policy
from uevavd.env.baselines import PoseSeekPolicy, pose_seek_hidden, pose_seek_moves
from uevavd.env.batched import BatchedAODEnv
from uevavd.env.gate import box_visible
from uevavd.env.rule_values import rule_values
from uevavd.policy.acting import load_policy
from uevavd.policy.collector import EpisodeCollector
from uevavd.policy.config import TrainConfig
from uevavd.policy.network import build_network
from uevavd.policy.rule_gate import RulePays
from uevavd.policy.trainer import train

from .test_stop_gate import _spec, hidden_table


def rule_moves(table, config) -> int:
    return pose_seek_moves(table, config)[0]


def test_the_rule_gate_is_refused_with_imitation_and_without_views():
    with pytest.raises(ConfigError, match="train.stop_gate"):
        TrainConfig(stop_gate="rule", imitation="visibility_oracle")
    TrainConfig(stop_gate="rule", stop_threshold=0.7)  # its probe reads the threshold
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule")
    net = build_network(spec.state, spec.head, table.feature_dim).set_stop_gate("rule")
    with pytest.raises(ValueError, match="view= and t="):
        net.allowed(torch.ones(2, 7, 4, dtype=torch.bool), torch.zeros(2, 4), training=True,
                    pays=torch.zeros(2, dtype=torch.bool))


def test_the_rule_gates_answer_is_the_rules_exact_advantage():
    """RulePays at (scene, view, t) is whether some allowed move, the rule after, beats the rule
    there, read off the rule's exact values with k = T_max - t decisions left."""
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule")
    env = BatchedAODEnv(table, "train", 8, spec.env, seed=0)
    moves = rule_moves(table, spec.env)
    pays = RulePays(env.tensors, moves)
    sol = rule_values(env.tensors, "train", PoseSeekPolicy(moves, spec.env.max_range))
    mask = env.tensors.mask.numpy()
    rng = np.random.default_rng(0)
    found = {True: 0, False: 0}
    for _ in range(300):
        s, v, t = rng.integers(len(sol.scenes)), rng.integers(605), rng.integers(spec.env.t_max)
        k = spec.env.t_max - t
        gains = [sol.q[s, k, v, a, r] - sol.value[s, k, v] for a in range(STOP) for r in range(spec.env.max_range)
                 if mask[v, a, r]]
        expected = max(gains) > 1e-9
        scene = env.tensors.scenes[s]
        assert bool(pays.at(scene[None], torch.tensor([v]), torch.tensor([t]))[0]) == expected
        found[expected] += 1
    assert found[True] > 10 and found[False] > 10


def test_the_rule_gate_takes_the_rules_action_wherever_the_box_is_hidden_in_training():
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule")
    net = build_network(spec.state, spec.head, table.feature_dim).set_stop_gate("rule")
    net.rule_moves.fill_(rule_moves(table, spec.env))
    env = BatchedAODEnv(table, "train", 256, spec.env, seed=0)
    pays = RulePays(env.tensors, int(net.rule_moves))
    col = EpisodeCollector(env, net, seed=0, device=torch.device("cpu"), pays=pays)
    col.reset()
    opened = closed = hidden = 0
    for _ in range(6):
        obs = col.obs
        visible = box_visible(obs["box"])
        flight = pays.at(obs["scene"], obs["view"], obs["t"])
        rule_type, rule_range = pose_seek_hidden(obs["view"], obs["t"], int(net.rule_moves), spec.env.max_range)
        t = obs["t"].clone()
        col.step(epsilon=1.0)  # random actions: the gate still holds
        rows = torch.arange(len(t))
        taken, taken_range = col.ep_type[rows, t], col.ep_range[rows, t]
        assert torch.equal(taken[~visible], rule_type[~visible])  # the rule's move, range and all
        flew = ~visible & (rule_type != STOP)
        assert torch.equal(taken_range[flew], rule_range[flew])
        assert (taken[visible & ~flight] == STOP).all()  # stop where no departure pays
        assert (taken[visible & flight] != STOP).any()  # opened where one does
        opened, closed = opened + int((visible & flight).sum()), closed + int((visible & ~flight).sum())
        hidden += int(flew.sum())
    assert opened > 20 and closed > 20 and hidden > 20


@pytest.mark.parametrize("threshold", [0.0, 1.0])
def test_a_rule_gated_run_resumes_bit_for_bit_and_is_the_rule_when_its_probe_never_opens(tmp_path, threshold):
    """Threshold 1 never opens the gate where the box is visible, so the trained policy is the
    pose rule return for return (its moves travel in the policy file); threshold 0 always
    opens it, so the Q network flies from visible boxes."""
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule", **{"train.stop_threshold": threshold})
    for d, epochs in (("whole", None), ("paused", 1), ("paused", None)):
        train(spec, table, out=tmp_path / d, seed=3, device="cpu", progress=False, max_epochs=epochs)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "paused"))
    assert {"stop_probe.weight", "rule_moves"} <= set(a["net"])
    assert all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])
    policy = load_policy(tmp_path / "whole", with_table=False)
    moves = int(policy.net.rule_moves)
    assert moves == rule_moves(table, spec.env)
    learned = evaluate_policy(table, "hard", policy, spec.env)
    rule = evaluate_policy(table, "hard", PoseSeekPolicy(moves, spec.env.max_range), spec.env)
    if threshold == 1.0:
        np.testing.assert_array_equal(learned.ret, rule.ret)
    else:
        assert learned.summary()["moved_if_box"] > 0.0


def test_the_rule_ensembles_settings_are_checked():
    for bad in ({"rule_ensemble": 1, "stop_gate": "rule"}, {"rule_ensemble": 3},
                {"rule_margin": 0.1, "stop_gate": "rule"},
                {"rule_ensemble": 3, "stop_gate": "rule", "stop_threshold": 0.7}):
        with pytest.raises(ConfigError, match="train.rule_|train.stop_threshold"):
            TrainConfig(**bad)
    TrainConfig(stop_gate="rule", rule_ensemble=5, rule_margin=0.02)


def test_the_ensembles_members_fit_their_own_resamples_of_the_contexts():
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule")
    env = BatchedAODEnv(table, "train", 8, spec.env, seed=0)
    pays = RulePays(env.tensors, rule_moves(table, spec.env), ensemble=4, seed=11)
    n = len(env.tensors.scenes)
    assert pays.counts.shape == (n, 4) and (pays.counts.sum(0) == n).all()
    assert not all(torch.equal(pays.counts[:, 0], pays.counts[:, k]) for k in range(1, 4))
    again = RulePays(env.tensors, rule_moves(table, spec.env), ensemble=4, seed=11)
    assert torch.equal(pays.counts, again.counts)
    assert torch.equal(pays.pays, pays.gain > 1e-9)


@pytest.mark.parametrize("margin", [-1.0, 1.0])
def test_a_rule_ensemble_run_resumes_bit_for_bit_and_departs_only_above_its_margin(tmp_path, margin):
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule_ens", **{"train.rule_ensemble": 3, "train.rule_margin": margin})
    for d, epochs in (("whole", None), ("paused", 1), ("paused", None)):
        train(spec, table, out=tmp_path / d, seed=3, device="cpu", progress=False, max_epochs=epochs)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "paused"))
    assert a["net"]["stop_probe.weight"].shape[0] == 3
    assert all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])
    policy = load_policy(tmp_path / "whole", with_table=False)
    learned = evaluate_policy(table, "hard", policy, spec.env)
    rule = evaluate_policy(table, "hard", PoseSeekPolicy(int(policy.net.rule_moves), spec.env.max_range), spec.env)
    if margin == 1.0:  # no advantage reaches 1: the rule, return for return
        np.testing.assert_array_equal(learned.ret, rule.ret)
    else:
        assert learned.summary()["moved_if_box"] > 0.0

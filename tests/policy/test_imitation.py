"""DAgger with the visibility oracle as the expert (``train.imitation``): the labels are the
oracle's plans for the steps left, a run learns to act as the oracle does, resumes bit for bit
across the switch to double DQN, and what it cannot run on is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.config import load_method
from uevavd.config_rules import ConfigError
from uevavd.env import EnvConfig, evaluate_policy
from uevavd.env.baselines import build_visibility_oracle
from uevavd.env.batched import EnvTensors
from uevavd.env.visibility_oracle import visibility_plans
from uevavd.policy.acting import load_policy
from uevavd.policy.imitation import OracleLabels
from uevavd.policy.trainer import train
from uevavd.table import ObservationTable
from uevavd.testing.policy import small_run, toy_table


def make_table() -> ObservationTable:
    """The toy table with a visible fraction at every view: its recognisability signal."""
    t = toy_table(n_train=1, n_hard=1, feature_dim=8)
    feats = np.array(t.features)
    return ObservationTable.from_arrays(feats, np.array(t.probs), np.array(t.boxes), scenes=list(t.scenes),
                                        targets=list(t.targets), splits=list(t.splits), contexts=list(t.contexts),
                                        visible=np.clip(feats[..., 3], 0.0, 1.0), config={"toy-visible": 0})


@pytest.fixture(scope="module")
def table():
    return make_table()


def _spec(method="ibe_map_pose_dagger", episodes=1500, **over):
    return load_method(method, overrides={**small_run("memo_map"), "train.episodes": episodes, **over})


def test_the_labels_are_the_oracles_first_action_for_the_steps_left(table):
    cfg = EnvConfig(t_max=4)
    tensors = EnvTensors(table, "train", cfg)
    labels = OracleLabels(tensors)
    views = torch.tensor([[7, 300, 31, 604, 0], [0, 1, 2, 3, 4]])
    a_type, a_range = labels.labels(torch.tensor([0, 0]), views)
    for t in range(4):  # decision t has 4 - t decisions left, from the view it was taken at
        plan_type, plan_range, _ = visibility_plans(np.asarray(table.visible)[:1], cfg.replace(t_max=4 - t))
        assert a_type[:, t].tolist() == plan_type[0, views[:, t].numpy(), 0].tolist()
        assert a_range[:, t].tolist() == plan_range[0, views[:, t].numpy(), 0].tolist()


def test_a_dagger_run_acts_as_the_oracle_more_than_a_dqn_run(table, tmp_path):
    oracle = evaluate_policy(table, "train", build_visibility_oracle(table=table, config=EnvConfig(pose=True)),
                             EnvConfig(pose=True))
    agree = {}
    for method in ("ibe_map_pose_dagger", "ibe_map_pose"):  # a learning rate at which 1,000 episodes show it
        spec = _spec(method, episodes=1000, **{"train.lr": 3e-3})
        run = train(spec, table, out=tmp_path / method, device="cpu", progress=False)
        res = evaluate_policy(table, "train", load_policy(run), spec.env)
        agree[method] = float(np.mean(res.trajectories[:, 1] == oracle.trajectories[:, 1]))
    assert agree["ibe_map_pose_dagger"] > 0.6 and agree["ibe_map_pose_dagger"] > agree["ibe_map_pose"] + 0.3


def test_a_run_that_switches_to_dqn_resumes_bit_for_bit(table, tmp_path):
    spec = _spec(episodes=400, **{"train.imitation_fraction": 0.5})
    whole = train(spec, table, out=tmp_path / "whole", device="cpu", progress=False)
    train(spec, table, out=tmp_path / "paused", device="cpu", progress=False, max_epochs=1)
    paused = train(spec, table, out=tmp_path / "paused", device="cpu", progress=False)
    a, b = load_policy(whole).net.state_dict(), load_policy(paused).net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert spec.train_config().imitating(199) and not spec.train_config().imitating(200)


def test_what_dagger_cannot_run_on_is_refused_before_the_run_starts(tmp_path):
    with pytest.raises(ConfigError, match="visible fraction"):  # a table without visible fractions
        train(_spec(), toy_table(n_train=2, n_hard=1, feature_dim=8), out=tmp_path / "a", device="cpu",
              progress=False)
    assert not (tmp_path / "a").exists()
    with pytest.raises(ConfigError, match="type branch"):  # a head of the joint form
        train(_spec(**{"head.name": "dueling_joint", "head.hidden": 16}), make_table(), out=tmp_path / "b",
              device="cpu", progress=False)
    with pytest.raises(ConfigError, match="imitation_fraction"):
        _spec(**{"train.imitation_fraction": 0.0}).train_config()


def test_behind_the_box_gate_only_the_decisions_where_the_box_is_hidden_are_imitated(table):
    from uevavd.policy.acting import method_network
    from uevavd.policy.learner import FeatureLookup, Learner
    from uevavd.policy.replay import EpisodeReplay

    cfg = EnvConfig(pose=True)
    tensors = EnvTensors(table, "train", cfg)  # the toy table shows the box at every view
    replay = EpisodeReplay(4, cfg.t_max)
    views = torch.tensor([[10, 20, 30, 0, 0, 0], [300, 301, 0, 0, 0, 0]])
    zeros = torch.zeros(2, cfg.t_max, dtype=torch.int64)
    replay.add(torch.zeros(2, dtype=torch.int64), views, zeros, zeros, zeros.float(), torch.tensor([3, 2]))
    batch = replay.sample(2, 1.0)
    losses = {}
    for method in ("ibe_map_pose_dagger", "ibe_map_pose_dagger_gate"):
        spec = _spec(method)
        torch.manual_seed(0)
        net = method_network(spec, table.feature_dim, cfg.max_range)
        learner = Learner(net, lr=1e-3, gamma=0.9, grad_clip=10.0, imitation=OracleLabels(tensors))
        losses[method], _ = learner.update(batch, FeatureLookup(tensors), imitate=True)
    assert losses["ibe_map_pose_dagger"] > 0.5 and losses["ibe_map_pose_dagger_gate"] == 0.0

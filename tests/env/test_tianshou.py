"""Tianshou 2.0's DQN over the env, unmodified, through its own vector env and Collector.

Tianshou 2.0 holds pandas below 3, so the test extra leaves it out and this module skips
where it is absent: ``pip install -e ".[tianshou]"`` runs it (docs/environment.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium.wrappers import FlattenObservation

from uevavd.env import AODEnv, DiscreteActions, FlatPolicy, MaskedFlatObservation, evaluate_policy
from uevavd.testing.policy import toy_table

ts = pytest.importorskip("tianshou", reason="Tianshou is not installed: pip install -e '.[tianshou]' (it holds "
                         "pandas below 3, so the test extra leaves it out)")


@pytest.fixture(scope="module")
def table():
    return toy_table(n_train=3, n_hard=2, feature_dim=8)


def _dqn(env, obs_dim: int):
    import torch
    from tianshou.algorithm.modelfree.dqn import DiscreteQLearningPolicy
    from tianshou.algorithm.optim import AdamOptimizerFactory
    from tianshou.utils.net.common import Net

    torch.manual_seed(0)
    net = Net(state_shape=(obs_dim,), action_shape=int(env.action_space.n), hidden_sizes=[32])
    policy = DiscreteQLearningPolicy(model=net, action_space=env.action_space, eps_training=0.3)
    return ts.algorithm.DQN(policy=policy, optim=AdamOptimizerFactory(lr=1e-3), gamma=0.9, target_update_freq=20)


@pytest.mark.parametrize("wrap", ["flatten", "masked"])
def test_tianshou_dqn_collects_and_learns_through_its_collector(table, wrap):
    """A few hundred steps of Tianshou's DQN in 4 envs: the collector's episodes end on the
    env's terminal step, updates run on its replay buffer, and a test collector evaluates the
    greedy policy. With MaskedFlatObservation Tianshou reads the mask (obs.mask): neither its
    greedy nor its random actions pick a move the mask forbids; FlattenObservation alone leaves
    it unread (a clamped move is legal: a wasted step)."""
    from tianshou.data import CollectStats
    from tianshou.utils.torch_utils import policy_within_training_step, torch_train_mode

    def make():
        env = AODEnv(table, "train")
        return MaskedFlatObservation(env) if wrap == "masked" else FlattenObservation(DiscreteActions(env))

    probe = make()
    obs_space = probe.observation_space["obs"] if wrap == "masked" else probe.observation_space
    algo = _dqn(probe, obs_space.shape[0])
    buffer = ts.data.VectorReplayBuffer(2000, 4)
    collector = ts.data.Collector[CollectStats](algo, ts.env.DummyVectorEnv([make] * 4), buffer,
                                                exploration_noise=True)
    collector.reset(gym_reset_kwargs={"seed": 0})
    stats = collector.collect(n_step=400)
    assert stats.n_collected_steps >= 400 and stats.n_collected_episodes > 0
    assert len(buffer) == stats.n_collected_steps
    before = [p.detach().clone() for p in algo.policy.parameters()]
    with policy_within_training_step(algo.policy), torch_train_mode(algo.policy):
        for _ in range(10):
            algo.update(sample_size=32, buffer=buffer)
    assert any(not (p == q).all() for p, q in zip(before, algo.policy.parameters(), strict=True))
    batch, _ = buffer.sample(0)
    if wrap == "masked":
        mask = batch.obs.mask
        forbidden = ~mask.astype(bool)
        assert forbidden.any(), "no collected view forbids a move: the check below would be empty"
        allowed = mask[np.arange(len(batch)), batch.act.astype(int)]
        assert allowed.all()  # Tianshou honoured the mask, exploration included
    test = ts.data.Collector[CollectStats](algo, ts.env.DummyVectorEnv([make] * 2))
    test.reset(gym_reset_kwargs={"seed": 1})
    returns = test.collect(n_episode=6).returns
    assert len(returns) == 6 and np.isfinite(returns).all()
    assert (np.asarray(returns) <= 1.0 + 1e-6).all()  # at most the recognition reward xi1
    if wrap == "masked":  # one flat layout: the network trained here scores through FlatPolicy as it is
        net = algo.policy.model
        n_actions = int(probe.action_space.n)
        policy = FlatPolicy(lambda x: net(torch.as_tensor(x))[0].detach().numpy(), max_range=n_actions // 7,
                            width=probe.observation_space["obs"])
        res = evaluate_policy(table, "hard", policy)
        assert np.isfinite(res.ret).all() and len(res.ret) == len(table.scene_indices("hard")) * 605

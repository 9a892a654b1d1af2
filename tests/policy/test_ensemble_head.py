"""The ensemble head: the head protocol, its acting rule, its per-member targets,
and a method that uses it trained and resumed like any other."""

from __future__ import annotations

import pytest
import torch

from uevavd.config import ConfigError, load_method
from uevavd.policy import targets as T
from uevavd.policy.contract import check_head_rules
from uevavd.policy.heads import build_ensemble_branching
from uevavd.policy.trainer import train
from uevavd.testing.policy import small_run, toy_table


def test_the_ensemble_keeps_the_head_protocol_and_refuses_bad_settings():
    head = build_ensemble_branching(state_dim=16, hidden=8, members=3, kappa=1.0)
    check_head_rules(head, state_dim=16)
    assert head.n_branches == 6
    for bad, key in (({"members": 1}, "head.members"), ({"members": 2.5}, "head.members"),
                     ({"kappa": float("nan")}, "head.kappa"), ({"kappa": "1"}, "head.kappa"),
                     ({"kappa": 1e300}, r"head.kappa = 1e\+300: expected a number in \[-1000, 1000\]")):
        with pytest.raises(ConfigError, match=key):
            build_ensemble_branching(state_dim=16, hidden=8, **bad)


def test_it_acts_on_the_members_lower_bound():
    """kappa 0 is the mean; kappa > 0 trades a higher mean for the members' agreement."""
    head = build_ensemble_branching(state_dim=4, hidden=4, members=2, kappa=0.0)
    # type branch: action 0 has mean 1.0 with the members far apart, action 6 (stop) mean 0.9 agreed
    q_type = [torch.tensor([[3.0, -9, -9, -9, -9, -9, 0.9]]), torch.tensor([[-1.0, -9, -9, -9, -9, -9, 0.9]])]
    q_range = [torch.zeros(1, 4), torch.zeros(1, 4)]
    q = (q_type[0], q_range[0], q_type[1], q_range[1])
    assert int(head.greedy(q, None)[0]) == 0
    head.kappa = 1.0
    assert int(head.greedy(q, None)[0]) == T.STOP


def test_each_member_bootstraps_from_its_own_greedy_action():
    head = build_ensemble_branching(state_dim=8, hidden=8, members=3, kappa=1.0)
    s = torch.randn(4, 8, generator=torch.Generator().manual_seed(0))
    q_online, q_target = head(s), head(s * 2)
    boot = head.bootstrap(q_online, q_target, None)
    for i, member in enumerate(head.members):
        alone = member.bootstrap(q_online[2 * i:2 * i + 2], q_target[2 * i:2 * i + 2], None)
        assert torch.equal(boot[..., 2 * i:2 * i + 2], alone)
    a_type = torch.tensor([0, 6, 2, 6])
    assert torch.equal(head.weights(a_type), T.branch_weights(a_type).repeat(1, 3))


def test_a_method_with_the_ensemble_trains_and_resumes_bit_for_bit(tmp_path):
    table = toy_table(n_train=3, n_hard=2, feature_dim=8)
    spec = load_method("ibe_map_ens", overrides={**small_run("ibe_map"), "train.episodes": 200, "head.members": 3})
    train(spec, table, out=tmp_path / "whole", seed=1, device="cpu", progress=False)
    train(spec, table, out=tmp_path / "paused", seed=1, device="cpu", progress=False, max_epochs=1)
    train(spec, table, out=tmp_path / "paused", seed=1, device="cpu", progress=False)
    a = torch.load(tmp_path / "whole" / "checkpoint.pt", weights_only=False)["net"]
    b = torch.load(tmp_path / "paused" / "checkpoint.pt", weights_only=False)["net"]
    assert any(k.startswith("head.members.2.") for k in a)
    assert all(torch.equal(a[k], b[k]) for k in a)

"""Every method config in model_zoo builds and runs one update."""

import pytest
import torch

from uevavd.config import known_methods, load_method
from uevavd.env.batched import BatchedAODEnv
from uevavd.policy.learner import FeatureLookup, Learner
from uevavd.policy.network import build_network
from uevavd.policy.replay import EpisodeReplay
from uevavd.testing.policy import toy_table

SMALL = {"state.input_dim": 24, "state.box_dim": 8, "state.state_dim": 16, "head.hidden": 16}


@pytest.mark.parametrize("method", known_methods())
@pytest.mark.parametrize("head", ["dueling_branch", "dueling_joint"])
def test_method_builds_and_updates(method, head):
    torch.manual_seed(0)
    table = toy_table(n_train=2, n_hard=1, feature_dim=8)
    over = dict(SMALL, **({"state.hidden": 16} if load_method(method).component("state")[0] == "gru" else {}))
    over["head.name"] = head
    over["head.hidden"] = 16
    spec = load_method(method, over)
    net = build_network(spec.state, spec.head, table.feature_dim)
    env = BatchedAODEnv(table, "train", 8, device="cpu", seed=0)
    # multi-step episodes from the env (moves, then a stop, or T_max moves), so every head's
    # TD target bootstraps at non-terminal steps
    obs = env.reset()
    scene, length = obs["scene"].clone(), torch.zeros(8, dtype=torch.int64)
    views = torch.zeros(8, 6, dtype=torch.int64)
    a_type = torch.zeros(8, 5, dtype=torch.int64)
    a_range = torch.zeros(8, 5, dtype=torch.int64)
    reward = torch.zeros(8, 5)
    stop_at = torch.tensor([0, 1, 2, 3, 4, 5, 5, 2])  # 5: never stops (ends at T_max)
    live = torch.ones(8, dtype=torch.bool)
    for t in range(5):
        views[live, t] = obs["view"][live]
        a_type[:, t] = torch.where(stop_at == t, 6, t % 6)
        a_range[:, t] = t % 4
        obs, r, done, info = env.step(a_type[:, t], a_range[:, t])
        reward[live, t] = r[live]
        ended = live & done
        views[ended, t + 1] = info["final_view"][ended]
        length[ended] = t + 1
        live &= ~done
    assert not bool(live.any()) and length.tolist() == [1, 2, 3, 4, 5, 5, 5, 3]
    replay = EpisodeReplay(32, 5)
    replay.add(scene, views, a_type, a_range, reward, length)
    batch = replay.sample(16, 0.4)
    assert bool((batch.valid & ~batch.done).any())
    learner = Learner(net, lr=1e-3, gamma=0.9, grad_clip=1.0)
    before = [p.detach().clone() for p in net.parameters()]
    loss, td = learner.update(batch, FeatureLookup(env.tensors))
    assert torch.isfinite(torch.tensor(loss)) and td.shape == (16,)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))

"""Every method config in model_zoo builds and runs one update."""

import pytest
import torch

from uevavd.config import known_methods, load_method
from uevavd.env.batched import BatchedAODEnv
from uevavd.policy.agent import Learner, TableLookup
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
    net = build_network(spec, table.feature_dim)
    env = BatchedAODEnv(table, "train", 8, device="cpu", seed=0)
    obs = env.reset()
    replay = EpisodeReplay(32, 5)
    t = obs["t"]
    views = torch.zeros(8, 6, dtype=torch.int64)
    views[:, 0] = obs["view"]
    a_type = torch.full((8, 5), 6)
    _, reward, done, info = env.step(a_type[:, 0], torch.zeros(8, dtype=torch.int64))
    assert bool(done.all())
    replay.add(obs["scene"], views, a_type, torch.zeros(8, 5, dtype=torch.int64),
               torch.nn.functional.pad(reward[:, None], (0, 4)), t + 1)
    learner = Learner(net, lr=1e-3, gamma=0.9, grad_clip=1.0)
    before = [p.detach().clone() for p in net.parameters()]
    loss, td = learner.update(replay.sample(4, 0.4), TableLookup(env.tables))
    assert torch.isfinite(torch.tensor(loss)) and td.shape == (4,)
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))

"""The double-DQN update on replayed episodes, against a plain padded reference."""

import copy

import pytest
import torch
import torch.nn.functional as F

from uevavd.config import load_method
from uevavd.env.batched import EnvTensors
from uevavd.env.config import EnvConfig
from uevavd.policy import targets as T
from uevavd.policy.agent import Learner, TableLookup
from uevavd.policy.network import build_network
from uevavd.policy.replay import EpisodeReplay

from .conftest import small


def _reference_loss(net, target, batch, lookup, gamma):
    """The update's loss written plainly: every padded position is encoded (the GRU
    unrolled over all T+1 observations) and only the mask keeps padding out."""
    feats, boxes, mask = lookup.gather(batch.scene, batch.views)
    head = net.head
    q_all = net(feats, boxes)
    with torch.no_grad():
        boot = head.bootstrap(tuple(q[:, 1:] for q in q_all), tuple(q[:, 1:] for q in target(feats, boxes)),
                              mask[:, 1:])
        y = T.td_target(batch.reward, batch.done, boot, gamma)
    q_taken = head.taken(tuple(q[:, :-1] for q in q_all), batch.a_type, batch.a_range)
    w = head.weights(batch.a_type) * batch.valid[..., None].float()
    per = F.smooth_l1_loss(q_taken, y, reduction="none")
    return (per * w * batch.weight[:, None, None]).sum() / w.sum().clamp_min(1.0)


@pytest.mark.parametrize("method", ["map", "memo_map"])
def test_update_matches_padded_reference_and_ignores_padding(table, method):
    torch.manual_seed(0)
    spec = load_method(method, small(method))
    net = build_network(spec, table.feature_dim)
    learner = Learner(net, lr=1e-3, gamma=0.9, grad_clip=0.0)
    with torch.no_grad():  # a target network that differs from the online one
        for p in learner.target.parameters():
            p.add_(0.1 * torch.randn_like(p))
    tables = EnvTensors(table, "train", EnvConfig())
    lookup = TableLookup(tables)
    replay = EpisodeReplay(64, 5, seed=0)
    g = torch.Generator().manual_seed(1)
    n = 12
    length = torch.tensor([1, 2, 3, 4, 5, 1, 2, 3, 4, 5, 1, 5])
    views = torch.randint(0, 605, (n, 6), generator=g)
    a_type = torch.randint(0, 7, (n, 5), generator=g)
    a_type[torch.arange(n), length - 1] = T.STOP
    replay.add(tables.scenes[torch.randint(0, len(tables.scenes), (n,), generator=g)], views, a_type,
               torch.randint(0, 4, (n, 5), generator=g), 0.1 * torch.randn(n, 5, generator=g), length)
    batch = replay.sample(16, 0.5)

    ref_net = copy.deepcopy(net)
    ref = _reference_loss(ref_net, learner.target, batch, lookup, 0.9)
    ref.backward()
    loss, td = learner.update(batch, lookup)
    assert loss == pytest.approx(float(ref.detach()), rel=1e-5, abs=1e-7)
    assert td.shape == (16,) and bool((td > 0).all())

    # the gradient step equals Adam's first step on the reference gradients
    opt = torch.optim.Adam(ref_net.parameters(), lr=1e-3)
    opt.step()
    for (k, a), b in zip(net.state_dict().items(), ref_net.state_dict().values(), strict=True):
        assert torch.allclose(a, b, atol=1e-6), k

    # garbage after an episode's end (views, actions, rewards) changes nothing
    junk = copy.copy(batch)
    pad = ~batch.valid
    junk.views = batch.views.clone()
    junk.views[:, 2:][pad[:, 1:]] = 604 - junk.views[:, 2:][pad[:, 1:]]
    junk.a_type = torch.where(pad, (batch.a_type + 1) % 7, batch.a_type)
    junk.reward = torch.where(pad, batch.reward + 5.0, batch.reward)
    net_a, net_b = copy.deepcopy(ref_net), copy.deepcopy(ref_net)
    la = Learner(net_a, lr=1e-3, gamma=0.9, grad_clip=0.0)
    lb = Learner(net_b, lr=1e-3, gamma=0.9, grad_clip=0.0)
    lb.target.load_state_dict(la.target.state_dict())
    assert la.update(batch, lookup)[0] == pytest.approx(lb.update(junk, lookup)[0], rel=1e-6)


def test_gru_packed_unroll_equals_padded_forward():
    torch.manual_seed(0)
    est = load_method("memo_map", small("memo_map")).build("state", feature_dim=8)
    f, b = torch.randn(5, 6, 8), torch.rand(5, 6, 4)
    seen = torch.arange(6)[None] <= torch.tensor([0, 5, 2, 3, 1])[:, None]
    with torch.no_grad():
        assert torch.allclose(est.forward_packed(f[seen], b[seen], seen), est(f, b)[seen], atol=1e-6)

"""The double-DQN update on replayed episodes, against a plain padded reference."""

import copy
import itertools

import pytest
import torch
import torch.nn.functional as F

from uevavd.config import load_method
from uevavd.env.batched import EnvTensors
from uevavd.env.config import EnvConfig
from uevavd.policy import targets as T
from uevavd.policy.learner import FeatureLookup, Learner, needed_observations
from uevavd.policy.network import build_network
from uevavd.policy.replay import EpisodeBatch, EpisodeReplay

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


def _explicit_loss(net, target, batch, lookup, gamma, head):
    """The double-DQN Huber loss and per-episode mean |TD error| written out step by step,
    without the heads' vectorised helpers: masked argmax of the online net at s_{t+1},
    evaluated by the target net; a greedy stop's range takes the type branch's value."""
    feats, boxes, mask = lookup.gather(batch.scene, batch.views)
    with torch.no_grad():
        q_on, q_tg, q_now = net(feats, boxes), target(feats, boxes), net(feats, boxes)
    n_ranges = mask.shape[-1]
    total, wsum, td = 0.0, 0.0, []
    for b in range(batch.reward.shape[0]):
        ep_err, ep_w = 0.0, 0.0
        for t in range(batch.reward.shape[1]):
            if not batch.valid[b, t]:
                continue
            r, a_t, a_r = float(batch.reward[b, t]), int(batch.a_type[b, t]), int(batch.a_range[b, t])
            if head == "dueling_joint":  # stop is one action: its range-0 entry
                taken = [float(q_now[0][b, t, a_t * n_ranges + (0 if a_t == T.STOP else a_r)])]
                weights = [1.0]
            else:
                taken = [float(q_now[0][b, t, a_t]), float(q_now[1][b, t, a_r])]
                weights = [1.0, 0.0 if a_t == T.STOP else 1.0]
            if batch.done[b, t]:
                y = [r] * len(taken)
            else:
                m = mask[b, t + 1]  # (7, A) allowed moves at s_{t+1}
                if head == "dueling_joint":
                    q = q_on[0][b, t + 1].view(7, n_ranges)
                    best = max(((i, j) for i in range(7) for j in range(n_ranges)
                                if m[i, j] and not (i == T.STOP and j > 0)),
                               key=lambda ij: float(q[ij]))
                    y = [r + gamma * float(q_tg[0][b, t + 1].view(7, n_ranges)[best])]
                else:
                    i = max((i for i in range(7) if m[i].any()), key=lambda i: float(q_on[0][b, t + 1, i]))
                    j = max((j for j in range(n_ranges) if m[i, j]), key=lambda j: float(q_on[1][b, t + 1, j]))
                    vt = float(q_tg[0][b, t + 1, i])
                    vr = vt if i == T.STOP else float(q_tg[1][b, t + 1, j])
                    if head == "indep":
                        y = [r + gamma * vt, r + gamma * vr]
                    else:
                        y = [r + gamma * (vt + vr) / 2] * 2
            for qv, yv, w in zip(taken, y, weights, strict=True):
                err = abs(qv - yv)
                huber = 0.5 * err**2 if err < 1.0 else err - 0.5
                total += float(batch.weight[b]) * w * huber
                wsum += w
                ep_err, ep_w = ep_err + w * err, ep_w + w
        td.append(ep_err / max(ep_w, 1.0))
    return total / max(wsum, 1.0), torch.tensor(td)


def _episodes(tables, seed=1):
    """12 episodes of 1..5 decisions: moves, then a stop, or T_max moves (half of the full ones
    end by stop at the last decision); ranges random, stops' included."""
    g = torch.Generator().manual_seed(seed)
    length = torch.tensor([1, 2, 3, 4, 5, 1, 2, 3, 4, 5, 3, 5])
    n = len(length)
    views = torch.randint(0, 605, (n, 6), generator=g)
    a_type = torch.randint(0, T.STOP, (n, 5), generator=g)
    last = torch.where((length < 5) | (torch.arange(n) % 2 == 0), T.STOP, 1)
    a_type[torch.arange(n), length - 1] = last
    return (tables.scenes[torch.randint(0, len(tables.scenes), (n,), generator=g)], views, a_type,
            torch.randint(0, 4, (n, 5), generator=g), 0.1 * torch.randn(n, 5, generator=g), length)


def _replayed_batch(table):
    """The feature lookup of the table's training split and 16 episodes sampled from a
    replay of :func:`_episodes`."""
    tables = EnvTensors(table, "train", EnvConfig())
    replay = EpisodeReplay(64, 5, seed=0)
    replay.add(*_episodes(tables))
    return FeatureLookup(tables), replay.sample(16, 0.5)


#: The heads and TD-target forms, each checked on multi-step episodes.
HEADS = {
    "dueling_branch": {"head.name": "dueling_branch", "head.td_target": "mean"},
    "indep": {"head.name": "dueling_branch", "head.td_target": "indep"},
    "dueling_joint": {"head.name": "dueling_joint"},
}


def _spec(method, head):
    return load_method(method, {**HEADS[head], **small(method)})


@pytest.mark.parametrize("head", list(HEADS))
@pytest.mark.parametrize("method", ["map", "memo_map"])
def test_update_matches_padded_reference_and_ignores_padding(table, method, head):
    torch.manual_seed(0)
    spec = _spec(method, head)
    net = build_network(spec.state, spec.head, table.feature_dim)
    assert spec.component("head")[0] == HEADS[head]["head.name"]
    learner = Learner(net, lr=1e-3, gamma=0.9, grad_clip=0.0)
    with torch.no_grad():  # a target network that differs from the online one
        for p in learner.target.parameters():
            p.add_(0.1 * torch.randn_like(p))
    lookup, batch = _replayed_batch(table)
    assert bool((batch.valid & ~batch.done).any())  # non-terminal steps: targets bootstrap

    ref_net = copy.deepcopy(net)
    explicit, explicit_td = _explicit_loss(ref_net, learner.target, batch, lookup, 0.9, head)
    ref = _reference_loss(ref_net, learner.target, batch, lookup, 0.9)
    assert float(ref.detach()) == pytest.approx(explicit, rel=1e-4, abs=1e-6)
    ref.backward()
    loss, td = learner.update(batch, lookup)
    assert loss == pytest.approx(float(ref.detach()), rel=1e-5, abs=1e-7)
    assert td.shape == (16,) and bool((td > 0).all())
    assert torch.allclose(td, explicit_td.float(), rtol=1e-4, atol=1e-6)

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
    la_loss = la.update(batch, lookup)[0]
    assert la_loss == pytest.approx(lb.update(junk, lookup)[0], rel=1e-6)

    # every episode ends with a termination, so its final observation o_L is never read
    # (the update does not encode it): changing it changes nothing
    last = copy.copy(batch)
    last.views = batch.views.clone()
    ends = batch.valid.sum(1)
    last.views[torch.arange(16), ends] = 604 - batch.views[torch.arange(16), ends]
    lc = Learner(copy.deepcopy(ref_net), lr=1e-3, gamma=0.9, grad_clip=0.0)
    lc.target.load_state_dict(la.target.state_dict())
    assert lc.update(last, lookup)[0] == pytest.approx(la_loss, rel=1e-6)

    # a last decision that did not end its episode (not produced by this environment, but
    # allowed by the batch format) bootstraps from o_L, and the update still matches
    open_end = copy.copy(batch)
    open_end.done = torch.zeros_like(batch.done)
    lo = Learner(copy.deepcopy(ref_net), lr=1e-3, gamma=0.9, grad_clip=0.0)
    lo.target.load_state_dict(la.target.state_dict())
    ref_open = _reference_loss(copy.deepcopy(ref_net), lo.target, open_end, lookup, 0.9)
    assert lo.update(open_end, lookup)[0] == pytest.approx(float(ref_open.detach()), rel=1e-5, abs=1e-7)
    assert float(ref_open.detach()) != pytest.approx(la_loss, rel=1e-4)

    # the discount reaches the loss (bootstrapped targets), for every head
    l0 = Learner(copy.deepcopy(ref_net), lr=1e-3, gamma=0.0, grad_clip=0.0)
    l0.target.load_state_dict(la.target.state_dict())
    l9 = Learner(copy.deepcopy(ref_net), lr=1e-3, gamma=0.9, grad_clip=0.0)
    l9.target.load_state_dict(la.target.state_dict())
    assert l0.update(batch, lookup)[0] != pytest.approx(l9.update(batch, lookup)[0], rel=1e-4)


def test_gru_packed_unroll_equals_padded_forward():
    torch.manual_seed(0)
    est = load_method("memo_map", small("memo_map")).build("state", feature_dim=8)
    f, b = torch.randn(5, 6, 8), torch.rand(5, 6, 4)
    seen = torch.arange(6)[None] <= torch.tensor([0, 5, 2, 3, 1])[:, None]
    with torch.no_grad():
        assert torch.allclose(est.forward_packed(f[seen], b[seen], seen), est(f, b)[seen], atol=1e-6)


@pytest.mark.parametrize("scale", [0.5, 0.999999, 1.0, 1.0005, 1.001, 1.002, 2.0])
def test_clipping_equals_clip_grad_norm_bit_for_bit(table, scale):
    """The update's clipping (which skips the multiply where its factor is exactly 1) leaves
    every parameter as torch's clip_grad_norm_ followed by Adam's step does, bit for bit,
    for a clip threshold below, at and just above the gradient's norm."""
    torch.manual_seed(0)
    spec = _spec("map", "dueling_branch")
    net = build_network(spec.state, spec.head, table.feature_dim)
    lookup, batch = _replayed_batch(table)
    probe = Learner(copy.deepcopy(net), lr=1e-3, gamma=0.9, grad_clip=1e9)
    probe.update(batch, lookup)
    clip = (probe.stats["grad_norm"] + 1e-6) * scale
    mine = Learner(copy.deepcopy(net), lr=1e-3, gamma=0.9, grad_clip=clip)
    ref = Learner(copy.deepcopy(net), lr=1e-3, gamma=0.9, grad_clip=0.0)
    step = ref.optimizer.step

    def clipped_step():
        torch.nn.utils.clip_grad_norm_(ref.net.parameters(), clip)
        step()

    ref.optimizer.step = clipped_step
    for _ in range(3):
        mine.update(batch, lookup)
        ref.update(batch, lookup)
    for (k, a), b in zip(mine.net.state_dict().items(), ref.net.state_dict().values(), strict=True):
        assert torch.equal(a, b), k


def test_needed_observations_on_every_episode_shape():
    """o_t is encoded exactly for t <= L, less o_L when the last decision ended the episode,
    for every length 0..T and every pattern of done flags (padding's included)."""
    t_max = 4
    rows = [(n, bits) for n in range(t_max + 1) for bits in itertools.product([False, True], repeat=t_max)]
    valid = torch.tensor([[t < n for t in range(t_max)] for n, _ in rows])
    done = torch.tensor([bits for _, bits in rows])
    none = torch.zeros(len(rows), dtype=torch.long)
    batch = EpisodeBatch(scene=none, views=torch.zeros(len(rows), t_max + 1, dtype=torch.long), a_type=None,
                         a_range=None, reward=None, valid=valid, done=done, index=none, weight=None)
    want = torch.tensor([[t <= n - (n > 0 and bits[n - 1]) for t in range(t_max + 1)] for n, bits in rows])
    assert torch.equal(needed_observations(batch), want)

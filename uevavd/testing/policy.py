"""Contract checks for ``state`` and ``head`` plugins, and a small learnable toy table.

    from uevavd.testing import check_state_estimator, check_head
    check_state_estimator(my_pkg.build_lstm(feature_dim=16))
    check_head(my_pkg.build_my_head(state_dim=32))
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..data.grid import N_VIEWS, view_coords
from ..table import ObservationTable


def check_state_estimator(est: Any, *, batch: int = 3, steps: int = 4) -> None:
    """Shapes, causality (s_t never reads o_{>t}), and step() agreeing with forward()."""
    for attr in ("feature_dim", "state_dim", "recurrent"):
        assert hasattr(est, attr), f"state estimator {type(est).__name__} has no attribute {attr!r}"
    assert isinstance(est, torch.nn.Module), f"state estimator {type(est).__name__} is not an nn.Module"
    g = torch.Generator().manual_seed(0)
    d = int(est.feature_dim)
    f = torch.randn(batch, steps, d, generator=g)
    b = torch.rand(batch, steps, 4, generator=g)
    est.eval()
    with torch.no_grad():
        s = est(f, b)
        assert tuple(s.shape) == (batch, steps, est.state_dim), (
            f"forward returned {tuple(s.shape)}; expected (B, T, state_dim) = {(batch, steps, est.state_dim)}")
        assert s.dtype == torch.float32, f"states are {s.dtype}; expected float32"
        f2, b2 = f.clone(), b.clone()
        f2[:, -1] += 5.0
        b2[:, -1] = 1.0 - b2[:, -1]
        s2 = est(f2, b2)
        assert torch.allclose(s[:, :-1], s2[:, :-1], atol=1e-5), "s_t changed when a later observation changed"
        h = est.initial_hidden(batch)
        assert h.shape[0] == batch, f"initial_hidden({batch}) has shape {tuple(h.shape)}"
        for t in range(steps):
            st, h = est.step(f[:, t], b[:, t], h)
            assert torch.allclose(st, s[:, t], atol=1e-4), f"step() at t={t} disagrees with forward()"
        if est.recurrent:
            f3 = f.clone()
            f3[:, 0] += 5.0
            assert not torch.allclose(est(f3, b)[:, -1], s[:, -1]), "a recurrent estimator ignores o_0"
    est.train()


def check_head(head: Any, *, state_dim: int | None = None, n_types: int = 7, n_ranges: int = 4) -> None:
    """forward/greedy/taken/bootstrap/weights shapes, masks respected, gradients flow."""
    state_dim = state_dim or int(head.state_dim)
    k = int(head.n_branches)
    g = torch.Generator().manual_seed(0)
    s = torch.randn(5, 3, state_dim, generator=g, requires_grad=True)
    q = head(s)
    assert isinstance(q, tuple) and len(q) == k, f"head returned {type(q).__name__}; expected a {k}-tuple"
    mask = torch.rand(5, 3, n_types, n_ranges, generator=g) > 0.5
    mask[..., n_types - 1, :] = True
    a_type, a_range = head.greedy(q, mask)
    assert a_type.shape == a_range.shape == (5, 3), f"greedy returned shapes {a_type.shape}, {a_range.shape}"
    assert bool(mask[..., :, :].reshape(-1, n_types, n_ranges)[
        torch.arange(15), a_type.reshape(-1), a_range.reshape(-1)].all()), "greedy chose a masked action"
    taken = head.taken(q, a_type, a_range)
    assert taken.shape == (5, 3, k), f"taken has shape {tuple(taken.shape)}; expected (5, 3, {k})"
    boot = head.bootstrap(tuple(x.detach() for x in q), tuple(x.detach() for x in q), mask)
    assert boot.shape == (5, 3, k), f"bootstrap has shape {tuple(boot.shape)}; expected (5, 3, {k})"
    assert head.weights(a_type).shape == (5, 3, k), "weights must be (..., K)"
    taken.sum().backward()
    assert s.grad is not None and torch.isfinite(s.grad).all(), "no finite gradient reaches the state"


def toy_table(n_train: int = 6, n_hard: int = 3, feature_dim: int = 16, *, seed: int = 0, n_simple: int = 0) -> Any:
    """An :class:`~uevavd.table.ObservationTable` where recognisability is
    learnable: each scene has a random "good" region of views (near a random viewpoint)
    whose probabilities favour the true class, and the features encode the view's
    position and a noisy recognisability signal. For tests and development only.
    Scenes are listed train, hard, then ``n_simple`` simple ones (the paper's third split;
    none by default, which leaves the tables of earlier versions unchanged)."""
    rng = np.random.default_rng(seed)
    s = n_train + n_hard + n_simple
    xyz = view_coords(np.arange(N_VIEWS)) / 50.0  # (605, 3)
    targets = rng.integers(0, 5, s)
    feats = np.zeros((s, N_VIEWS, feature_dim), np.float32)
    probs = np.zeros((s, N_VIEWS, 5), np.float32)
    boxes = np.zeros((s, N_VIEWS, 4), np.float32)
    for i in range(s):
        centre = xyz[rng.integers(N_VIEWS)]
        dist = np.linalg.norm(xyz - centre, axis=1)
        good = np.exp(-(dist**2) / 0.5)  # (605,) in (0, 1]
        p_true = 0.05 + 0.9 * good * (rng.random(N_VIEWS) > 0.1)
        rest = (1 - p_true)[:, None] * rng.dirichlet(np.ones(4), N_VIEWS)
        probs[i] = np.insert(rest, 0, 0.0, axis=1)
        probs[i][:, 0] = 0.0
        cls = [c for c in range(5) if c != targets[i]]
        probs[i][:, targets[i]] = p_true
        probs[i][:, cls] = rest
        feats[i, :, :3] = xyz
        feats[i, :, 3] = good + 0.1 * rng.standard_normal(N_VIEWS)
        feats[i, :, 4:] = 0.3 * rng.standard_normal((N_VIEWS, feature_dim - 4))
        w = 0.1 + 0.2 * good
        boxes[i] = np.stack([0.5 - w / 2, 0.5 - w / 2, 0.5 + w / 2, 0.5 + w / 2], axis=1)
    splits = ["train"] * n_train + ["hard"] * n_hard + ["simple"] * n_simple
    return ObservationTable.from_arrays(
        feats, probs, boxes, scenes=[f"toy{i:03d}" for i in range(s)], targets=targets.tolist(),
        splits=splits, contexts=list(range(1, s + 1)), config={"toy": seed, "feature_dim": feature_dim},
    )


#: Method overrides that make a run tiny (networks of 16-24 units, 16 environments, epochs of
#: 100 episodes, one evaluated context): for tests on :func:`toy_table` (feature_dim 8).
SMALL_RUN = {
    "state.input_dim": 24, "state.box_dim": 8, "state.state_dim": 16,
    "head.hidden": 16, "train.n_envs": 16, "train.batch_size": 8, "train.buffer_episodes": 400,
    "train.learning_starts": 40, "train.updates_per_step": 1.0, "train.target_update": 5,
    "train.epoch_episodes": 100, "train.eval_contexts": 1, "train.threads": 1,
}


def small_run(method: str) -> dict[str, Any]:
    """:data:`SMALL_RUN` for ``method``; the GRU methods' hidden size too."""
    return {**SMALL_RUN, **({"state.hidden": 16} if method != "map" else {})}

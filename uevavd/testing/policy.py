"""Contract checks for ``state`` and ``head`` plugins, and a small learnable toy table.

    from uevavd.testing import check_state_estimator, check_head
    check_state_estimator(my_pkg.build_lstm(feature_dim=16))
    check_head(my_pkg.build_my_head(state_dim=32))
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..data.grid import N_VIEWS, view_coords
from ..policy.contract import ComponentError, check_estimator_rules, check_head_rules
from ..table import ObservationTable


def check_state_estimator(est: Any, *, batch: int = 3, steps: int = 4) -> None:
    """Shapes, causality (s_t never reads o_{>t}), the memory at an episode start (zeros),
    and step() agreeing with forward(): the rules `uevavd train` checks before a run
    (:func:`uevavd.policy.contract.check_estimator_rules`), as an ``AssertionError``."""
    try:
        check_estimator_rules(est, batch=batch, steps=steps, what=f"state estimator {type(est).__name__}")
    except ComponentError as exc:
        raise AssertionError(str(exc)) from None


def check_head(head: Any, *, state_dim: int | None = None, n_types: int = 7, n_ranges: int = 4) -> None:
    """forward/greedy/taken/bootstrap/weights shapes, masks respected, gradients flow: the
    rules `uevavd train` checks (:func:`uevavd.policy.contract.check_head_rules`)."""
    try:
        check_head_rules(head, state_dim=int(state_dim or head.state_dim), n_types=n_types, n_ranges=n_ranges,
                         what=f"head {type(head).__name__}")
    except ComponentError as exc:
        raise AssertionError(str(exc)) from None


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

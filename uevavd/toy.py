"""A small learnable observation table, for tests, plugin checks and development only.

Below the env layer, so that the checks a command runs before any work (a plugin's baseline
evaluated on it) can build one; :mod:`uevavd.testing` re-exports it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .data.grid import N_VIEWS, view_coords
from .table import ObservationTable


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

"""Small observation tables for the env tests (real ObservationTable, random contents)."""

from __future__ import annotations

import numpy as np
import pytest

from uevavd.data.grid import N_VIEWS
from uevavd.table import ObservationTable


def make_table(
    n_scenes: int = 4,
    dim: int = 8,
    seed: int = 0,
    splits: tuple[str, ...] | None = None,
    probs: np.ndarray | None = None,
) -> ObservationTable:
    """A table of ``n_scenes`` scenes with random features, boxes and peaked probabilities."""
    rng = np.random.default_rng(seed)
    splits = splits or tuple(("train", "simple", "hard")[i % 3] for i in range(n_scenes))
    if probs is None:
        logits = rng.normal(0, 2.0, (n_scenes, N_VIEWS, 5))
        probs = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    lo = rng.uniform(0, 0.5, (n_scenes, N_VIEWS, 2))
    boxes = np.concatenate([lo, lo + rng.uniform(0, 0.5, lo.shape)], -1)
    return ObservationTable.from_arrays(
        rng.normal(size=(n_scenes, N_VIEWS, dim)),
        probs,
        boxes,
        scenes=[f"{i + 1:03d}" for i in range(n_scenes)],
        contexts=list(range(1, n_scenes + 1)),
        targets=[i % 5 for i in range(n_scenes)],
        splits=splits,
        visible=rng.uniform(0, 1, (n_scenes, N_VIEWS)),
    )


@pytest.fixture
def table() -> ObservationTable:
    return make_table(6, splits=("train", "train", "train", "simple", "hard", "hard"))

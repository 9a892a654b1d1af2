"""Checkpoints of training runs: written atomically, read with ``weights_only=True``.

A checkpoint is a dict of tensors and plain values (``torch.save``): ``meta`` (what it
belongs to: method, spec hash, table key, feature size, action space), the online and
target networks, the optimizer, the replay buffer, the environment's state, the RNG
states, the running episodes and the loop counters. Loading checks ``meta`` against the
run's settings and refuses a checkpoint of another method or other spaces, naming what
differs.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch

#: Settings a checkpoint must agree on with the run that loads it.
META_KEYS = ("method", "spec_hash", "table_key", "feature_dim", "n_types", "n_ranges", "t_max", "state", "head")


class CheckpointError(ValueError):
    """A checkpoint is unreadable or belongs to another method, table or action space."""


def checkpoint_meta(settings: dict[str, Any]) -> dict[str, Any]:
    return {k: settings.get(k) for k in META_KEYS}


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """``torch.save`` to a temp file in the same folder, fsync, then ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike[str], *, expect: dict[str, Any] | None = None) -> dict[str, Any]:
    """Load a checkpoint (CPU tensors). With ``expect`` (a run's settings), refuse one whose
    method, spec, table or spaces differ, listing each difference."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint there (train first with `uevavd train`)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means unreadable
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc}); delete it to start over") from None
    if not isinstance(state, dict) or "meta" not in state:
        raise CheckpointError(f"{path}: not a uevavd training checkpoint (no meta)")
    if expect is not None:
        want = checkpoint_meta(expect)
        diffs = [f"{k}: checkpoint has {state['meta'].get(k)!r}, expected {v!r}"
                 for k, v in want.items() if state["meta"].get(k) != v]
        if diffs:
            raise CheckpointError(f"{path} belongs to another configuration: " + "; ".join(diffs))
    return state

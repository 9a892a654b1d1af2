"""Checkpoints of training runs: written atomically, read with ``weights_only=True``.

A checkpoint is a dict of tensors and plain values (``torch.save``): ``meta`` (what it
belongs to: method, spec hash, table key, feature size, action space), the online and
target networks, the optimizer, the replay buffer, the environment's state, the RNG
states, the running episodes and the loop counters. Loading checks ``meta`` against the
run's settings and refuses a checkpoint of another method or other spaces, naming what
differs.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_write

#: What a checkpoint's network must agree on with whoever loads it (method, table, spaces).
ARCH_KEYS = ("method", "spec_hash", "table_key", "feature_dim", "n_types", "n_ranges", "t_max", "state", "head")
#: What a run must agree on to *resume* from a checkpoint: a checkpoint of another seed,
#: other training settings, another torch thread count or another uevavd version would
#: resume into a run that differs from an uninterrupted one.
META_KEYS = (*ARCH_KEYS, "seed", "train", "env", "threads", "uevavd")


class CheckpointError(ValueError):
    """A checkpoint is unreadable or belongs to another method, table or action space."""


def checkpoint_meta(settings: dict[str, Any]) -> dict[str, Any]:
    meta = {k: settings.get(k) for k in META_KEYS}
    meta["uevavd"] = (settings.get("versions") or {}).get("uevavd")
    return meta


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """``torch.save`` to a temp file in the same folder, fsync, then ``os.replace``."""
    try:
        return atomic_write(path, lambda f: torch.save(state, f), fsync=True)
    except RuntimeError as exc:
        if "unexpected pos" in str(exc) or "write" in str(exc).lower():  # torch's words for a failed write
            raise OSError(errno.ENOSPC, "could not write the checkpoint (disk full?): free space and rerun; "
                          "the previous checkpoint is intact", str(path)) from None
        raise


def load_checkpoint(path: str | os.PathLike[str], *, expect: dict[str, Any] | None = None,
                    keys: tuple[str, ...] = META_KEYS) -> dict[str, Any]:
    """Load a checkpoint (CPU tensors). With ``expect`` (a run's settings), refuse one that
    differs in ``keys`` (default: everything a resume must share; :data:`ARCH_KEYS` for
    loading the network alone), listing each difference."""
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
        diffs = [f"{k}: checkpoint has {state['meta'].get(k)!r}, expected {want[k]!r}"
                 for k in keys if state["meta"].get(k) != want[k]]
        if diffs:
            raise CheckpointError(f"{path} belongs to another configuration: " + "; ".join(diffs))
    return state

"""A training run's directory: the one place that names its files.

==========================  =====================================================================
``settings.json``           what the run is: method, spec hash, table, seed, training and env
                            settings, torch threads (checked on resume)
``method.toml``             the resolved method spec
``checkpoint.pt``           the latest checkpoint (networks, optimizer, replay, RNG states, loop)
``evals.jsonl``             one row per (epoch, split) evaluation
``done.json``               written last: the run finished (counts, wall time, final evaluation)
``policy.safetensors``      the shareable policy: the network and its method, no replay buffer
``final_eval.json``         an ablation's exhaustive evaluation of the final policy (a cache)
``tb/``                     TensorBoard scalars
==========================  =====================================================================
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunDir:
    """The files of the run directory at ``path``."""

    path: Path

    def __init__(self, path: str | os.PathLike[str]) -> None:
        object.__setattr__(self, "path", Path(path))

    @property
    def settings(self) -> Path:
        return self.path / "settings.json"

    @property
    def method(self) -> Path:
        return self.path / "method.toml"

    @property
    def checkpoint(self) -> Path:
        return self.path / "checkpoint.pt"

    @property
    def evals(self) -> Path:
        return self.path / "evals.jsonl"

    @property
    def done(self) -> Path:
        return self.path / "done.json"

    @property
    def policy(self) -> Path:
        return self.path / "policy.safetensors"

    @property
    def final_eval(self) -> Path:
        return self.path / "final_eval.json"

    @property
    def tensorboard(self) -> Path:
        return self.path / "tb"

    @property
    def finished(self) -> bool:
        return self.done.is_file()

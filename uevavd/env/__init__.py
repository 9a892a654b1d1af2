"""The AOD environment layer: the CMDP of docs/environment.md over an observation table.

Public API (kept stable for ``uevavd.state`` / ``uevavd.policy``):

* :class:`EnvConfig` - episode and reward constants (``[env]`` section of a method TOML)
* :class:`AODEnv` - ``gymnasium.Env``, registered as ``"uevavd/AOD-v0"`` on import of
  this package (``gymnasium.make("uevavd/AOD-v0", table=..., split="train")``);
  :class:`DiscreteActions` turns its ``MultiDiscrete([7, A])`` into ``Discrete(7 * A)``;
  :class:`MaskedFlatObservation` gives ``{"obs", "mask"}`` for libraries that read ``obs.mask``
* :class:`BatchedAODEnv` - N episodes in lockstep as torch tensors, auto-reset
* :func:`evaluate_policy` / :class:`EvalResult` - exhaustive evaluation (every context
  of a split x every start view), with :class:`RandomPolicy`, :class:`PassivePolicy`
  and :class:`OraclePolicy` (dynamic programming upper bound) as baselines

Heavy modules (torch) load only when their names are first used.
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium as gym

from .config import EnvConfig, EnvConfigError

ENV_ID = "uevavd/AOD-v0"
"""The Gymnasium id :func:`register` registers (``gym.make(ENV_ID, table=...)``)."""
IMPORTABLE_ID = f"uevavd.env:{ENV_ID}"
"""The id with its module, which Gymnasium imports before it makes the env: what a process that
never imported uevavd takes (RLlib's env runners, Ray tasks, subprocess vector envs)."""

_LAZY = {
    "AODEnv": "aod_env",
    "load_table": ".table",  # one package up: the table layer
    "select_scenes": ".table",
    "DiscreteActions": "wrappers",
    "MaskedFlatObservation": "wrappers",
    "BatchedAODEnv": "batched",
    "AODVectorEnv": "vector",
    "evaluate_policy": "evaluate",
    "EvalResult": "evaluate",
    "RandomPolicy": "baselines",
    "PassivePolicy": "baselines",
    "OraclePolicy": "oracle",
    "flat_dataset": "offline",
    "flat_observation": "offline",
    "FlatPolicy": "offline",
    "oracle_values": "oracle",
    "flight_pays": "oracle",
    "rule_values": "rule_values",
    "departure_ceiling": "rule_values",
    "RuleSolution": "rule_values",
}

__all__ = ["ENV_ID", "IMPORTABLE_ID", "EnvConfig", "EnvConfigError", "register", *_LAZY]


def register() -> None:
    """Register ``uevavd/AOD-v0`` with gymnasium (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="uevavd.env.aod_env:AODEnv",
                     vector_entry_point="uevavd.env.vector:make_vector_env")


register()


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Baseline policies under the evaluation protocol of :mod:`uevavd.env.evaluate`.

Both implement ``reset(n)`` / ``act(obs) -> (a_type (n,), a_range (n,))`` and read no
features (``needs_features = False``).
"""

from __future__ import annotations

import torch

from ..data.grid import STOP
from ..plugins.manager import manager
from .evaluate import evaluate_policy
from .oracle import OraclePolicy
from .visibility_oracle import VisibilityOraclePolicy


class RandomPolicy:
    """Uniform over the *distinct allowed* actions of the current view.

    Allowed = the observation's ``mask`` (moves that are not clamped) plus stop, which
    counts once (not once per range: stop ignores its range). With ``masked=False`` it is
    uniform over the distinct actions of the whole space: 6 * A moves + stop.
    """

    needs_features = False

    def __init__(self, seed: int = 0, *, masked: bool = True) -> None:
        self.seed = int(seed)
        self.masked = masked
        self._gen: torch.Generator | None = None

    def reset(self, n: int) -> None:
        self._gen = None  # re-seeded on the first act, on the observations' device

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        mask = obs["mask"]  # (n, 7, A) bool
        if self._gen is None or self._gen.device != mask.device:
            self._gen = torch.Generator(device=mask.device)
            self._gen.manual_seed(self.seed)
        w = mask.float() if self.masked else torch.ones_like(mask, dtype=torch.float32)
        w[:, STOP, :] = 0.0
        w[:, STOP, 0] = 1.0
        a = w.shape[2]
        flat = torch.multinomial(w.reshape(len(w), -1), 1, generator=self._gen)[:, 0]
        return flat // a, flat % a


class PassivePolicy:
    """Stop at once: classify the first view (no flight)."""

    needs_features = False

    def reset(self, n: int) -> None:
        pass

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        n = obs["view"].shape[0]
        dev = obs["view"].device
        return torch.full((n,), STOP, dtype=torch.int64, device=dev), torch.zeros(n, dtype=torch.int64, device=dev)


def build_random(*, table=None, config=None, seed: int = 0) -> RandomPolicy:
    return RandomPolicy(seed)


def build_passive(*, table=None, config=None, seed: int = 0) -> PassivePolicy:
    return PassivePolicy()


def build_visibility_oracle(*, table, config, seed: int = 0):
    """The visibility oracle, or None for a table without visible fractions."""
    import numpy as np

    if np.isnan(np.asarray(table.visible)).all():
        return None

    return VisibilityOraclePolicy(table, config)


def build_oracle(*, table, config, seed: int = 0):
    return OraclePolicy(table, config)


def baseline_entries() -> list:
    """The registered baselines (:func:`uevavd.plugins.hookspecs.register_baselines`), in
    registration order."""
    return manager.registry.in_order("baseline")


def baseline_names() -> tuple[str, ...]:
    """Names of the registered baselines: the policies the report and the claims never
    count as learned."""
    return tuple(e.name for e in baseline_entries())


def reference_policies(table, config, *, seed: int = 0) -> dict:
    """The baselines every evaluation shows beside a learned policy, by name, in
    registration order (built in: random (``seed``), passive, the visibility oracle where
    the table knows visible fractions, and the class-knowing oracle, an upper bound)."""
    out = {}
    for entry in baseline_entries():
        policy = entry.load()(table=table, config=config, seed=seed)
        if policy is not None:
            out[entry.name] = policy
    return out


def evaluate_beside_baselines(table, split: str, policy, name: str, config, *, device="cpu", baselines: bool = True,
                              contexts=None):
    """``(DataFrame, per-context DataFrame)``: one row per policy (``policy`` as ``name``,
    then :func:`reference_policies` when ``baselines``), each evaluated exhaustively on
    ``split`` (optionally only ``contexts``) under ``config``, with
    :meth:`~uevavd.env.evaluate.EvalResult.summary`'s columns; and ``policy``'s rows per
    context. What ``uevavd evaluate``, ``Run.evaluate`` and the model zoo print."""
    import pandas as pd

    policies = {name: policy, **(reference_policies(table, config) if baselines else {})}
    results = {n: evaluate_policy(table, split, p, config, device=device, contexts=contexts)
               for n, p in policies.items()}
    frame = pd.DataFrame([{"policy": n, **r.summary()} for n, r in results.items()]).set_index("policy")
    return frame, results[name].per_context()

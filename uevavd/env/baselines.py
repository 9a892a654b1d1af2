"""Baseline policies under the evaluation protocol of :mod:`uevavd.env.evaluate`.

Both implement ``reset(n)`` / ``act(obs) -> (a_type (n,), a_range (n,))`` and read no
features (``needs_features = False``).
"""

from __future__ import annotations

import torch

from ..data.grid import STOP


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


def reference_policies(table, config) -> dict:
    """The baselines every evaluation shows beside a learned policy, by name: random (seed 0),
    passive, the visibility oracle (where the table knows visible fractions) and the
    class-knowing oracle (an upper bound)."""
    import numpy as np

    from .oracle import OraclePolicy

    out = {"random": RandomPolicy(0), "passive": PassivePolicy()}
    if not np.isnan(np.asarray(table.visible)).all():
        from .visibility_oracle import VisibilityOraclePolicy

        out["visibility_oracle"] = VisibilityOraclePolicy(table, config)
    out["oracle"] = OraclePolicy(table, config)
    return out


def evaluate_beside_baselines(table, split: str, policy, name: str, config, *, device="cpu", baselines: bool = True,
                              contexts=None):
    """``(DataFrame, per-context DataFrame)``: one row per policy (``policy`` as ``name``,
    then :func:`reference_policies` when ``baselines``), each evaluated exhaustively on
    ``split`` (optionally only ``contexts``) under ``config``, with
    :meth:`~uevavd.env.evaluate.EvalResult.summary`'s columns; and ``policy``'s rows per
    context. What ``uevavd evaluate``, ``Run.evaluate`` and the model zoo print."""
    import pandas as pd

    from .evaluate import evaluate_policy

    policies = {name: policy, **(reference_policies(table, config) if baselines else {})}
    results = {n: evaluate_policy(table, split, p, config, device=device, contexts=contexts)
               for n, p in policies.items()}
    frame = pd.DataFrame([{"policy": n, **r.summary()} for n, r in results.items()]).set_index("policy")
    return frame, results[name].per_context()

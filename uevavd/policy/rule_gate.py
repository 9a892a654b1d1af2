"""The rule gate's answer in training (``train.stop_gate = "rule"``): where departing from
the pose rule pays.

Where the box is hidden the rule gate takes ``pose_seek``'s action; where it is visible the
rule stops, and the gate opens (every action allowed) where a flight now, with the rule
followed after, returns more than stopping. That is the rule's exact advantage on the table
(:func:`uevavd.env.rule_values.rule_values`), an answer an observation-only probe can learn,
unlike the oracle's best reachable return (the "pays" gate's), which assumes what no
observation holds.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..data.grid import STOP
from ..env.baselines import PoseSeekPolicy
from ..env.rule_values import rule_values
from .learner import PaysLabels

#: An advantage counts as a gain above this (the values are float64 sums of float32 rewards).
ADVANTAGE_TOL = 1e-9


class RulePays(PaysLabels):
    """Where departing from the pose rule pays: ``pays[k - 1, s, v]`` is True where some move
    the view allows, taken with k decisions left and the rule (``moves`` moves) followed after,
    returns more than the rule's own action there; ``gain`` (T_max, S', 605) float32, the best
    such move's advantage. With ``ensemble`` K >= 2, ``counts`` (S', K): how often each local
    context is drawn in each member's bootstrap resample of the training contexts (from
    ``seed``, so a resumed run draws the same)."""

    def __init__(self, tensors: Any, moves: int, *, ensemble: int = 0, seed: int = 0) -> None:
        cfg = tensors.config
        sol = rule_values(tensors, "train", PoseSeekPolicy(moves, cfg.max_range))
        allowed = tensors.mask.cpu().numpy()[:, :STOP]  # (605, 6, A): moves the grid does not clamp
        adv = sol.advantage()[:, 1:, :, :STOP]  # (S', T_max, 605, 6, A)
        best = np.where(allowed, adv, -np.inf).max(axis=(-2, -1)).transpose(1, 0, 2)  # (T_max, S', 605)
        self.pays = torch.as_tensor(best > ADVANTAGE_TOL, device=tensors.device)
        self.gain = torch.as_tensor(np.nan_to_num(best, neginf=-2.0).astype(np.float32), device=tensors.device)
        self.local, self.t_max = tensors.local, cfg.t_max
        n = best.shape[1]
        draws = np.random.default_rng(seed).integers(0, n, size=(max(ensemble, 1), n))
        self.counts = torch.as_tensor(np.stack([np.bincount(d, minlength=n) for d in draws], 1),
                                      dtype=torch.float32, device=tensors.device)

    def gains(self, scene: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """scene (B,), views (B, L) of decisions t = 0..L-1 -> (B, L) float32, the best move's
        advantage over the rule (0 where t >= T_max)."""
        return self.per_decision(self.gain, scene, views)

    def weights(self, scene: torch.Tensor) -> torch.Tensor:
        """(N,) table scene indices -> (N, K) each member's count of the row's context."""
        return self.counts[self.local[scene]]

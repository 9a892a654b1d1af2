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
from ..env.baselines import PoseSeekPolicy, pose_seek_moves
from ..env.rule_values import rule_values
from .learner import PaysLabels

#: An advantage counts as a gain above this (the values are float64 sums of float32 rewards).
ADVANTAGE_TOL = 1e-9


def rule_moves(table: Any, config: Any) -> int:
    """``pose_seek``'s number of moves for the rule gate, chosen on ``table``'s training
    contexts under ``config`` (:func:`uevavd.env.baselines.pose_seek_moves`)."""
    return pose_seek_moves(table, config)[0]


class RulePays(PaysLabels):
    """Where departing from the pose rule pays: ``pays[k - 1, s, v]`` is True where some move
    the view allows, taken with k decisions left and the rule (``moves`` moves) followed after,
    returns more than the rule's own action there."""

    def __init__(self, tensors: Any, moves: int) -> None:
        cfg = tensors.config
        sol = rule_values(tensors, "train", PoseSeekPolicy(moves, cfg.max_range))
        allowed = tensors.mask.cpu().numpy()[:, :STOP]  # (605, 6, A): moves the grid does not clamp
        adv = sol.advantage()[:, 1:, :, :STOP]  # (S', T_max, 605, 6, A)
        best = np.where(allowed, adv, -np.inf).max(axis=(-2, -1))  # (S', T_max, 605)
        self.pays = torch.as_tensor((best > ADVANTAGE_TOL).transpose(1, 0, 2).copy(), device=tensors.device)
        self.local, self.t_max = tensors.local, cfg.t_max

"""DAgger with the visibility oracle as the expert (``train.imitation = "visibility_oracle"``).

The student acts as in every run; each decision it took, replayed from the buffer (the
aggregated dataset), is labelled with the expert's action for the steps left: the visibility
oracle's plan from that (scene, view) with T_max set to the decisions that remain
(:func:`uevavd.env.visibility_oracle.visibility_plans`). The labels depend on the table and the
env config alone, so they are computed once per run and a resumed run reads the same ones.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..config_rules import ConfigError
from ..data.grid import N_TYPES, STOP
from ..env.visibility_oracle import visibility_plans


class OracleLabels:
    """``a_type`` / ``a_range`` (T_max, S', 605) int64: the visibility oracle's first action
    from each (local scene, view) of the env's split with k + 1 decisions left, at index k."""

    def __init__(self, tensors: Any) -> None:
        table_visible = tensors.visible  # (S', 605) float, NaN where the data has none
        if np.isnan(table_visible).any():
            raise ConfigError("train.imitation = 'visibility_oracle' needs the visible fraction of every view (the "
                              "synthetic world's tables have it; the real release's do not)")
        cfg = tensors.config
        types, ranges = [], []
        for left in range(1, cfg.t_max + 1):
            a_type, a_range, _ = visibility_plans(table_visible, cfg.replace(t_max=left))
            types.append(a_type[..., 0])
            ranges.append(a_range[..., 0])
        dev = tensors.device
        self.a_type = torch.as_tensor(np.stack(types), device=dev)
        self.a_range = torch.as_tensor(np.stack(ranges), device=dev)
        self.local, self.t_max = tensors.local, cfg.t_max

    def labels(self, scene: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """scene (B,) table indices, views (B, T+1) -> the labels of decisions 0..T-1, (B, T) each."""
        t = torch.arange(self.t_max, device=views.device)
        left = (self.t_max - 1 - t)[None].expand(views.shape[0], -1)
        s = self.local[scene][:, None].expand_as(left)
        return self.a_type[left, s, views[:, :-1]], self.a_range[left, s, views[:, :-1]]


def check_branches(q: tuple[torch.Tensor, ...], n_ranges: int) -> None:
    """Imitation reads a type branch (7) and a range branch (A): a head of another form is refused."""
    if len(q) != 2 or q[0].shape[-1] != N_TYPES or q[1].shape[-1] != n_ranges:
        raise ConfigError(f"train.imitation needs a head with a type branch ({N_TYPES}) and a range branch "
                          f"({n_ranges}), such as dueling_branch; this head gives {[tuple(x.shape) for x in q]}")


def imitation_loss(q: tuple[torch.Tensor, ...], a_type: torch.Tensor, a_range: torch.Tensor, valid: torch.Tensor,
                   weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The cross-entropy of the head's branches at decisions 0..T-1 (``q`` each (B, T+1, n))
    with the labels (B, T), over the ``valid`` decisions (the range's only where the label is a
    move: stop ignores its range), each episode weighted by ``weight`` (B,) (the replay's
    importance weights). Returns (loss, per-episode mean cross-entropy (B,), for the priorities)."""
    q_type, q_range = q[0][:, :-1], q[1][:, :-1]
    ce = F.cross_entropy(q_type.flatten(0, 1), a_type.flatten(), reduction="none").view_as(a_type)
    moves = a_type != STOP
    ce = ce + torch.where(moves, F.cross_entropy(q_range.flatten(0, 1), a_range.flatten(), reduction="none")
                          .view_as(a_range), 0.0)
    w = valid.float()
    per_episode = (ce * w).sum(1) / w.sum(1).clamp_min(1.0)
    loss = (ce * w * weight[:, None]).sum() / w.sum().clamp_min(1.0)
    return loss, per_episode.detach()

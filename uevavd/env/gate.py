"""The stop gate: "stop wherever the target's box is non-empty".

A rule that reads the observation alone (its ``box``, XYXY normalised to [0, 1], zeros where
the target is fully occluded), never the table's true visibility. It is used three ways:

* :class:`StopGate` wraps any policy of the evaluation protocol (``reset(n)``, ``act(obs)``):
  where the box is non-empty the wrapped policy's action is replaced by stop. Every
  evaluation reports a learned policy's return behind it (the "gated" column).
* :func:`gate_mask` narrows an action mask so that only stop is allowed where the box is
  non-empty: the gate inside training (``train.stop_gate = "box"``), where the agent's
  greedy and random actions and its TD targets all see the narrowed mask.
* :class:`uevavd.env.baselines.BoxGatePolicy`, the scripted baseline ``box_gate``.
"""

from __future__ import annotations

from typing import Any

import torch

from ..data.grid import STOP


def box_visible(box: torch.Tensor) -> torch.Tensor:
    """(..., 4) observed boxes -> (...,) bool: True where the box is non-empty (the target
    is at least partly visible in the observation)."""
    return (box != 0).any(dim=-1)


def gate_mask(mask: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """(..., 7, A) action mask, (..., 4) boxes -> the mask with every move blocked where the
    box is non-empty (stop, always allowed, stays allowed). A new tensor."""
    gated = mask.clone()
    vis = box_visible(box)
    moves = gated[..., :STOP, :]
    moves[vis] = False
    return gated


def fit_to_mask(mask: torch.Tensor, a_type: torch.Tensor, a_range: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Actions kept to the (n, 7, A) action mask, (n,) int64 each: a move the mask forbids (the
    grid's edge would clamp it) becomes the longest allowed range of its type, or stop where no
    range of it is allowed; stop's range is 0. The scripted box gate and the offline flat policy
    keep to the mask by this one rule."""
    allowed = mask[torch.arange(len(a_type), device=mask.device), a_type].sum(-1)  # a prefix 0..k-1 of ranges
    fly = (a_type != STOP) & (allowed > 0)
    return torch.where(fly, a_type, STOP), torch.where(fly, torch.minimum(a_range, allowed - 1), 0)


class StopGate:
    """``policy`` behind the stop gate: its action wherever the observed box is empty,
    stop (range 0) wherever it is not. The wrapped policy still sees every observation, so a
    recurrent policy's memory advances as it would ungated."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    @property
    def needs_features(self) -> bool:
        return getattr(self.policy, "needs_features", True)

    @property
    def features_key(self) -> str | None:
        """The wrapped policy's (see :mod:`uevavd.env.evaluate`)."""
        return getattr(self.policy, "features_key", None)

    def reset(self, n: int) -> None:
        """Reset the gated policy for ``n`` new episodes."""
        self.policy.reset(n)

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The gated policy's action, replaced by stop wherever the gate is open (the box in view)."""
        a_type, a_range = self.policy.act(obs)
        a_type = torch.as_tensor(a_type, device=obs["box"].device)
        a_range = torch.as_tensor(a_range, device=obs["box"].device)
        vis = box_visible(obs["box"])
        return torch.where(vis, STOP, a_type), torch.where(vis, 0, a_range)

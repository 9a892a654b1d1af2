"""The Q network of a method: state estimator (``state`` plugin) + head (``head`` plugin)."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..config import Component
from ..data.grid import DEFAULT_MAX_RANGE, N_TYPES


class QNetwork(nn.Module):
    """s_t = estimator(o_1..o_t); Q = head(s_t).

    ``forward`` reads whole episodes (B, T, D) / (B, T, 4) float32 and returns the head's
    branch tuple, each (B, T, n); ``step`` acts one decision from a carried memory.
    """

    def __init__(self, estimator: nn.Module, head: nn.Module) -> None:
        super().__init__()
        if getattr(head, "state_dim", estimator.state_dim) != estimator.state_dim:
            raise ValueError(
                f"head expects state_dim={head.state_dim} but the state estimator gives "
                f"{estimator.state_dim}; set head.state_dim = state.state_dim in the method config"
            )
        self.estimator, self.head = estimator, head

    @property
    def recurrent(self) -> bool:
        return bool(self.estimator.recurrent)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.head(self.estimator(features, boxes))

    def initial_hidden(self, n: int, device: torch.device | str = "cpu") -> torch.Tensor:
        return self.estimator.initial_hidden(n, device)

    def step(
        self, features: torch.Tensor, boxes: torch.Tensor, hidden: torch.Tensor
    ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        s, hidden = self.estimator.step(features, boxes, hidden)
        return self.head(s), hidden


def build_network(state: Component, head: Component, feature_dim: int, *, n_types: int = N_TYPES,
                  n_ranges: int = DEFAULT_MAX_RANGE) -> QNetwork:
    """The Q network of a method's ``state`` and ``head`` sections (``spec.state``,
    ``spec.head``): the estimator built for the table's feature size, the head for its
    state size (unless the head section sets ``state_dim``) and the action space."""
    estimator = state.build(feature_dim=feature_dim)
    head_kwargs: dict[str, Any] = {"n_types": n_types, "n_ranges": n_ranges}
    if "state_dim" not in head.kwargs:
        head_kwargs["state_dim"] = estimator.state_dim
    return QNetwork(estimator, head.build(**head_kwargs))

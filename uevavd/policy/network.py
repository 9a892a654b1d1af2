"""The Q network of a method: state estimator (``state`` plugin) + head (``head`` plugin)."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..config import Component
from ..data.grid import DEFAULT_MAX_RANGE, N_TYPES, STOP
from ..env.gate import gate_mask
from .config import STOP_GATES


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
        self.stop_gate, self.stop_threshold = "none", 0.5
        self.stop_probe: nn.Linear | None = None

    def set_stop_gate(self, kind: str, threshold: float = 0.5) -> QNetwork:
        """Give the network its stop gate (:data:`STOP_GATES`); "learned" and "pays" add the
        gate's probe, a linear layer on s_t (its weights are part of the network and of its
        policy file).
        Call it where the network is built, before its weights are loaded. Returns self."""
        if kind not in STOP_GATES:
            raise ValueError(f"stop gate {kind!r}: expected one of {STOP_GATES}")
        self.stop_gate, self.stop_threshold = kind, float(threshold)
        self.stop_probe = nn.Linear(self.estimator.state_dim, 1) if kind in ("learned", "pays") else None
        return self

    def q_parameters(self) -> list[nn.Parameter]:
        """The parameters the TD loss trains: all but the stop probe's (trained on its own)."""
        return [p for n, p in self.named_parameters() if not n.startswith("stop_probe.")]

    def stop_probability(self, s: torch.Tensor) -> torch.Tensor:
        """(N, state_dim) -> (N,) the gate's probe's probability: that the recognizer recognises
        the current view ("learned"), that a flight pays from it ("pays")."""
        assert self.stop_probe is not None, "the network has no probe (train.stop_gate is not 'learned' or 'pays')"
        return torch.sigmoid(self.stop_probe(s)[..., 0])

    def allowed(self, mask: torch.Tensor, box: torch.Tensor, s: torch.Tensor | None = None, *,
                training: bool = False, pays: torch.Tensor | None = None) -> torch.Tensor:
        """The (..., 7, A) action mask narrowed by the stop gate: where it closes, only stop is
        allowed. ``box`` (..., 4) the observed boxes; ``s`` (..., state_dim) the states, read
        by the learned and the "pays" gates when acting greedily (``training`` False);
        ``pays`` (...) bool, where a flight pays, which opens the "pays" gate in training."""
        if self.stop_gate == "box":
            return gate_mask(mask, box)
        if self.stop_gate == "pays":
            if training:
                opened = pays
            else:
                opened = None if s is None else self.stop_probability(s) > self.stop_threshold
            gated = gate_mask(mask, box)
            return gated if opened is None else torch.where(opened[..., None, None], mask, gated)
        if self.stop_gate == "learned" and not training and s is not None:
            gated = mask.clone()
            gated[..., :STOP, :][self.stop_probability(s) > self.stop_threshold] = False
            return gated
        return mask

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

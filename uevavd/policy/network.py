"""The Q network of a method: state estimator (``state`` plugin) + head (``head`` plugin)."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..config import Component
from ..data.grid import DEFAULT_MAX_RANGE, N_TYPES, STOP
from ..env.baselines import pose_seek_hidden
from ..env.gate import box_visible, gate_mask
from .config import STOP_GATES

#: The gates that narrow the mask in training too (its actions and TD targets), and those of
#: them a probe trained on where a flight pays opens in acting.
TRAINING_GATES = ("box", "pays", "rule")
PROBED_GATES = ("pays", "rule")

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
        self.rule_ensemble, self.rule_margin = 0, 0.0
        self.stop_probe: nn.Linear | None = None

    def set_stop_gate(self, kind: str, threshold: float = 0.5, *, ensemble: int = 0, margin: float = 0.0) -> QNetwork:
        """Give the network its stop gate (:data:`STOP_GATES`); "learned", "pays" and "rule" add
        the gate's probe, a linear layer on s_t (its weights are part of the network and of its
        policy file); "rule" also holds the pose rule's number of moves (``rule_moves``, a buffer
        of the policy file, set by the trainer from the training contexts), and with ``ensemble``
        K >= 2 its probe is K regressors of a departure's advantage, opening where the smallest
        exceeds ``margin`` (``train.rule_ensemble``, ``train.rule_margin``).
        Call it where the network is built, before its weights are loaded. Returns self."""
        if kind not in STOP_GATES:
            raise ValueError(f"stop gate {kind!r}: expected one of {STOP_GATES}")
        if ensemble and kind != "rule":
            raise ValueError(f"a probe ensemble ({ensemble}) is the rule gate's: the stop gate is {kind!r}")
        self.stop_gate, self.stop_threshold = kind, float(threshold)
        self.rule_ensemble, self.rule_margin = int(ensemble), float(margin)
        width = max(1, self.rule_ensemble)
        self.stop_probe = nn.Linear(self.estimator.state_dim, width) if kind in ("learned", "pays", "rule") else None
        if kind == "rule":
            self.register_buffer("rule_moves", torch.zeros((), dtype=torch.int64))
        return self

    def q_parameters(self) -> list[nn.Parameter]:
        """The parameters the TD loss trains: all but the stop probe's (trained on its own)."""
        return [p for n, p in self.named_parameters() if not n.startswith("stop_probe.")]

    def stop_probability(self, s: torch.Tensor) -> torch.Tensor:
        """(N, state_dim) -> (N,) the gate's probe's probability: that the recognizer recognises
        the current view ("learned"), that a flight pays from it ("pays"), that departing from the
        pose rule pays ("rule")."""
        assert self.stop_probe is not None, "the network has no probe (train.stop_gate is 'none' or 'box')"
        return torch.sigmoid(self.stop_probe(s)[..., 0])

    def opens(self, s: torch.Tensor) -> torch.Tensor:
        """(N, state_dim) -> (N,) bool: where the "pays" or "rule" gate opens in greedy acting,
        its probe's probability above the threshold, or the ensemble's lowest advantage above
        the margin."""
        if self.rule_ensemble:
            return self.stop_probe(s).amin(-1) > self.rule_margin
        return self.stop_probability(s) > self.stop_threshold

    def allowed(self, mask: torch.Tensor, box: torch.Tensor, s: torch.Tensor | None = None, *,
                training: bool = False, pays: torch.Tensor | None = None, view: torch.Tensor | None = None,
                t: torch.Tensor | None = None) -> torch.Tensor:
        """The (..., 7, A) action mask narrowed by the stop gate: where it closes, only stop is
        allowed. ``box`` (..., 4) the observed boxes; ``s`` (..., state_dim) the states, read
        by the learned, "pays" and "rule" gates when acting greedily (``training`` False);
        ``pays`` (...) bool, where a flight (a departure from the rule) pays, which opens the
        "pays" ("rule") gate in training; ``view`` and ``t`` (...) the views and steps, which
        the "rule" gate reads for the pose rule's action where the box is hidden."""
        if self.stop_gate == "box":
            return gate_mask(mask, box)
        if self.stop_gate in PROBED_GATES:
            if training:
                opened = pays
            else:
                opened = None if s is None else self.opens(s)
            gated = gate_mask(mask, box)
            gated = gated if opened is None else torch.where(opened[..., None, None], mask, gated)
            if self.stop_gate == "pays":
                return gated
            if view is None or t is None:
                raise ValueError('the "rule" stop gate reads the views and steps: pass view= and t=')
            rule = torch.zeros(mask.shape, dtype=torch.bool, device=mask.device)  # the pose rule's one action where the box is hidden
            a_type, a_range = pose_seek_hidden(view, t, self.rule_moves, mask.shape[-1])
            rule.view(-1, *mask.shape[-2:])[torch.arange(a_type.numel(), device=mask.device),
                                           a_type.reshape(-1), a_range.reshape(-1)] = True
            return torch.where(box_visible(box)[..., None, None], gated, rule)
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

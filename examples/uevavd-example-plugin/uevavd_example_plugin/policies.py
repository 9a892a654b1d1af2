"""The example plugin's policy components: an LSTM state estimator and a baseline.

Builders are keyword-only. uevavd passes a state builder ``feature_dim`` (the table's feature
size) beside the method file's keys, and the shipped presets set ``input_dim`` and
``state_dim``; it passes a baseline builder ``table``, ``config`` and ``seed``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from uevavd.data.grid import STOP
from uevavd.env.baselines import RandomPolicy
from uevavd.state.base import ObservationEncoder


class LSTMState(nn.Module):
    """h_t, c_t = LSTM(g_t, (h_{t-1}, c_{t-1})) from zeros at the episode start; s_t = ReLU(Linear(h_t)).

    uevavd carries an estimator's memory as one 2-D tensor (N, H) and starts every episode
    from zeros, so the LSTM's two states travel side by side: memory = [h, c] (N, 2 x hidden).
    """

    recurrent = True

    def __init__(self, feature_dim: int, input_dim: int, box_dim: int, hidden: int, state_dim: int) -> None:
        super().__init__()
        self.feature_dim, self.hidden_dim, self.state_dim = feature_dim, hidden, state_dim
        self.encoder = ObservationEncoder(feature_dim, input_dim - box_dim, box_dim)
        self.lstm = nn.LSTM(input_dim, hidden, batch_first=True)
        self.out = nn.Linear(hidden, state_dim)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """(B, T, D), (B, T, 4) -> (B, T, state_dim), causal: the LSTM reads left to right."""
        h, _ = self.lstm(self.encoder(features, boxes))
        return torch.relu(self.out(h))

    def initial_hidden(self, n: int, device: torch.device | str = "cpu") -> torch.Tensor:
        return torch.zeros(n, 2 * self.hidden_dim, device=device)

    def step(self, features: torch.Tensor, boxes: torch.Tensor, hidden: torch.Tensor):
        h0, c0 = hidden.split(self.hidden_dim, dim=-1)
        y, (h, c) = self.lstm(self.encoder(features, boxes)[:, None], (h0[None].contiguous(), c0[None].contiguous()))
        return torch.relu(self.out(y[:, 0])), torch.cat([h[0], c[0]], dim=-1)


def build_lstm(*, feature_dim: int, input_dim: int = 544, box_dim: int = 32, hidden: int | None = None,
               state_dim: int = 512) -> LSTMState:
    hidden = input_dim if hidden is None else hidden
    for key, value in (("input_dim", input_dim), ("box_dim", box_dim), ("hidden", hidden), ("state_dim", state_dim)):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"state.{key} = {value!r}: expected an integer >= 1")
    if input_dim <= box_dim:
        raise ValueError(f"state.input_dim = {input_dim} must exceed state.box_dim = {box_dim} (g_t = image + box)")
    return LSTMState(feature_dim, input_dim, box_dim, hidden, state_dim)


class ConfidentStop:
    """Stop where the recognizer is confident (its top probability on the current view
    reaches the run's ``thre``); elsewhere take one random allowed action. Reads the
    recognizer's probabilities per view from the table (``table.probs`` (S, 605, 5))."""

    needs_features = False

    def __init__(self, probs: torch.Tensor, thre: float, seed: int) -> None:
        self.confident = probs.max(dim=-1).values >= thre  # (S, 605) bool
        self.moves = RandomPolicy(seed)

    def reset(self, n: int) -> None:
        self.moves.reset(n)

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        confident = self.confident.to(obs["view"].device)[obs["scene"], obs["view"]]
        a_type, a_range = self.moves.act(obs)
        return torch.where(confident, STOP, a_type), torch.where(confident, 0, a_range)


def build_confident_stop(*, table, config, seed: int = 0) -> ConfidentStop:
    return ConfidentStop(torch.from_numpy(np.asarray(table.probs, dtype=np.float32)), float(config.thre), seed)

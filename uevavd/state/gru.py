"""Memo-MAP / IBE-MAP's state estimator: a GRU over the episode's observations."""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ..config_rules import check_flag, check_widths
from .base import ObservationEncoder, check_recognizer
from .packed_gru import packed_gru, supports_packed


class GRUState(nn.Module):
    """h_t = GRU(g_t, h_{t-1}) from h_0 = 0 at the episode start; s_t = ReLU(Linear(h_t)).

    (B, T, D), (B, T, 4) -> (B, T, state_dim); sequences must start at the episode start.
    """

    recurrent = True

    def __init__(self, feature_dim: int, input_dim: int, box_dim: int, hidden: int, state_dim: int,
                 pose_dim: int = 0, image: bool = True, recognizer: bool = False) -> None:
        super().__init__()
        if input_dim <= box_dim:
            raise ValueError(f"input_dim={input_dim} must exceed box_dim={box_dim} (g_t = image + box)")
        self.feature_dim, self.hidden_dim, self.state_dim, self.pose = feature_dim, hidden, state_dim, pose_dim > 0
        self.encoder = ObservationEncoder(feature_dim, input_dim - box_dim, box_dim, pose_dim, image, recognizer)
        self.gru = nn.GRU(input_dim + pose_dim, hidden, batch_first=True)
        self.out = nn.Linear(hidden, state_dim)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        h, _ = self.gru(self.encoder(features, boxes))
        return torch.relu(self.out(h))

    def forward_packed(self, features: torch.Tensor, boxes: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """s_t of the observations episodes really had: ``seen`` (B, T) bool, True on a
        prefix of each row (o_0..o_L); ``features`` (N, D) / ``boxes`` (N, 4) those rows in
        ``seen.nonzero()`` order -> (N, state_dim), same order. Equals ``forward`` on the
        padded batch at the seen positions, without computing the padding (and, with the
        built-in GRU, without W_hh h_0 = 0: see :mod:`uevavd.state.packed_gru`)."""
        g = self.encoder(features, boxes)
        # On CPU the hand-written unroll is faster than ATen's packed GRU (see packed_gru);
        # on a GPU cuDNN's fused GRU stays in charge (not measured against it here)
        if g.device.type == "cpu" and supports_packed(self.gru):
            return torch.relu(self.out(packed_gru(self.gru, g, seen)))
        from torch.nn.utils.rnn import pack_padded_sequence, pad_packed_sequence

        b, t = seen.shape
        padded = g.new_zeros(b, t, g.shape[-1])
        padded[seen] = g
        lengths = seen.sum(1).cpu()
        packed = pack_padded_sequence(padded, lengths, batch_first=True, enforce_sorted=False)
        h, _ = pad_packed_sequence(self.gru(packed)[0], batch_first=True, total_length=t)
        return torch.relu(self.out(h[seen]))

    def initial_hidden(self, n: int, device: torch.device | str = "cpu") -> torch.Tensor:
        return torch.zeros(n, self.hidden_dim, device=device)

    def step(
        self, features: torch.Tensor, boxes: torch.Tensor, hidden: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.step_encoded(self.encoder(features, boxes), hidden)

    def step_encoded(self, g: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, _ = self.gru(g[:, None], hidden[None].contiguous())
        h = h[:, 0]
        return torch.relu(self.out(h)), h

    # -- the optional InputGateCache capability (uevavd.state.base): evaluation's fast path -----
    @property
    def gate_width(self) -> int:
        return self.gru.weight_ih_l0.shape[0]

    def caches_input_gates(self) -> bool:
        """The built-in cell (one unidirectional layer with biases, this class's own
        ``step_encoded``, a Linear ``out`` with bias): then :meth:`step_from_gates` is
        ``step_encoded`` bit for bit on CPU."""
        return (type(self).step_encoded is GRUState.step_encoded and supports_packed(self.gru)
                and isinstance(self.out, nn.Linear) and self.out.bias is not None)

    def input_gates(self, g: torch.Tensor) -> torch.Tensor:
        return F.linear(g, self.gru.weight_ih_l0, self.gru.bias_ih_l0)

    def step_from_gates(self, gates: torch.Tensor, hidden: torch.Tensor, *, from_zero: bool,
                        buffer: Any) -> tuple[torch.Tensor, torch.Tensor]:
        gru = self.gru
        n, width = hidden.shape
        i_r, i_z, i_n = gates.chunk(3, -1)  # updated in place below
        if from_zero:  # h = 0: W_hh h + b_hh is b_hh exactly, skip the product
            h_r, h_z, h_n = gru.bias_hh_l0.chunk(3)
        else:  # addmm is what F.linear runs; out= only reuses the memory
            gh = torch.addmm(gru.bias_hh_l0, hidden, gru.weight_hh_l0.t(), out=buffer("gh", n, 3 * width))
            h_r, h_z, h_n = gh.chunk(3, -1)
        # ATen's CPU GRU cell, operation for operation and on the same (N, 3H) row layout:
        # sigmoid and tanh round differently in their vectorised and scalar loops, so other
        # layouts (e.g. contiguous (N, H) copies) can change the last bit of h_t
        r = i_r.add_(h_r).sigmoid_()
        z = i_z.add_(h_z).sigmoid_()
        cand = torch.add(i_n, torch.mul(h_n, r, out=buffer("h_n r", n, width)), out=buffer("cand", n, width)).tanh_()
        h = (hidden - cand).mul_(z).add_(cand)  # a fresh tensor: it becomes the stored memory
        s = torch.addmm(self.out.bias, h, self.out.weight.t(), out=buffer("s", n, self.out.weight.shape[0]))
        return s.relu_(), h


def build_gru(
    *, feature_dim: int = 2048, input_dim: int = 544, box_dim: int = 32, hidden: int | None = None,
    state_dim: int = 512, pose: bool = False, pose_dim: int = 32, image: bool = True,
    recognizer: bool = False,
) -> GRUState:
    """The recurrent estimator (paper sizes: g_t 544, h_t 544, s_t 512). ``hidden`` (h_t)
    defaults to ``input_dim``, as in the paper, so scaling g_t scales h_t with it.
    ``feature_dim`` (D of the table) is passed by the trainer at build time. With ``pose``
    (``state.pose``; needs ``env.pose``) g_t gains ``pose_dim`` channels for the viewpoint's pose;
    with ``image`` false (``state.image``) it reads no image features, and with ``recognizer`` as well
    (``state.recognizer``) the recognizer's class probabilities alone (:class:`ObservationEncoder`)."""
    hidden = input_dim if hidden is None else hidden
    check_widths("state", input_dim=input_dim, box_dim=box_dim, hidden=hidden, state_dim=state_dim,
                 **({"pose_dim": pose_dim} if check_flag("state", "pose", pose) else {}))
    return GRUState(feature_dim, input_dim, box_dim, hidden, state_dim, pose_dim if pose else 0,
                    check_flag("state", "image", image), check_recognizer(image, recognizer))

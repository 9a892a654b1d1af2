"""A GRU over packed episodes with a hand-written backward, for replayed training batches.

``nn.GRU`` on packed sequences (CPU) runs each step's cell as separate autograd ops and
multiplies the zero initial memory by W_hh at every episode's first step. Replayed
episodes always start from h_0 = 0, so this unroll skips that product, and its backward
computes dW_hh in one matrix product over all steps instead of one per step. The input
gates W_ih g_t + b_ih stay an ordinary ``F.linear`` over every row (one product, autograd
as usual); only the recurrence is in :class:`_PackedGRUFunction`.

Same equations and gate order (r, z, n) as ``nn.GRU``; agrees with it to float32 rounding
(``tests/state/test_packed_gru.py`` compares outputs and every gradient).
"""

from __future__ import annotations

import torch
from torch import nn


class PackedLayout:
    """Where each observation of a batch of episodes sits in time-major packed order.

    ``seen`` (B, T) bool, True on a prefix of each row (the episode's observations). Rows
    are numbered in ``seen.nonzero()`` order (episode-major). Episodes are sorted by
    length, longest first (stable), so at step t the running ones are a prefix of that
    order: ``batch_sizes[t]`` of them. ``perm[k]`` is the episode-major row of the k-th
    time-major row, and ``prev`` (N - batch_sizes[0],) the time-major row of h_{t-1} for
    every time-major row of a step t >= 1.
    """

    def __init__(self, seen: torch.Tensor) -> None:
        lengths = seen.sum(1)
        order = torch.sort(lengths, descending=True, stable=True).indices
        sorted_len = lengths[order]
        offset = torch.cumsum(lengths, 0) - lengths  # first row of each episode
        t_max = int(sorted_len[0]) if sorted_len.numel() else 0
        steps = torch.arange(t_max, device=seen.device)
        running = sorted_len[None, :] > steps[:, None]  # (T, B) in sorted order
        self.perm = (offset[order][None, :] + steps[:, None])[running]
        self.batch_sizes: list[int] = running.sum(1).tolist()
        starts = [0]
        for bs in self.batch_sizes[:-1]:
            starts.append(starts[-1] + bs)
        self.starts = starts
        prev = [torch.arange(starts[t - 1], starts[t - 1] + bs, device=seen.device)
                for t, bs in enumerate(self.batch_sizes) if t > 0]
        self.prev = torch.cat(prev) if prev else torch.zeros(0, dtype=torch.int64, device=seen.device)


class _PackedGRUFunction(torch.autograd.Function):
    """h_t for every packed row from the input gates ``gi`` (N, 3H) (episode-major rows),
    W_hh (3H, H), b_hh (3H); h_0 = 0. Returns (N, H) in episode-major order."""

    @staticmethod
    def forward(ctx, gi, w_hh, b_hh, layout: PackedLayout):  # type: ignore[override]
        n_rows, h3 = gi.shape
        hid = h3 // 3
        gi_tm = gi.index_select(0, layout.perm)
        h_tm = gi.new_empty(n_rows, hid)
        r_all = gi.new_empty(n_rows, hid)
        z_all = gi.new_empty(n_rows, hid)
        n_all = gi.new_empty(n_rows, hid)
        ghn_all = gi.new_empty(n_rows, hid)
        w_t = w_hh.t()
        for t, (s, bs) in enumerate(zip(layout.starts, layout.batch_sizes, strict=True)):
            g_t = gi_tm[s:s + bs]
            if t == 0:  # h_0 = 0: W_hh h_0 vanishes, only b_hh remains
                gh = b_hh.expand(bs, h3)
            else:
                p = layout.starts[t - 1]
                h_prev = h_tm[p:p + bs]
                gh = torch.addmm(b_hh, h_prev, w_t)
            rz = torch.sigmoid(g_t[:, :2 * hid] + gh[:, :2 * hid])
            r, z = rz[:, :hid], rz[:, hid:]
            ghn = gh[:, 2 * hid:]
            n = torch.tanh(torch.addcmul(g_t[:, 2 * hid:], r, ghn))
            # h_t = (1 - z) n + z h_{t-1}
            h = n - z * n if t == 0 else torch.addcmul(n, z, h_prev - n)
            h_tm[s:s + bs] = h
            r_all[s:s + bs], z_all[s:s + bs], n_all[s:s + bs], ghn_all[s:s + bs] = r, z, n, ghn
        out = torch.empty_like(h_tm)
        out[layout.perm] = h_tm
        ctx.layout = layout
        ctx.save_for_backward(w_hh, h_tm, r_all, z_all, n_all, ghn_all)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        layout: PackedLayout = ctx.layout
        w_hh, h_tm, r_all, z_all, n_all, ghn_all = ctx.saved_tensors
        n_rows, hid = h_tm.shape
        dh_tm = grad_out.index_select(0, layout.perm)  # a copy: accumulated into below
        dgi_tm = grad_out.new_empty(n_rows, 3 * hid)
        dgh_tm = grad_out.new_empty(n_rows, 3 * hid)
        carry = None
        for t in range(len(layout.batch_sizes) - 1, -1, -1):
            s, bs = layout.starts[t], layout.batch_sizes[t]
            dh = dh_tm[s:s + bs]
            if carry is not None:
                dh[:carry.shape[0]] += carry
            r, z, n, ghn = r_all[s:s + bs], z_all[s:s + bs], n_all[s:s + bs], ghn_all[s:s + bs]
            if t == 0:
                dz = -dh * n
            else:
                p = layout.starts[t - 1]
                dz = dh * (h_tm[p:p + bs] - n)
            dn = dh * (1 - z) * (1 - n * n)  # through tanh
            dr = dn * ghn * r * (1 - r)  # through sigmoid
            dz = dz * z * (1 - z)
            dgi = dgi_tm[s:s + bs]
            dgi[:, :hid], dgi[:, hid:2 * hid], dgi[:, 2 * hid:] = dr, dz, dn
            dgh = dgh_tm[s:s + bs]
            dgh[:, :2 * hid] = dgi[:, :2 * hid]
            torch.mul(dn, r, out=dgh[:, 2 * hid:])
            if t > 0:
                carry = torch.addmm(dh * z, dgh, w_hh)
        grad_gi = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_gi = torch.empty_like(dgi_tm)
            grad_gi[layout.perm] = dgi_tm
        if ctx.needs_input_grad[1]:
            b0 = layout.batch_sizes[0]
            grad_w = dgh_tm[b0:].t() @ h_tm.index_select(0, layout.prev)
        if ctx.needs_input_grad[2]:
            grad_b = dgh_tm.sum(0)
        return grad_gi, grad_w, grad_b, None


def packed_gru(gru: nn.GRU, x: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """h_t of a one-layer, unidirectional, biased ``gru`` over episodes from h_0 = 0.

    ``seen`` (B, T) bool, True on a prefix of each row; ``x`` (N, input) the inputs of the
    seen positions in ``seen.nonzero()`` order. Returns (N, hidden) in the same order."""
    if x.shape[0] == 0:
        return x.new_zeros(0, gru.hidden_size)
    gi = torch.nn.functional.linear(x, gru.weight_ih_l0, gru.bias_ih_l0)
    return _PackedGRUFunction.apply(gi, gru.weight_hh_l0, gru.bias_hh_l0, PackedLayout(seen))


def supports_packed(gru: nn.Module) -> bool:
    """Whether ``gru`` is a plain one-layer, unidirectional, biased ``nn.GRU`` (not a
    subclass, which may compute something else): the recurrence :func:`packed_gru` and
    ``GreedyPolicy``'s cached-gate cell reproduce."""
    return (type(gru) is nn.GRU and gru.num_layers == 1 and not gru.bidirectional and gru.bias
            and gru.batch_first and getattr(gru, "proj_size", 0) == 0)

"""The hand-written packed GRU against nn.GRU: outputs and every gradient."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from uevavd.state.gru import build_gru
from uevavd.state.packed_gru import PackedLayout, _PackedGRUFunction, packed_gru, supports_packed


def _episodes(lengths: list[int], t: int) -> torch.Tensor:
    return torch.arange(t)[None] < torch.tensor(lengths)[:, None]


def _reference(gru: nn.GRU, x: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    padded = x.new_zeros(*seen.shape, x.shape[-1])
    padded[seen] = x
    return gru(padded)[0][seen]  # causal: padding after an episode never reaches its rows


@pytest.mark.parametrize("lengths", [[3, 1, 6, 2, 6, 4], [1, 1, 1], [5], [2, 6, 6, 1, 3, 3, 5, 4]])
def test_matches_nn_gru_outputs_and_gradients(lengths):
    torch.manual_seed(0)
    gru = nn.GRU(12, 10, batch_first=True).double()
    seen = _episodes(lengths, 6)
    x = torch.randn(int(seen.sum()), 12, dtype=torch.float64, requires_grad=True)
    w = torch.randn(int(seen.sum()), 10, dtype=torch.float64)

    ref = _reference(gru, x, seen)
    grads_ref = torch.autograd.grad((ref * w).sum(), [x, *gru.parameters()])
    out = packed_gru(gru, x, seen)
    grads = torch.autograd.grad((out * w).sum(), [x, *gru.parameters()])

    assert torch.allclose(out, ref, atol=1e-12)
    names = ["x"] + [n for n, _ in gru.named_parameters()]
    for name, g, r in zip(names, grads, grads_ref, strict=True):
        assert torch.allclose(g, r, atol=1e-12), f"gradient of {name} differs by {(g - r).abs().max():.2e}"


def test_gradcheck_of_the_recurrence():
    torch.manual_seed(1)
    seen = _episodes([4, 2, 3, 1], 4)
    n = int(seen.sum())
    gi = torch.randn(n, 9, dtype=torch.float64, requires_grad=True)
    w = torch.randn(9, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(9, dtype=torch.float64, requires_grad=True)
    layout = PackedLayout(seen)
    assert torch.autograd.gradcheck(lambda gi, w, b: _PackedGRUFunction.apply(gi, w, b, layout), (gi, w, b))


def test_layout_orders_running_episodes_first():
    seen = _episodes([2, 4, 1, 4], 4)
    lay = PackedLayout(seen)
    assert lay.batch_sizes == [4, 3, 2, 2]
    # episode-major rows: ep0 0-1, ep1 2-5, ep2 6, ep3 7-10; longest first, stable
    assert lay.perm.tolist() == [2, 7, 0, 6, 3, 8, 0 + 1, 4, 9, 5, 10]
    assert lay.prev.tolist() == [0, 1, 2, 4, 5, 7, 8]


def test_gru_state_uses_it_and_matches_forward():
    torch.manual_seed(2)
    est = build_gru(feature_dim=16, input_dim=24, box_dim=8, state_dim=12)
    assert supports_packed(est.gru)
    seen = _episodes([3, 6, 1, 5], 6)
    f, b = torch.randn(4, 6, 16), torch.rand(4, 6, 4)
    assert torch.allclose(est.forward_packed(f[seen], b[seen], seen), est(f, b)[seen], atol=1e-6)


def test_other_grus_fall_back():
    assert not supports_packed(nn.GRU(4, 4, num_layers=2, batch_first=True))
    assert not supports_packed(nn.GRU(4, 4, bidirectional=True, batch_first=True))
    assert not supports_packed(nn.GRU(4, 4, bias=False, batch_first=True))

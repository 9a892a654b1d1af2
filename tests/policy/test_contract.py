"""`uevavd train` checks a plugin's state estimator and head against their rules before it
writes anything: a non-causal estimator trained to completion, a learned initial memory acted
differently at t = 0 than it was trained, a builder without ``feature_dim`` and a faulty
forward ended in raw tracebacks after method.toml, settings.json and tb/ were written."""

from __future__ import annotations

import types

import pytest
import torch
from torch import nn

from uevavd.cli import main
from uevavd.config import load_method
from uevavd.plugins import hookimpl
from uevavd.plugins.manager import manager
from uevavd.policy.contract import ComponentError, build_checked_network
from uevavd.policy.network import build_network
from uevavd.policy.trainer import train
from uevavd.state.base import ObservationEncoder

from .conftest import small
from .test_cli import _one_line_error as _one_line
from .test_cli import _sets


class _Base(nn.Module):
    recurrent = False

    def __init__(self, feature_dim: int, state_dim: int = 16):
        super().__init__()
        self.feature_dim, self.state_dim = feature_dim, state_dim
        self.enc = ObservationEncoder(feature_dim, 16, 8)
        self.out = nn.Linear(24, state_dim)

    def forward(self, features, boxes):
        return torch.relu(self.out(self.enc(features, boxes)))

    def initial_hidden(self, n, device="cpu"):
        return torch.zeros(n, 0, device=device)

    def step(self, features, boxes, hidden):
        return self.forward(features[:, None], boxes[:, None])[:, 0], hidden


class NonCausal(_Base):
    """Mixes the episode's mean over all steps into every step: reads the future."""

    def forward(self, features, boxes):
        g = self.enc(features, boxes)
        return torch.relu(self.out(g + g.mean(dim=1, keepdim=True)))

    def step(self, features, boxes, hidden):
        return self.forward(features[:, None], boxes[:, None])[:, 0], hidden


class LearnedStart(nn.Module):
    """A GRU whose initial memory is a parameter: consistent in itself, but training zeroes
    the memory at every episode start."""

    recurrent = True

    def __init__(self, feature_dim: int, state_dim: int = 16):
        super().__init__()
        self.feature_dim, self.state_dim = feature_dim, state_dim
        self.enc = ObservationEncoder(feature_dim, 16, 8)
        self.cell = nn.GRUCell(24, state_dim)
        self.h0 = nn.Parameter(torch.full((state_dim,), 0.5))

    def initial_hidden(self, n, device="cpu"):
        return self.h0.detach().expand(n, -1).clone().to(device)

    def step(self, features, boxes, hidden):
        h = self.cell(self.enc(features, boxes), hidden)
        return h, h

    def forward(self, features, boxes):
        h, out = self.initial_hidden(features.shape[0]), []
        for t in range(features.shape[1]):
            s, h = self.step(features[:, t], boxes[:, t], h)
            out.append(s)
        return torch.stack(out, 1)


class TupleOut(_Base):
    def forward(self, features, boxes):
        return super().forward(features, boxes), None


class BadIndex(_Base):
    def forward(self, features, boxes):
        return super().forward(features, boxes)[:, :, torch.tensor([0, 99])]


def build_non_causal(*, feature_dim, input_dim=24, box_dim=8, state_dim=16):
    return NonCausal(feature_dim, state_dim)


def build_learned_start(*, feature_dim, input_dim=24, box_dim=8, state_dim=16, hidden=16):
    return LearnedStart(feature_dim, state_dim)


def build_tuple_out(*, feature_dim, input_dim=24, box_dim=8, state_dim=16):
    return TupleOut(feature_dim, state_dim)


def build_bad_index(*, feature_dim, input_dim=24, box_dim=8, state_dim=16):
    return BadIndex(feature_dim, state_dim)


def build_no_feature_dim(*, input_dim=24, box_dim=8, state_dim=16):
    return _Base(8, state_dim)


BROKEN = {
    "non_causal": ("not causal: s_t changed when a later observation changed",),
    "learned_start": ("initial_hidden() is not zeros", "learn it inside forward/step"),
    "tuple_out": ("returned tuple; expected a tensor",),
    "bad_index": ("forward(features (3, 4, 8) float32", "raised IndexError"),
    "no_feature_dim": ("its builder, called with the method's keys and ['feature_dim'], raised TypeError",
                       "a state builder takes keyword feature_dim"),
}


@pytest.fixture
def broken_states():
    @hookimpl
    def register_state_estimators(registry):
        for name in BROKEN:
            registry.add(name, f"{__name__}:build_{name}")

    manager.register_plugin(types.SimpleNamespace(register_state_estimators=register_state_estimators),
                            name="broken-states")
    yield
    manager.unregister_plugin("broken-states")


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_a_broken_state_estimator_is_one_line_before_anything_is_written(table, tmp_path, capsys, monkeypatch,
                                                                         broken_states, name):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    out = tmp_path / "run"
    method = "memo_map" if name == "learned_start" else "map"
    rc = main(["train", "--method", method, "--table", str(path), "--episodes", "100", "--out", str(out),
               "--no-progress", "--device", "cpu", *_sets(**{"state.name": name})])
    assert rc == 2
    # names the component and where it is registered, then the rule
    _one_line(capsys, f"state '{name}' ({__name__}:build_{name}, plugin 'broken-states')", *BROKEN[name])
    assert not out.exists()


def test_a_head_that_chooses_forbidden_actions_is_refused(table):
    from uevavd.policy.heads import build_branching_dueling

    head = build_branching_dueling(state_dim=16, hidden=8, n_types=7, n_ranges=4)
    head.greedy = lambda q, mask: (torch.zeros(q[0].shape[:-1], dtype=torch.int64),) * 2  # ignores the mask
    from uevavd.policy.contract import check_head_rules

    with pytest.raises(ComponentError, match="greedy chose an action the mask forbids"):
        check_head_rules(head, state_dim=16, n_types=7, n_ranges=4)


@pytest.mark.parametrize("method", ["map", "memo_map", "ibe_map"])
def test_the_checks_change_no_number(table, method):
    """The built-in networks pass, and the checked build is the unchecked one, weight for
    weight, with torch's global stream where build_network leaves it."""
    spec = load_method(method, overrides=small(method))
    torch.manual_seed(7)
    plain = build_network(spec.state, spec.head, table.feature_dim)
    after_plain = torch.rand(3)
    torch.manual_seed(7)
    checked = build_checked_network(spec.state, spec.head, table.feature_dim)
    assert torch.equal(torch.rand(3), after_plain)
    for (k, a), (_, b) in zip(plain.state_dict().items(), checked.state_dict().items(), strict=True):
        assert torch.equal(a, b), k
    assert checked.training and all(p.grad is None for p in checked.parameters())


def test_a_learned_start_trained_through_the_api_is_refused_too(table, tmp_path, broken_states):
    spec = load_method("memo_map", overrides={**small("memo_map"), "state.name": "learned_start"})
    with pytest.raises(ComponentError, match="initial_hidden"):
        train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
    assert not (tmp_path / "run").exists()


class Window(nn.Module):
    """A causal 1-D convolution over the last 3 views (a windowed memory): s_t reads o_{t-2}..o_t,
    never o_0 once t >= 3. Its memory is the last two encoded views."""

    recurrent = True

    def __init__(self, feature_dim: int, state_dim: int = 16, k: int = 3):
        super().__init__()
        self.feature_dim, self.state_dim, self.k = feature_dim, state_dim, k
        self.enc = ObservationEncoder(feature_dim, 16, 8)
        self.conv = nn.Conv1d(24, state_dim, k)

    def initial_hidden(self, n, device="cpu"):
        return torch.zeros(n, 24 * (self.k - 1), device=device)

    def forward(self, features, boxes):
        g = self.enc(features, boxes).transpose(1, 2)  # (B, 24, T)
        return torch.relu(self.conv(nn.functional.pad(g, (self.k - 1, 0)))).transpose(1, 2)

    def step(self, features, boxes, hidden):
        past = hidden.view(len(hidden), self.k - 1, 24)
        window = torch.cat([past, self.enc(features, boxes)[:, None]], 1)  # (N, k, 24)
        s = torch.relu(self.conv(window.transpose(1, 2)))[:, :, 0]
        return s, window[:, 1:].reshape(len(hidden), -1)


class CurrentViewOnly(nn.Module):
    """Declares a memory but reads the current view alone."""

    recurrent = True

    def __init__(self, feature_dim: int, state_dim: int = 16):
        super().__init__()
        self.feature_dim, self.state_dim = feature_dim, state_dim
        self.enc = ObservationEncoder(feature_dim, 16, 8)
        self.out = nn.Linear(24, state_dim)

    def initial_hidden(self, n, device="cpu"):
        return torch.zeros(n, 1, device=device)

    def forward(self, features, boxes):
        return torch.relu(self.out(self.enc(features, boxes)))

    def step(self, features, boxes, hidden):
        return torch.relu(self.out(self.enc(features, boxes))), hidden


def test_a_windowed_estimator_is_a_recurrent_one_and_a_current_view_one_is_told_what_to_declare():
    from uevavd.policy.contract import check_estimator_rules

    check_estimator_rules(Window(8), feature_dim=8)  # s_T ignores o_0, and it is still a memory
    with pytest.raises(ComponentError, match=r"reads no earlier view than o_t.*set recurrent = False.*window"):
        check_estimator_rules(CurrentViewOnly(8), feature_dim=8)

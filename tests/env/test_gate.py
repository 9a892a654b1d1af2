"""The stop gate, the stopping diagnosis and the scripted box-gate baseline.

The tables here hide the target's box at some views and give every view a visible fraction
that disagrees with the box, so a gate or a diagnosis that read the true visibility instead
of the observation would fail these tests.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.data.grid import N_VIEWS, STOP, transitions
from uevavd.env import EnvConfig, evaluate_policy
from uevavd.env.baselines import BoxGatePolicy, box_gate_move, build_box_gate, reference_policies
from uevavd.env.evaluate import evaluate_gated
from uevavd.env.gate import StopGate, box_visible, gate_mask
from uevavd.table import ObservationTable

from .conftest import make_table
from .test_evaluate import ScriptPolicy


def occluded_table(seed: int = 0, hard_seed: int | None = None) -> ObservationTable:
    """6 scenes (3 train, 1 simple, 2 hard); about 40 % of the views have an empty box, and the
    visible fraction is high exactly where the box is empty (the opposite of the observation)."""
    t = make_table(6, splits=("train", "train", "train", "simple", "hard", "hard"), seed=seed)
    rng = np.random.default_rng(100 + seed)
    boxes = np.array(t.boxes)
    hidden = rng.uniform(size=boxes.shape[:2]) < 0.4
    if hard_seed is not None:  # other hard scenes, the same training ones
        other = make_table(6, seed=hard_seed)
        boxes[4:] = np.array(other.boxes)[4:]
        hidden[4:] = np.random.default_rng(hard_seed).uniform(size=(2, N_VIEWS)) < 0.6
    boxes[hidden] = 0.0
    probs = np.array(t.probs)
    if hard_seed is not None:
        probs[4:] = np.array(make_table(6, seed=hard_seed).probs)[4:]
    return ObservationTable.from_arrays(
        np.array(t.features), probs, boxes, scenes=list(t.scenes), contexts=list(t.contexts),
        targets=list(t.targets), splits=list(t.splits), visible=np.where(hidden, 0.9, 0.05))


def test_box_visible_and_gate_mask_read_the_box():
    box = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.3, 0.4], [0.0, 0.0, 0.5, 0.5]])
    assert box_visible(box).tolist() == [False, True, True]
    mask = torch.ones(3, 7, 4, dtype=torch.bool)
    gated = gate_mask(mask, box)
    assert gated[0].all()  # empty box: every move stays allowed
    assert not gated[1:, :STOP].any() and gated[1:, STOP].all()  # in view: stop only
    assert mask.all()  # a new tensor


def test_diagnosis_counts_what_the_observation_shows():
    table, cfg = occluded_table(), EnvConfig(t_max=3)
    res = evaluate_policy(table, "train", ScriptPolicy(), cfg)
    s = res.summary()
    boxes = np.array(table.boxes)[res.scene, res.start_view]
    box = (boxes != 0).any(-1)
    moved = res.trajectories[:, 1] >= 0
    start_reco = cfg.recognized(table.true_class_probs())[res.scene, res.start_view]
    assert 0.3 < box.mean() < 0.9 and 0 < moved[box].mean() < 1  # the table and policy exercise both cases
    assert s["box_start"] == pytest.approx(box.mean())
    assert s["moved_if_box"] == pytest.approx(moved[box].mean())
    assert s["box_lost"] == pytest.approx((box & moved & ~res.recognized).mean())
    assert s["reco_lost"] == pytest.approx((start_reco & ~res.recognized).mean())
    ctx = res.per_context()
    first = ctx.iloc[0]
    sel = res.scene == first["scene"]
    assert first["moved_if_box"] == pytest.approx(moved[sel & box].sum() / (sel & box).sum())


def test_stop_gate_stops_wherever_the_box_is_in_view_and_defers_elsewhere():
    table, cfg = occluded_table(), EnvConfig(t_max=3)
    res, gated = evaluate_gated(table, "train", ScriptPolicy(), cfg)
    boxes = np.array(table.boxes)
    start_box = (boxes[gated.scene, gated.start_view] != 0).any(-1)
    # a box in view at the start: stop at once
    assert (gated.decisions[start_box] == 1).all() and gated.stopped[start_box].all()
    assert (gated.final_view[start_box] == gated.start_view[start_box]).all()
    # no episode ever moves away from a view whose box is non-empty
    for i in range(len(gated)):
        views = gated.trajectories[i][gated.trajectories[i] >= 0]
        for v in views[:-1]:
            assert not (boxes[gated.scene[i], v] != 0).any()
    # box empty at the start: the first decision is the policy's own
    free = ~start_box
    assert np.array_equal(gated.trajectories[free, 1], res.trajectories[free, 1])
    assert gated.summary()["moved_if_box"] == 0.0 and gated.summary()["box_lost"] == 0.0


def test_stop_gate_keeps_a_recurrent_policys_memory_stepping():
    class Counting:
        needs_features = False

        def reset(self, n):
            self.seen = 0

        def act(self, obs):
            self.seen += 1
            n = obs["view"].shape[0]
            return torch.zeros(n, dtype=torch.int64), torch.zeros(n, dtype=torch.int64)

    inner = Counting()
    gate = StopGate(inner)
    assert gate.needs_features is False
    evaluate_policy(occluded_table(), "train", gate, EnvConfig(t_max=3))
    assert inner.seen >= 1


def test_box_gate_policy_stops_in_view_and_flies_its_move_elsewhere():
    tr = transitions(4)
    views = torch.arange(N_VIEWS)
    mask = torch.as_tensor(np.array(tr.mask))[views]
    box = torch.zeros(N_VIEWS, 4)
    box[::2] = 0.3  # in view at every other view
    pol = BoxGatePolicy(2, 3)
    a_type, a_range = pol.act({"mask": mask, "box": box, "view": views})
    in_view = box_visible(box)
    assert (a_type[in_view] == STOP).all()
    out = ~in_view
    allowed = mask[:, 2, :].sum(-1)
    flies = out & (allowed > 0)
    assert (a_type[flies] == 2).all()
    # the longest allowed range no longer than the requested one, never a clamped move
    assert (a_range[flies] == torch.clamp(allowed[flies] - 1, max=3)).all()
    assert mask[flies, 2, :].gather(1, a_range[flies, None]).all()
    assert (a_type[out & (allowed == 0)] == STOP).all()  # at the edge of that direction: stop


def test_box_gate_move_is_the_best_on_training_contexts_and_ignores_test_splits():
    cfg = EnvConfig(t_max=3)
    table = occluded_table()
    a_type, a_range, returns = box_gate_move(table, cfg)
    assert len(returns) == STOP * cfg.max_range
    for (t, r), value in list(returns.items())[:3]:  # the returns are those of the training split
        assert value == pytest.approx(evaluate_policy(table, "train", BoxGatePolicy(t, r), cfg).ret.mean())
    assert returns[(a_type, a_range)] == max(returns.values())
    # other test contexts, the same training contexts: the same move
    other = occluded_table(hard_seed=7)
    assert not np.array_equal(np.array(other.boxes)[4:], np.array(table.boxes)[4:])
    assert box_gate_move(other, cfg)[:2] == (a_type, a_range)
    assert "box_gate" in reference_policies(table, cfg)


def test_box_gate_does_not_apply_without_training_contexts():
    t = make_table(2, splits=("hard", "hard"))
    assert build_box_gate(table=t, config=EnvConfig()) is None

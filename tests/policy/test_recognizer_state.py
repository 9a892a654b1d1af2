"""``state.recognizer``: a state that reads the recognizer's class probabilities at the end of the
table's features (``perception.recognizer_in_state``) and none of the image's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.config_rules import ConfigError
from uevavd.env import evaluate_policy
from uevavd.policy.acting import load_policy
from uevavd.policy.contract import check_estimator_rules
from uevavd.policy.trainer import train
from uevavd.state.base import RECOGNIZER_COLUMNS, estimator_boxes, reads_image, reads_recognizer
from uevavd.state.gru import build_gru
from uevavd.state.single_view import build_single_view
from uevavd.table import ObservationTable

from .test_stop_gate import _spec, hidden_table

D = 8  # the toy table's feature size: 3 image columns, then the 5 class probabilities


@pytest.mark.parametrize("build", [build_gru, build_single_view])
def test_the_estimator_reads_the_last_five_columns_ranked_and_nothing_before_them(build):
    est = build(feature_dim=D, input_dim=24, box_dim=8, state_dim=16, pose=True, image=False, recognizer=True)
    assert reads_recognizer(est) and not reads_image(est)
    check_estimator_rules(est, feature_dim=D)
    f, box = torch.rand(2, 3, D), torch.rand(2, 3, 4)
    inputs = estimator_boxes(est, box, torch.tensor([[-50.0, 20.0, 60.0]]).expand(2, 3, 3))
    s = est(f, inputs)
    image_changed = f.clone()
    image_changed[..., :D - RECOGNIZER_COLUMNS] = torch.randn(2, 3, D - RECOGNIZER_COLUMNS) * 9
    assert torch.equal(s, est(image_changed, inputs))  # whatever the image's features
    probs = f[..., D - RECOGNIZER_COLUMNS:]
    relabelled = torch.cat([f[..., :D - RECOGNIZER_COLUMNS], probs[..., torch.tensor([3, 0, 4, 1, 2])]], dim=-1)
    assert torch.equal(s, est(relabelled, inputs))  # whichever class holds which probability
    surer = torch.cat([f[..., :D - RECOGNIZER_COLUMNS], probs * torch.tensor([4.0, 0, 0, 0, 0])], dim=-1)
    assert not torch.allclose(s, est(surer, inputs))  # how sure it is moves the state
    blind = build(feature_dim=D, input_dim=24, box_dim=8, state_dim=16, pose=True, image=False)
    assert set(blind.state_dict()) == set(est.state_dict())  # one file layout
    with pytest.raises(ConfigError, match="state.recognizer = true: expected it beside state.image = false"):
        build(feature_dim=D, recognizer=True)
    with pytest.raises(ConfigError, match="state.recognizer"):
        build(feature_dim=D, image=False, recognizer="yes")


def test_a_run_needs_the_recognizers_columns_in_its_table(tmp_path):
    spec = _spec("ibe_map_boxpose_rule", **{"state.recognizer": True})
    with pytest.raises(ConfigError, match="perception.recognizer_in_state = true"):
        train(spec, hidden_table(), out=tmp_path / "run", seed=0, device="cpu", progress=False)
    with pytest.raises(ConfigError, match="train.mirror = 0.5: expected 0"):
        train(_spec("ibe_map_boxpose_rule_reco", **{"train.mirror": 0.5}), hidden_table(), out=tmp_path / "run",
              seed=0, device="cpu", progress=False)
    t = hidden_table()
    probs = np.array(t.probs)[..., :4]
    four = ObservationTable.from_arrays(np.array(t.features), probs / probs.sum(-1, keepdims=True), np.array(t.boxes),
                                        scenes=list(t.scenes), targets=[int(x) % 4 for x in t.targets],
                                        splits=list(t.splits), contexts=list(t.contexts),
                                        class_names=t.class_names[:4], config={"four": 1})
    with pytest.raises(ConfigError, match="expected a table of 5 classes"):
        train(_spec("ibe_map_boxpose_rule_reco"), four, out=tmp_path / "run", seed=0, device="cpu", progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_acts_on_the_probabilities_alone_and_resumes_bit_for_bit(tmp_path):
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule_reco")
    assert spec.perception.recognizer_in_state and spec["state.recognizer"]
    run = train(spec, table, out=tmp_path / "run", seed=1, device="cpu", progress=False)
    fast = evaluate_policy(table, "hard", load_policy(run), spec.env)
    plain = evaluate_policy(table, "hard", load_policy(run, with_table=False), spec.env)
    assert (fast.trajectories == plain.trajectories).all() and (fast.ret == plain.ret).all()
    # the image's columns scrambled: the same flights
    feats = np.array(table.features)
    feats[..., :D - RECOGNIZER_COLUMNS] = np.random.default_rng(0).normal(size=feats[..., :3].shape) * 5
    scrambled = ObservationTable.from_arrays(feats, np.array(table.probs), np.array(table.boxes),
                                             scenes=list(table.scenes), targets=list(table.targets),
                                             splits=list(table.splits), contexts=list(table.contexts),
                                             config={"scrambled": 1})
    other = evaluate_policy(scrambled, "hard", load_policy(run, with_table=False), spec.env)
    assert (other.trajectories == plain.trajectories).all()
    train(spec, table, out=tmp_path / "paused", seed=1, device="cpu", progress=False, max_epochs=1)
    train(spec, table, out=tmp_path / "paused", seed=1, device="cpu", progress=False)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False)["net"] for d in ("run", "paused"))
    assert all(torch.equal(a[k], b[k]) for k in a)

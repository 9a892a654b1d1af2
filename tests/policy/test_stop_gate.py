"""The stop gates a method takes (``train.stop_gate``): "box" inside training and acting,
"learned", a stop probe on the state that gates greedy acting only, and "pays", the box gate
opened where a flight pays (the oracle's answer in training, a probe's in acting)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.config import ConfigError, load_method
from uevavd.env import evaluate_policy
from uevavd.env.baselines import PassivePolicy
from uevavd.env.batched import BatchedAODEnv
from uevavd.env.gate import box_visible
from uevavd.policy.acting import load_policy
from uevavd.policy.collector import EpisodeCollector
from uevavd.policy.config import TrainConfig
from uevavd.policy.learner import FlightPays
from uevavd.policy.network import build_network
from uevavd.policy.trainer import train
from uevavd.table import ObservationTable
from uevavd.testing.policy import small_run, toy_table


def hidden_table(seed: int = 0) -> ObservationTable:
    """The toy table with the target's box hidden at about half of each scene's views (where
    its recognisability signal is low), so the gate has both cases to decide."""
    t = toy_table(n_train=3, n_hard=1, feature_dim=8, seed=seed)
    feats, boxes = np.array(t.features), np.array(t.boxes)
    hide = feats[..., 3] < np.median(feats[..., 3], axis=1, keepdims=True)
    boxes[hide] = 0.0
    return ObservationTable.from_arrays(feats, np.array(t.probs), boxes, scenes=list(t.scenes),
                                        targets=list(t.targets), splits=list(t.splits), contexts=list(t.contexts),
                                        config={"toy-hidden": seed})


def _spec(method: str, **overrides):
    return load_method(method, overrides={**small_run("ibe_map"), "train.episodes": 200, **overrides})


def test_bad_stop_gate_settings_are_refused():
    with pytest.raises(ConfigError, match="train.stop_gate"):
        TrainConfig(stop_gate="always")
    with pytest.raises(ConfigError, match="train.stop_threshold"):
        TrainConfig(stop_threshold=1.5)


def test_the_box_gate_shapes_exploration_in_training():
    table = hidden_table()
    spec = _spec("ibe_map_gate")
    net = build_network(spec.state, spec.head, table.feature_dim).set_stop_gate("box")
    env = BatchedAODEnv(table, "train", 256, seed=0)
    col = EpisodeCollector(env, net, seed=0, device=torch.device("cpu"))
    col.reset()
    for _ in range(6):
        obs = col.obs
        visible = box_visible(obs["box"])
        t = obs["t"].clone()
        col.step(epsilon=1.0)  # random actions: the gate still holds
        rows = torch.arange(len(t))
        taken = col.ep_type[rows, t]
        assert visible.any() and (~visible).any()
        assert (taken[visible] == 6).all()
        assert (taken[~visible] != 6).any()


def test_the_pays_gate_opens_in_training_exactly_where_a_flight_pays():
    table = hidden_table()
    spec = _spec("ibe_map_pose_pays")
    net = build_network(spec.state, spec.head, table.feature_dim).set_stop_gate("pays")
    env = BatchedAODEnv(table, "train", 256, spec.env, seed=0)
    pays = FlightPays(env.tensors)
    col = EpisodeCollector(env, net, seed=0, device=torch.device("cpu"), pays=pays)
    col.reset()
    opened = closed = 0
    for _ in range(6):
        obs = col.obs
        visible = box_visible(obs["box"])
        flight = pays.at(obs["scene"], obs["view"], obs["t"])
        t = obs["t"].clone()
        col.step(epsilon=1.0)  # random actions: the gate still holds
        taken = col.ep_type[torch.arange(len(t)), t]
        assert (taken[visible & ~flight] == 6).all()  # the box gate, where no flight pays
        assert (taken[visible & flight] != 6).any()  # opened where one does
        assert (taken[~visible] != 6).any()
        opened, closed = opened + int((visible & flight).sum()), closed + int((visible & ~flight).sum())
    assert opened > 20 and closed > 20


@pytest.mark.parametrize("threshold", [0.0, 1.0])
def test_a_pays_gated_run_trains_its_probe_resumes_and_acts_at_its_thresholds_ends(tmp_path, threshold):
    """The probe learns beside the Q network and its optimizer resumes with the run; in greedy
    acting, threshold 1 keeps the box gate closed (never a flight from a visible box) and
    threshold 0 leaves it open (the Q network's own choice there)."""
    table = hidden_table()
    spec = _spec("ibe_map_pose_pays", **{"train.stop_threshold": threshold})
    for d, epochs in (("whole", None), ("paused", 1), ("paused", None)):
        train(spec, table, out=tmp_path / d, seed=3, device="cpu", progress=False, max_epochs=epochs)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "paused"))
    assert {"stop_probe.weight", "stop_probe.bias"} <= set(a["net"]) and "stop_probe" in a
    assert all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])
    res = evaluate_policy(table, "hard", load_policy(tmp_path / "whole"), spec.env).summary()
    assert res["box_start"] > 0.2
    assert (res["moved_if_box"] == 0.0) == (threshold == 1.0)


def test_a_box_gated_run_never_flies_from_a_visible_target_and_resumes_bit_for_bit(tmp_path):
    table = hidden_table()
    spec = _spec("ibe_map_gate")
    for d, epochs in (("whole", None), ("paused", 1), ("paused", None)):
        train(spec, table, out=tmp_path / d, seed=3, device="cpu", progress=False, max_epochs=epochs)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "paused"))
    assert all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])
    res = evaluate_policy(table, "hard", load_policy(tmp_path / "whole"), spec.env)
    boxes = np.array(table.boxes)
    for i in range(len(res)):
        views = res.trajectories[i][res.trajectories[i] >= 0]
        assert not any((boxes[res.scene[i], v] != 0).any() for v in views[:-1])
    assert res.summary()["moved_if_box"] == 0.0 and res.summary()["box_start"] > 0.2


def test_the_learned_gate_trains_a_probe_beside_an_unchanged_q_network(tmp_path):
    table = hidden_table()
    train(_spec("ibe_map_stop"), table, out=tmp_path / "stop", seed=1, device="cpu", progress=False)
    train(_spec("ibe_map"), table, out=tmp_path / "plain", seed=1, device="cpu", progress=False)
    stop, plain = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("stop", "plain"))
    # the Q network's updates are the plain method's, bit for bit; the probe learned
    assert set(stop["net"]) - set(plain["net"]) == {"stop_probe.weight", "stop_probe.bias"}
    assert all(torch.equal(stop["net"][k], plain["net"][k]) for k in plain["net"])
    assert "stop_probe" in stop and "stop_probe" not in plain
    policy = load_policy(tmp_path / "stop")
    probe = policy.net.stop_probe
    assert probe is not None and not torch.equal(probe.weight, torch.zeros_like(probe.weight))


@pytest.mark.parametrize("threshold", [0.0, 1.0])
def test_the_learned_gates_threshold_acts_at_its_ends(tmp_path, threshold):
    """Threshold 0: every probability is above it, so the policy stops at once (passive's
    episodes); threshold 1: never, so it acts as the network without the gate."""
    table = hidden_table()
    spec = _spec("ibe_map_stop", **{"train.stop_threshold": threshold})
    train(spec, table, out=tmp_path / "stop", seed=1, device="cpu", progress=False)
    train(_spec("ibe_map"), table, out=tmp_path / "plain", seed=1, device="cpu", progress=False)
    got = evaluate_policy(table, "hard", load_policy(tmp_path / "stop"), spec.env)
    want = evaluate_policy(table, "hard", PassivePolicy() if threshold == 0.0 else load_policy(tmp_path / "plain"),
                           spec.env)
    np.testing.assert_array_equal(got.ret, want.ret)
    np.testing.assert_array_equal(got.trajectories, want.trajectories)


def test_a_policy_acts_on_the_table_it_is_given_or_is_refused(tmp_path):
    """load_run(run).policy() read the run's own table's features by (scene, view) whatever table
    it was evaluated on: a same-shape table with other features gave the run's own numbers."""
    from uevavd.api import load_run
    from uevavd.env.gate import StopGate

    # two tables of one perception config (as prepare records it) over other data, on disk as runs' are
    parts = {"encoder": "toy", "classifier": "toy", "dataset": "a"}
    t = hidden_table()
    table = ObservationTable.load(ObservationTable.from_arrays(
        np.array(t.features), np.array(t.probs), np.array(t.boxes), scenes=list(t.scenes), targets=list(t.targets),
        splits=list(t.splits), contexts=list(t.contexts), config={"key_parts": parts}).save(tmp_path / "a"))
    spec = _spec("ibe_map")
    train(spec, table, out=tmp_path / "run", seed=1, device="cpu", progress=False)
    other = ObservationTable.from_arrays(  # the scenes' features, probabilities and boxes permuted
        np.array(t.features)[::-1].copy(), np.array(t.probs)[::-1].copy(), np.array(t.boxes)[::-1].copy(),
        scenes=list(t.scenes), targets=list(t.targets)[::-1], splits=list(t.splits), contexts=list(t.contexts),
        config={"key_parts": {**parts, "dataset": "b"}})
    run = load_run(tmp_path / "run")
    with pytest.raises(ValueError, match=f"reads the features of table {table.key}, but the evaluation is on table "
                                         f"{other.key}"):
        evaluate_policy(other, "hard", run.policy(), spec.env)
    with pytest.raises(ValueError, match="reads the features of table"):
        evaluate_policy(other, "hard", StopGate(run.policy()), spec.env)
    # given the other table, it acts on its features: as the network reading them from the observations
    got = evaluate_policy(other, "hard", run.policy(table=other), spec.env)
    plain = load_policy(tmp_path / "run", with_table=False)
    want = evaluate_policy(other, "hard", plain, spec.env)
    np.testing.assert_array_equal(got.trajectories, want.trajectories)

"""``state.pose``: the viewpoint's pose in the state estimators' input, through training, acting,
the evaluation's fast paths and a plugin estimator's builder."""

from __future__ import annotations

import pytest
import torch

from uevavd.config import load_method
from uevavd.config_rules import ConfigError
from uevavd.env import EnvConfig, evaluate_policy
from uevavd.plugins import hookimpl
from uevavd.plugins.manager import manager
from uevavd.policy.acting import load_policy
from uevavd.policy.contract import check_estimator_rules
from uevavd.policy.trainer import train
from uevavd.state.base import estimator_boxes
from uevavd.state.gru import build_gru
from uevavd.state.single_view import build_single_view
from uevavd.testing.policy import small_run, toy_table


@pytest.mark.parametrize("build", [build_gru, build_single_view])
def test_a_pose_estimator_reads_seven_columns_and_keeps_the_protocol(build):
    est = build(feature_dim=8, input_dim=24, box_dim=8, state_dim=16, pose=True)
    assert est.pose and est.encoder.out_dim == 24 + 32
    check_estimator_rules(est, feature_dim=8)  # causal, step == forward, fast path == step
    f, box = torch.randn(2, 3, 8), torch.rand(2, 3, 4)
    pose = torch.tensor([[-50.0, 20.0, 60.0]]).expand(2, 3, 3)
    s = est(f, estimator_boxes(est, box, pose))
    assert s.shape == (2, 3, 16)
    moved = est(f, estimator_boxes(est, box, pose + torch.tensor([10.0, 0.0, 0.0])))
    assert not torch.allclose(s, moved)  # the state reads the pose
    with pytest.raises(ValueError, match="env.pose"):
        est(f, box)  # the box alone
    with pytest.raises(ValueError, match="env.pose = true"):
        estimator_boxes(est, box, None)
    plain = build(feature_dim=8, input_dim=24, box_dim=8, state_dim=16)
    assert not getattr(plain, "pose", False) and estimator_boxes(plain, box, pose) is box  # the paper's input
    assert set(plain.state_dict()) < set(est.state_dict())  # the paper's files load as before
    with pytest.raises(ConfigError, match="state.pose"):
        build(feature_dim=8, pose="yes")


@pytest.mark.parametrize("build", [build_gru, build_single_view])
def test_an_estimator_without_the_image_reads_the_box_and_the_pose_alone(build):
    est = build(feature_dim=8, input_dim=24, box_dim=8, state_dim=16, pose=True, image=False)
    check_estimator_rules(est, feature_dim=8)  # a memory still reads o_{t-1}: its box and pose
    f, box = torch.randn(2, 3, 8), torch.rand(2, 3, 4)
    inputs = estimator_boxes(est, box, torch.tensor([[-50.0, 20.0, 60.0]]).expand(2, 3, 3))
    s = est(f, inputs)
    assert torch.equal(s, est(f * 7 + 3, inputs))  # whatever the image features
    assert not torch.allclose(s, est(f, inputs.flip(-1)))
    seeing = build(feature_dim=8, input_dim=24, box_dim=8, state_dim=16, pose=True)
    assert set(seeing.state_dict()) == set(est.state_dict())  # one file layout
    with pytest.raises(ConfigError, match="state.image"):
        build(feature_dim=8, image="false")


def test_the_state_reads_the_pose_only_where_the_observation_has_it():
    with pytest.raises(ConfigError, match="env.pose = true"):
        load_method("ibe_map", overrides={"state.pose": True})
    spec = load_method("ibe_map_pose")
    assert spec.env.pose and spec["state.pose"]
    assert not load_method("ibe_map").env.pose  # the paper's methods keep their inputs


def test_a_pose_run_trains_resumes_and_acts_alike_on_both_evaluation_paths(tmp_path):
    table = toy_table(n_train=3, n_hard=2, feature_dim=8)
    over = {**small_run("memo_map"), "train.episodes": 300}
    spec = load_method("ibe_map_pose", overrides=over)
    run = train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
    fast = evaluate_policy(table, "hard", load_policy(run), spec.env)  # the cached GRU input gates
    plain = evaluate_policy(table, "hard", load_policy(run, with_table=False), spec.env)
    assert (fast.trajectories == plain.trajectories).all() and (fast.ret == plain.ret).all()
    with pytest.raises(ValueError, match="env.pose = true"):
        evaluate_policy(table, "hard", load_policy(run), EnvConfig())  # no pose in the observation
    # one epoch, then the rest: the same network, bit for bit
    train(spec, table, out=tmp_path / "resumed", device="cpu", progress=False, max_epochs=1)
    resumed = train(spec, table, out=tmp_path / "resumed", device="cpu", progress=False)
    a, b = load_policy(run).net.state_dict(), load_policy(resumed).net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


class _PosePlugin:
    """A third-party estimator whose builder takes ``pose`` as the built-ins do."""

    @staticmethod
    @hookimpl
    def register_state_estimators(registry):
        registry.add("pose_mlp", f"{__name__}:build_pose_mlp", summary="a plugin estimator that reads the pose")


def build_pose_mlp(*, feature_dim, input_dim=24, box_dim=8, state_dim=16, pose=False):
    return build_single_view(feature_dim=feature_dim, input_dim=input_dim, box_dim=box_dim, state_dim=state_dim,
                             pose=pose, pose_dim=4)


def test_a_plugin_estimator_gets_the_pose_through_its_builder(tmp_path):
    manager.register_plugin(_PosePlugin, name="pose-plugin")
    try:
        spec = load_method("ibe_map_pose", overrides={**small_run("map"), "state.name": "pose_mlp",
                                                      "state.pose": True, "train.episodes": 200})
        est = spec.state.build(feature_dim=8)
        assert est.pose and est.encoder.pose_dim == 4
        table = toy_table(n_train=2, n_hard=1, feature_dim=8)
        run = train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
        assert evaluate_policy(table, "hard", load_policy(run), spec.env).ret.shape == (605,)
    finally:
        manager.unregister_plugin("pose-plugin")

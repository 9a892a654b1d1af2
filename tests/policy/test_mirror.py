"""The task's left-right mirror (``train.mirror``): exact on the grid and in the renderer's
boxes, and the learner's mirrored update equals the plain update on the mirrored table."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from uevavd.config import ConfigError
from uevavd.data.grid import ACTION_TYPES, MIRROR_TYPES, N_VIEWS, mirror_views, transitions, view_coords
from uevavd.data.synthetic.render import render_view
from uevavd.data.synthetic.scenes import TARGET_ID
from uevavd.data.synthetic.world import build_context
from uevavd.env.batched import BatchedAODEnv
from uevavd.policy.collector import EpisodeCollector
from uevavd.policy.config import TrainConfig
from uevavd.policy.learner import FeatureLookup, Learner
from uevavd.policy.mirror import MirrorAugment
from uevavd.policy.network import build_network
from uevavd.policy.replay import EpisodeReplay
from uevavd.policy.rule_gate import RulePays
from uevavd.policy.trainer import train
from uevavd.table import ObservationTable

from .test_rule_gate import rule_moves
from .test_stop_gate import _spec, hidden_table


def test_the_grids_mirror_maps_views_moves_and_edges_onto_each_other():
    m = mirror_views()
    assert np.array_equal(m[m], np.arange(N_VIEWS))
    xyz = view_coords(np.arange(N_VIEWS))
    assert np.array_equal(view_coords(m), xyz * np.array([-1.0, 1.0, 1.0]))
    types = np.array(MIRROR_TYPES)
    assert [ACTION_TYPES[t] for t in MIRROR_TYPES] == ["forward", "backward", "right", "left", "down", "up", "stop"]
    tr = transitions(4)
    # the move mirrored from the mirrored view lands on the mirror of where the move lands
    assert np.array_equal(tr.next_view[m][:, types], m[tr.next_view])
    assert np.array_equal(tr.mask[m][:, types], tr.mask)


def _mirrored_scene(scene):
    """The scene with world x negated: the hulls' planes and vertices, the ellipsoids' centres,
    the point the camera looks at and the sun."""
    prims = {k: np.array(v) for k, v in scene.prims.items()}
    prims["h_planes"][..., 0] *= -1
    prims["h_verts"][..., 0] *= -1
    prims["e_centre"][..., 0] *= -1
    flip = np.array([-1.0, 1.0, 1.0])
    return dataclasses.replace(scene, prims=prims, look_at=scene.look_at * flip, sun_dir=scene.sun_dir * flip)


@pytest.mark.parametrize("context", [1, 26])
def test_the_renderers_boxes_and_visible_fractions_are_exactly_mirrored(context):
    """The image of the mirrored scene from the mirrored viewpoint is the image reversed left to
    right, as far as the box-and-pose state reads it: the target's pixels, so its box and its
    visible fraction."""
    scene = build_context(context, seed=0)
    mirrored = _mirrored_scene(scene)
    m = mirror_views()
    rng = np.random.default_rng(context)
    boxes = 0
    for view in rng.choice(N_VIEWS, 24, replace=False).tolist():
        a = render_view(scene, view, 64, shade=False)
        b = render_view(mirrored, int(m[view]), 64, shade=False)
        assert np.array_equal(b.seg[:, ::-1] == TARGET_ID, a.seg == TARGET_ID)
        assert b.visible == a.visible
        x1, y1, x2, y2 = a.box.tolist()
        assert b.box.tolist() == ([64 - x2, y1, 64 - x1, y2] if a.box.any() else [0, 0, 0, 0])
        boxes += bool(a.box.any())
    assert boxes >= 4


def mirrored_table(table: ObservationTable) -> ObservationTable:
    """Every scene of ``table`` mirrored: view v holds what the original's mirror view holds,
    its box reversed left to right."""
    m = mirror_views()
    feats, probs, boxes = (np.array(a)[:, m] for a in (table.features, table.probs, table.boxes))
    shown = boxes.any(-1)
    boxes[shown] = np.stack([1.0 - boxes[shown][:, 2], boxes[shown][:, 1], 1.0 - boxes[shown][:, 0],
                             boxes[shown][:, 3]], -1)
    return ObservationTable.from_arrays(feats, probs, boxes, scenes=list(table.scenes), targets=list(table.targets),
                                        splits=list(table.splits), contexts=list(table.contexts),
                                        config={"mirrored": True})


def _learner(net, env, mirror=None):
    pays = RulePays(env.tensors, int(net.rule_moves))
    return Learner(copy.deepcopy(net), lr=1e-3, gamma=0.9, grad_clip=10.0, pays=pays, mirror=mirror), pays


def test_a_mirrored_update_is_the_plain_update_on_the_mirrored_table():
    """With ``train.mirror = 1`` every replayed episode is seen mirrored: the loss, every
    parameter after the step and the rule gate's probe equal those of the plain update on the
    mirrored table's mirrored episodes. Half of them (p = 0.5) is neither."""
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule")
    net = build_network(spec.state, spec.head, table.feature_dim).set_stop_gate("rule")
    net.rule_moves.fill_(rule_moves(table, spec.env))
    env = BatchedAODEnv(table, "train", 64, spec.env, seed=0)
    flipped = BatchedAODEnv(mirrored_table(table), "train", 64, spec.env, seed=0)
    col = EpisodeCollector(env, net, seed=0, device=torch.device("cpu"), pays=RulePays(env.tensors, int(net.rule_moves)))
    replay = EpisodeReplay(256, spec.env.t_max, seed=0)
    col.reset()
    while replay.size < 64:
        done = col.step(epsilon=1.0)
        if done is not None:
            replay.add(done.scene, done.views, done.types, done.ranges, done.rewards, done.lengths)
    batch = replay.sample(32, 0.5)
    m = torch.as_tensor(mirror_views())
    mirrored = dataclasses.replace(batch, views=m[batch.views], a_type=torch.as_tensor(MIRROR_TYPES)[batch.a_type])

    plain, _ = _learner(net, flipped)
    augmented, _ = _learner(net, env, MirrorAugment(1.0, seed=0, device="cpu"))
    half, _ = _learner(net, env, MirrorAugment(0.5, seed=0, device="cpu"))
    unmirrored, _ = _learner(net, env)
    loss_plain, td_plain = plain.update(mirrored, FeatureLookup(flipped.tensors))
    loss_aug, td_aug = augmented.update(batch, FeatureLookup(env.tensors))
    loss_half, _ = half.update(batch, FeatureLookup(env.tensors))
    loss_none, _ = unmirrored.update(batch, FeatureLookup(env.tensors))
    assert loss_aug == loss_plain and torch.equal(td_aug, td_plain)
    for (name, a), b in zip(augmented.net.state_dict().items(), plain.net.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    assert len({loss_aug, loss_half, loss_none}) == 3


def test_mirror_settings_are_checked(tmp_path):
    for bad in ({"mirror": 1.5}, {"mirror": -0.1}, {"mirror": 0.5, "imitation": "visibility_oracle"}):
        with pytest.raises(ConfigError, match="train.mirror"):
            TrainConfig(**bad)
    table = hidden_table()
    with pytest.raises(ConfigError, match="train.mirror = 0.5: expected 0 for a state that reads the table.s features"):
        train(_spec("ibe_map_pose_pays", **{"train.mirror": 0.5}), table, out=tmp_path / "run", seed=0,
              device="cpu", progress=False)
    assert not (tmp_path / "run").exists()


def test_a_mirrored_run_resumes_bit_for_bit(tmp_path):
    table = hidden_table()
    spec = _spec("ibe_map_boxpose_rule", **{"train.mirror": 0.5})
    for d, epochs in (("whole", None), ("paused", 1), ("paused", None)):
        train(spec, table, out=tmp_path / d, seed=3, device="cpu", progress=False, max_epochs=epochs)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in ("whole", "paused"))
    assert "mirror" in a
    assert all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])
    plain = tmp_path / "plain"
    train(_spec("ibe_map_boxpose_rule"), table, out=plain, seed=3, device="cpu", progress=False)
    c = torch.load(plain / "checkpoint.pt", weights_only=False)
    assert not all(torch.equal(a["net"][k], c["net"][k]) for k in a["net"])

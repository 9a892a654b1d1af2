"""The generalisation training options: level replay over the training contexts (the sampler's weights,
the env drawing from them, a run that uses it trained and resumed like any other), the
features' dropout in the updates and the recognition probe."""

from __future__ import annotations

import pytest
import torch

from uevavd.config import ConfigError, load_method
from uevavd.env.batched import BatchedAODEnv
from uevavd.policy.config import TrainConfig
from uevavd.policy.level_replay import LevelReplay
from uevavd.policy.trainer import train
from uevavd.testing.policy import small_run, toy_table


def _runs(spec, table, tmp_path, seed: int, *, plain=None) -> tuple[dict, ...]:
    """The checkpoints of ``spec`` trained whole and paused after one epoch then resumed (and of
    ``plain``, the same run without the option, where given), by the same seed."""
    train(spec, table, out=tmp_path / "whole", seed=seed, device="cpu", progress=False)
    train(spec, table, out=tmp_path / "paused", seed=seed, device="cpu", progress=False, max_epochs=1)
    train(spec, table, out=tmp_path / "paused", seed=seed, device="cpu", progress=False)
    runs = ["whole", "paused"]
    if plain is not None:
        train(plain, table, out=tmp_path / "plain", seed=seed, device="cpu", progress=False)
        runs.append("plain")
    return tuple(torch.load(tmp_path / d / "checkpoint.pt", weights_only=False) for d in runs)


def _same_net(a: dict, b: dict) -> bool:
    return all(torch.equal(a["net"][k], b["net"][k]) for k in a["net"])


def test_unscored_contexts_first_then_by_rank_with_staleness():
    plr = LevelReplay(4, temperature=1.0, staleness=0.0)
    plr.score(torch.tensor([0, 1, 1]), torch.tensor([0.1, 0.4, 0.2]))
    w = plr.weights()
    # 2 and 3 unscored rank first (ties by index), then 1 (score 0.3), then 0: h = 1/rank
    assert torch.allclose(w, torch.tensor([1 / 4, 1 / 3, 1, 1 / 2], dtype=torch.float64) / (25 / 12))
    plr.score(torch.tensor([1]), torch.tensor([1.3]))  # moves 0.1 of the way: 0.3 -> 0.4
    assert float(plr.scores[1]) == pytest.approx(0.4)
    cold = LevelReplay(3, temperature=0.1, staleness=1.0)
    for scene in (0, 1, 1, 2, 0):  # last started: 0 at 5, 1 at 3, 2 at 4
        cold.started(torch.tensor([scene]))
    assert torch.allclose(cold.weights(), torch.tensor([0.0, 2 / 3, 1 / 3], dtype=torch.float64))
    assert torch.allclose(LevelReplay(5, temperature=0.1, staleness=0.5).weights().sum(),
                          torch.tensor(1.0, dtype=torch.float64))


def test_the_env_draws_new_episodes_from_the_weights():
    table = toy_table(n_train=3, n_hard=1, feature_dim=8)
    env = BatchedAODEnv(table, "train", 256, seed=0)
    env.scene_weights = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    assert set(env.tensors.local[env.reset()["scene"]].tolist()) == {1}


@pytest.mark.parametrize("bad", [{"context_sampling": "plr"}, {"plr_temperature": 0.0}, {"plr_staleness": 1.5}])
def test_bad_level_replay_settings_are_refused(bad):
    with pytest.raises(ConfigError, match=f"train.{next(iter(bad))}"):
        TrainConfig(**bad)


def test_a_level_replay_run_skews_its_contexts_and_resumes_bit_for_bit(tmp_path):
    table = toy_table(n_train=4, n_hard=1, feature_dim=8)
    spec = load_method("ibe_map_plr", overrides={**small_run("ibe_map"), "train.episodes": 300})
    a, b = _runs(spec, table, tmp_path, 2)
    assert _same_net(a, b)
    assert torch.equal(a["level_replay"]["scores"], b["level_replay"]["scores"])
    assert bool(a["level_replay"]["scored"].all())  # every training context was scored
    plr = LevelReplay(4, temperature=0.1, staleness=0.1)
    plr.load_state_dict(a["level_replay"])
    w = plr.weights()
    assert float(w.max()) > 0.5 and int(w.argmax()) == int(plr.scores.argmax())  # the top context dominates


def test_feature_dropout_augments_the_updates_only_and_resumes_bit_for_bit(tmp_path):
    """train.feature_dropout: the updates read masked, rescaled features from the
    run's own stream, saved with the run; 0 leaves the run as it was (no stream drawn)."""
    from uevavd.policy.learner import FeatureDropout

    drop = FeatureDropout(0.5, seed=0, device="cpu")
    x = torch.ones(2000, 8)
    y = drop(x)
    assert set(y.unique().tolist()) == {0.0, 2.0} and abs(float((y == 0).float().mean()) - 0.5) < 0.03
    with pytest.raises(ConfigError, match="train.feature_dropout"):
        TrainConfig(feature_dropout=1.0)
    table = toy_table(n_train=3, n_hard=1, feature_dim=8)
    spec = load_method("ibe_map_aug", overrides={**small_run("ibe_map"), "train.episodes": 200,
                                                 "train.feature_dropout": 0.3})
    plain = load_method("ibe_map", overrides={**small_run("ibe_map"), "train.episodes": 200})
    a, b, c = _runs(spec, table, tmp_path, 4, plain=plain)
    assert _same_net(a, b) and "feature_dropout" in a
    assert not _same_net(a, c) and "feature_dropout" not in c


def test_the_recognition_probe_trains_with_the_state_and_resumes_bit_for_bit(tmp_path):
    """train.aux_recognition: a probe on s_t learns the view's recognition beside the
    TD loss; it shapes the network (other weights than without it), its weights and their Adam
    state are saved with the run, and the policy file holds the network alone."""
    from safetensors.torch import load_file

    table = toy_table(n_train=3, n_hard=1, feature_dim=8)
    spec = load_method("ibe_map_aux", overrides={**small_run("ibe_map"), "train.episodes": 200})
    plain = load_method("ibe_map", overrides={**small_run("ibe_map"), "train.episodes": 200})
    a, b, c = _runs(spec, table, tmp_path, 5, plain=plain)
    assert _same_net(a, b)
    assert torch.equal(a["aux_recognition"]["linear.weight"], b["aux_recognition"]["linear.weight"]) and "aux_recognition" not in c
    assert not _same_net(a, c)
    assert set(load_file(str(tmp_path / "whole" / "policy.safetensors"))) == set(a["net"])
    with pytest.raises(ConfigError, match="train.aux_recognition"):
        TrainConfig(aux_recognition=-1.0)

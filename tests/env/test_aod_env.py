"""AODEnv: the reward of every branch of Eq. 2/3, clamping, path length, T_max, bad input."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import uevavd.env  # noqa: F401  (registers uevavd/AOD-v0)
from uevavd.data.grid import N_VIEWS, STOP, view_index
from uevavd.env import AODEnv, DiscreteActions, EnvConfig, EnvConfigError
from uevavd.table import ObservationTable, TableError

from .conftest import make_table

# views with x = 0 / y = 0 / z = 80 m (centre), and at the x = +50 m edge
CENTRE = view_index(5, 5, 2)
EDGE_X = view_index(10, 5, 2)


def reco_table(recognised_views: set[int], target: int = 1) -> ObservationTable:
    """One train scene whose true class has p = 0.9 at ``recognised_views``, 0.1 elsewhere."""
    probs = np.full((1, N_VIEWS, 5), 0.0, np.float32)
    other = (target + 1) % 5
    probs[0, :, target] = 0.1
    probs[0, :, other] = 0.9
    for v in recognised_views:
        probs[0, v, target], probs[0, v, other] = 0.9, 0.1
    return make_table(1, splits=("train",), probs=probs, seed=3).__class__.from_arrays(
        np.zeros((1, N_VIEWS, 4)), probs, np.zeros((1, N_VIEWS, 4)),
        scenes=["001"], contexts=[1], targets=[target], splits=["train"],
    )


def run(env: AODEnv, view: int, actions: list[tuple[int, int]]):
    env.reset(seed=0, options={"view": view})
    rewards, info, term, trunc = [], {}, False, False
    for a in actions:
        _, r, term, trunc, info = env.step(np.array(a))
        rewards.append(r)
    return rewards, term, trunc, info


def test_stop_rewards_and_ends():
    env = AODEnv(reco_table({CENTRE}), "train")
    rewards, term, trunc, info = run(env, CENTRE, [(STOP, 3)])
    assert rewards == [0.5] and term and not trunc  # stop ignores its range: no cost
    assert info["recognized"] and info["correct"] and info["stopped"] and info["distance_m"] == 0.0
    rewards, *_ , info = run(env, CENTRE + 1, [(STOP, 0)])
    assert rewards == [-0.5] and not info["recognized"] and not info["correct"]


def test_move_then_terminal_at_tmax():
    # T_max = 2: move (non-terminal), then a move at t = T_max-1 ends at the new view
    cfg = EnvConfig(t_max=2)
    target_view = view_index(5, 8, 2)  # forward (+y) 3 steps from the centre
    env = AODEnv(reco_table({target_view}), "train", cfg)
    rewards, term, trunc, info = run(env, CENTRE, [(0, 1), (0, 0)])  # +2 then +1 steps forward
    assert rewards[0] == pytest.approx(-0.1 - 0.02 * 2)
    assert rewards[1] == pytest.approx(0.5 - 0.02 * 1)
    assert term and not trunc and info["view"] == target_view and info["recognized"]
    assert info["steps"] == 3 and info["distance_m"] == 30.0
    assert info["return"] == pytest.approx(rewards[0] + 0.9 * rewards[1])
    rewards, term, _, info = run(env, CENTRE, [(0, 1), (1, 3)])  # ends unrecognised
    assert rewards[1] == pytest.approx(-0.5 - 0.02 * 4) and term and not info["recognized"]
    assert not info["stopped"]


def test_stop_after_moves_has_no_movement_cost():
    env = AODEnv(reco_table({view_index(4, 5, 2)}), "train")
    rewards, term, _, info = run(env, CENTRE, [(2, 0), (STOP, 2)])  # left 1 step, stop
    assert rewards == pytest.approx([-0.12, 0.5]) and term and info["recognized"]
    assert info["t"] == 2 and info["return"] == pytest.approx(-0.12 + 0.9 * 0.5)


def test_clamping_costs_requested_range_and_flies_actual_distance():
    env = AODEnv(reco_table(set()), "train")
    obs, _ = env.reset(options={"view": EDGE_X})
    assert obs["action_mask"][3].tolist() == [0, 0, 0, 0]  # right is clamped at x = +50
    assert obs["action_mask"][2].tolist() == [1, 1, 1, 1] and obs["action_mask"][STOP].all()
    _, r, term, _, info = env.step(np.array([3, 3]))  # right 4: stays at the edge
    assert info["view"] == EDGE_X and info["distance_m"] == 0.0 and info["steps"] == 0
    assert r == pytest.approx(-0.1 - 0.08) and not term
    _, r, *_ , info = env.step(np.array([5, 3]))  # up 4 from z = 80: flies 2 steps to z = 100
    assert info["xyz"].tolist() == [50.0, 0.0, 100.0] and info["distance_m"] == 20.0 and info["steps"] == 2
    assert r == pytest.approx(-0.18)


def test_tmax_ends_episode_and_step_after_end_refused():
    env = AODEnv(reco_table(set()), "train", t_max=3)
    env.reset(options={"view": CENTRE})
    ends = [env.step(np.array([0, 0]))[2:4] for _ in range(3)]
    assert ends == [(False, False), (False, False), (True, False)]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.array([0, 0]))


def test_info_and_observation_contents(table):
    env = AODEnv(table, "hard")
    obs, info = env.reset(seed=5, options={"context": 6, "view": 17})
    assert info["context"] == 6 and info["scene"] == 5 and info["view"] == 17 and info["t"] == 0
    np.testing.assert_array_equal(obs["features"], table.features[5, 17].astype(np.float32))
    np.testing.assert_array_equal(obs["box"], table.boxes[5, 17])
    np.testing.assert_array_equal(info["probs"], table.probs[5, 17])
    assert info["visible"] == pytest.approx(float(table.visible[5, 17]))
    assert info["target"] == int(table.targets[5])
    seen = {env.reset(seed=s)[1]["context"] for s in range(20)}
    assert seen == {5, 6}  # only contexts of the split


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped version")
def test_check_env_and_gym_make(table):
    check_env(AODEnv(table, "train"), skip_render_check=True)
    check_env(DiscreteActions(AODEnv(table, "train", t_max=2)), skip_render_check=True)
    env = gym.make("uevavd/AOD-v0", table=table, split="simple", t_max=3)
    obs, info = env.reset(seed=0)
    assert env.action_space == gym.spaces.MultiDiscrete([7, 4]) and info["context"] == 4
    wrapped = DiscreteActions(env)
    assert wrapped.action_space == gym.spaces.Discrete(28)
    obs, _ = wrapped.reset(seed=0, options={"view": EDGE_X})
    assert obs["action_mask"].shape == (28,) and obs["action_mask"][3 * 4 : 4 * 4].sum() == 0
    _, _, term, _, info = wrapped.step(6 * 4 + 2)  # stop with any range
    assert term and info["stopped"]


def test_fixed_start_from_config(table):
    env = AODEnv(table, "train", start="302")
    assert all(env.reset(seed=s)[1]["view"] == 302 for s in range(3))


def test_bad_input(table, tmp_path):
    env = AODEnv(table, "train")
    env.reset(seed=0)
    for bad in ([7, 0], [0, 4], [-1, 0], [1, 2, 3], ["a", "b"], [0.5, 1]):
        with pytest.raises(ValueError, match="action"):
            env.step(np.array(bad))
    with pytest.raises(ValueError, match="outside Discrete"):
        DiscreteActions(AODEnv(table, "train")).step(28)
    with pytest.raises(ValueError, match="context=9"):
        env.reset(options={"context": 9})
    with pytest.raises(ValueError, match="view=605"):
        env.reset(options={"view": 605})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"start": 3})
    only_train = make_table(2, splits=("train", "train"))
    with pytest.raises(TableError, match="no scenes in split 'hard'"):
        AODEnv(only_train, "hard")
    for kwargs, match in (({"t_max": 0}, "t_max"), ({"gamma": 1.5}, "gamma"), ({"thre": 1.0}, "thre"),
                          ({"start": "middle"}, "start"), ({"xi1": -1}, "xi1")):
        with pytest.raises(EnvConfigError, match=match):
            EnvConfig(**kwargs)
    with pytest.raises(TypeError, match="unexpected keyword argument 'tmax' \\(did you mean 't_max'\\?\\)"):
        AODEnv(table, "train", tmax=3)
    # a table folder works in place of the table; NaN in it is refused at load
    path = table.save(tmp_path / "tbl")
    assert gym.make("uevavd/AOD-v0", table=str(path), split="hard").reset(seed=0)[1]["context"] in (5, 6)
    feats = np.load(path / "features.npy")
    feats[2, 7, 0] = np.nan
    np.save(path / "features.npy", feats)
    with pytest.raises(TableError, match="NaN"):
        AODEnv(path, "train")


def test_sb3_dqn_trains_on_discrete_form(table):
    sb3 = pytest.importorskip("stable_baselines3")
    env = DiscreteActions(AODEnv(table, "train"))
    model = sb3.DQN(
        "MultiInputPolicy", env, learning_starts=100, buffer_size=1000, batch_size=32,
        train_freq=4, target_update_interval=100, policy_kwargs={"net_arch": [32]}, seed=0, device="cpu",
    )
    from uevavd.env.sb3 import silent_logger

    model.set_logger(silent_logger())  # no empty SB3-<date> folder in the temp directory
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny network: threads only contend on a shared machine
    try:
        model.learn(total_timesteps=500)
    finally:
        torch.set_num_threads(threads)
    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(int(action))
    _, _, term, trunc, _ = env.step(int(action))
    assert not trunc


def test_env_section_of_method_configs_is_envconfig():
    from uevavd.config import ConfigError, validate

    validate({"name": "m", "env": {"t_max": 3, "C": 0.05, "start": "uniform"}})
    with pytest.raises(ConfigError, match="did you mean 't_max'"):
        validate({"name": "m", "env": {"tmax": 3}})
    uevavd.env.register()  # idempotent
    assert "uevavd/AOD-v0" in gym.registry


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped version")
def test_check_env_passes_on_a_table_without_visible_fractions_and_through_gym_make(table):
    """The real release (and from_arrays' default) has no visible fractions: the env used to
    put NaN in info, and NaN != NaN failed Gymnasium's determinism check. DiscreteActions
    around gym.make(...) used to break env.spec.make() and so check_env."""
    from uevavd.table import ObservationTable

    bare = ObservationTable.from_arrays(table.features, table.probs, table.boxes, scenes=table.scenes,
                                        targets=table.targets, splits=table.splits, contexts=table.contexts)
    env = AODEnv(bare, "train")
    _, info = env.reset(seed=0)
    assert info["visible"] == -1.0  # a number equal to itself, not NaN: the key is there at every step
    check_env(env, skip_render_check=True)
    wrapped = DiscreteActions(gym.make("uevavd/AOD-v0", table=bare, split="train"))
    check_env(wrapped, skip_render_check=True)
    assert wrapped.spec.make().action_space == gym.spaces.Discrete(28)


def test_train_per_block_keeps_the_first_training_contexts_of_each_block():
    """EnvConfig.train_per_block: of the training contexts, the first N of each block (by id)
    make the "train" split of the env, the batched env and the evaluation; test contexts stay;
    a block holding fewer is refused naming it."""
    from uevavd.env.baselines import PassivePolicy
    from uevavd.env.batched import EnvTensors
    from uevavd.env.evaluate import evaluate_policy

    t = _two_block_table()
    two = EnvConfig(train_per_block=2)
    assert sorted(t.contexts[AODEnv(t, "train", two).scenes]) == [1, 2, 31, 32]
    # the rule is the table's own: the env, the trainer and the evaluation ask it
    assert sorted(t.contexts[t.select("train", train_per_block=2)]) == [1, 2, 31, 32]
    assert sorted(t.contexts[t.select("validation", train_per_block=2)]) == [3]
    assert t.select("train", [31, 2], train_per_block=2).tolist() == [3, 1]
    with pytest.raises(ValueError, match=r"context\(s\) \[3\] are not in split 'train'"):
        t.select("train", [3], train_per_block=2)
    with pytest.raises(TableError, match="set env.train_per_block"):
        t.select("validation")  # nothing held out
    assert sorted(AODEnv(t, "train").scenes.tolist()) == [0, 1, 2, 3, 4]  # 0: all
    assert sorted(EnvTensors(t, "train", EnvConfig(train_per_block=1)).contexts) == [1, 31]
    assert sorted(EnvTensors(t, "hard", EnvConfig(train_per_block=1)).contexts) == [26, 56]
    res = evaluate_policy(t, "train", PassivePolicy(), EnvConfig(train_per_block=1))
    assert sorted(set(res.context.tolist())) == [1, 31]
    with pytest.raises(TableError, match=r"env.train_per_block = 3: .*block 1 \(contexts 31-60\) holds only 2"):
        AODEnv(t, "train", EnvConfig(train_per_block=3))
    for bad in (-1, 21, 1.5, True):
        with pytest.raises(EnvConfigError, match="train_per_block"):
            EnvConfig(train_per_block=bad)


def test_info_has_the_same_keys_and_types_at_every_step(table):
    """Minari's record_infos and Gymnasium's vector envs stack infos step by step: the keys and
    their types do not change between reset, a move and the last step (recognized / correct /
    stopped / return of the current view and the episode so far; visible -1 where unknown)."""
    env = AODEnv(table, "train")
    _, first = env.reset(seed=0, options={"view": 302})
    _, r0, _, _, moved = env.step(np.array([5, 0]))  # up one step: the episode goes on
    _, r1, term, _, last = env.step(np.array([STOP, 0]))
    assert term and last["stopped"] and not moved["stopped"] and not first["stopped"]
    for info in (first, moved, last):
        assert list(info) == list(first)
        assert [type(v) for v in info.values()] == [type(v) for v in first.values()]
    assert first["return"] == 0.0 and moved["return"] == pytest.approx(r0)
    assert last["return"] == pytest.approx(r0 + 0.9 * r1)
    assert moved["recognized"] == bool((table.true_class_probs() > 0.2)[moved["scene"], moved["view"]])
    unknown = ObservationTable.from_arrays(table.features, table.probs, table.boxes, scenes=table.scenes,
                                           contexts=table.contexts, targets=table.targets, splits=table.splits)
    env = AODEnv(unknown, "train")
    _, info = env.reset(seed=0)
    assert info["visible"] == -1.0 and list(info) == list(first)


def test_unknown_keywords_are_pythons_type_error_and_t_is_a_numpy_integer(table):
    """TorchRL's GymEnv passes frameskip= and drops it only on the standard TypeError."""
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        AODEnv(table, "train", frameskip=4)
    obs, _ = AODEnv(table, "train").reset(seed=0)
    assert isinstance(obs["t"], np.integer) and obs["t"] in AODEnv(table, "train").observation_space["t"]


def test_the_lazy_api_is_listed_by_dir():
    import uevavd

    assert {"train", "load_method", "evaluate_pretrained", "registry"} <= set(dir(uevavd))


@pytest.mark.parametrize("options, needle", [
    ({"view": 2.5}, "view=2.5: expected an integer"),
    ({"view": True}, "view=True: expected an integer"),
    ({"view": float("nan")}, "view=nan: expected an integer"),
    ({"context": 1.7}, "context=1.7: expected an integer"),
    ({"scene": "0"}, "scene='0': expected an integer"),
    ([("view", 3)], "expected a dict"),
])
def test_reset_options_that_are_not_integers_are_refused_naming_the_option(table, options, needle):
    """They used to be truncated (view 2.5 -> 2, context 1.7 -> 1, True -> 1) or fail naming nothing."""
    with pytest.raises(ValueError, match=re.escape(needle)):
        AODEnv(table, "train").reset(seed=0, options=options)
    assert AODEnv(table, "train").reset(seed=0, options={"view": np.int64(3)})[1]["view"] == 3


def test_the_validation_split_is_the_training_contexts_a_run_leaves_out():
    """split "validation" with env.train_per_block = N: the training contexts past the first N of
    each block (to choose recipes on training data only); refused without N, or when N leaves
    nothing out."""
    from uevavd.env.batched import EnvTensors

    contexts = [1, 2, 3, 31, 32, 26]
    t = ObservationTable.from_arrays(
        np.zeros((6, N_VIEWS, 4)), np.full((6, N_VIEWS, 5), 0.2), np.zeros((6, N_VIEWS, 4)),
        scenes=[f"{c:03d}" for c in contexts], contexts=contexts, targets=[0, 0, 0, 1, 1, 0],
        splits=["train"] * 5 + ["hard"])
    cfg = EnvConfig(train_per_block=1)
    assert sorted(t.contexts[AODEnv(t, "validation", cfg).scenes]) == [2, 3, 32]
    assert sorted(t.contexts[AODEnv(t, "train", cfg).scenes]) == [1, 31]
    assert sorted(EnvTensors(t, "validation", EnvConfig(train_per_block=2)).contexts) == [3]
    with pytest.raises(TableError, match="set env.train_per_block"):
        AODEnv(t, "validation")
    with pytest.raises(TableError, match="block 1 .* holds only 2"):
        AODEnv(t, "validation", EnvConfig(train_per_block=3))


def test_a_held_out_block_leaves_the_train_split_whole_and_is_the_validation_split():
    """env.holdout_block = k: every training context of target block k joins the validation
    split (a held-out set that is a distribution shift); with train_per_block the two combine;
    test contexts are never dropped, and the Gymnasium env and the batched env agree."""
    from uevavd.env.batched import EnvTensors

    t = _two_block_table()
    cfg = EnvConfig(holdout_block=2)
    assert sorted(t.contexts[AODEnv(t, "train", cfg).scenes]) == [1, 2, 3]
    assert sorted(EnvTensors(t, "validation", cfg).contexts) == [31, 32]
    assert sorted(EnvTensors(t, "hard", cfg).contexts) == [26, 56]  # a test split is never cut
    both = EnvConfig(holdout_block=2, train_per_block=1)
    assert sorted(EnvTensors(t, "train", both).contexts) == [1]
    assert sorted(EnvTensors(t, "validation", both).contexts) == [2, 3, 31, 32]
    alone = ObservationTable.from_arrays(
        np.zeros((1, N_VIEWS, 4)), np.full((1, N_VIEWS, 5), 0.2), np.zeros((1, N_VIEWS, 4)), scenes=["001"],
        contexts=[1], targets=[0], splits=["train"])
    with pytest.raises(TableError, match="env.holdout_block = 1 holds out every training context"):
        AODEnv(alone, "train", EnvConfig(holdout_block=1))
    with pytest.raises(EnvConfigError, match="holdout_block"):
        EnvConfig(holdout_block=6)


def _two_block_table() -> ObservationTable:
    """Training contexts 1-3 (block 1) and 31-32 (block 2), hard contexts 26 and 56."""
    contexts = [1, 2, 3, 31, 32, 26, 56]
    return ObservationTable.from_arrays(
        np.zeros((7, N_VIEWS, 4)), np.full((7, N_VIEWS, 5), 0.2), np.zeros((7, N_VIEWS, 4)),
        scenes=[f"{c:03d}" for c in contexts], contexts=contexts, targets=[0, 0, 0, 1, 1, 0, 1],
        splits=["train"] * 5 + ["hard"] * 2)


def test_a_table_folder_of_the_cache_is_recorded_by_key_in_the_env_spec(table, tmp_path, monkeypatch):
    """gym.make with a table's path stored that absolute path in the env spec, and a Minari
    dataset recorded from the env kept it without a word."""
    import warnings

    import gymnasium as gym

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    from uevavd.paths import tables_dir

    inside = table.save(tables_dir() / table.key)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make("uevavd/AOD-v0", table=str(inside), split="train")
    assert env.spec.kwargs["table"] == table.key and gym.make(env.spec).unwrapped.table.key == table.key
    outside = table.save(tmp_path / "elsewhere")
    with pytest.warns(UserWarning, match="by its path, which exists on this machine only"):
        env = gym.make("uevavd/AOD-v0", table=outside, split="train")
    assert env.spec.kwargs["table"] == outside

"""The viewpoint's pose relative to the target (``env.pose``): in every env's observation and
the clients built on them, off by default; and the scripted ``pose_seek`` baseline that reads it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from uevavd.data.grid import N_VIEWS, coords_to_view, view_coords
from uevavd.env import ENV_ID, AODEnv, BatchedAODEnv, EnvConfig, EnvConfigError, evaluate_policy
from uevavd.env.baselines import PoseSeekPolicy, build_pose_seek, pose_seek_moves
from uevavd.env.offline import flat_observation
from uevavd.table import ObservationTable

POSE = EnvConfig(pose=True, t_max=3)


def test_the_single_env_adds_the_pose_only_when_asked(table):
    plain = AODEnv(table, "train")
    obs, _ = plain.reset(seed=0)
    assert "pose" not in obs and "pose" not in plain.observation_space.spaces  # the paper's observation
    env = AODEnv(table, "train", POSE)
    from gymnasium.utils.env_checker import check_env

    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=1)
    for _ in range(20):
        assert env.observation_space.contains(obs)
        assert obs["pose"].dtype == np.float32
        np.testing.assert_array_equal(obs["pose"], view_coords(info["view"]))  # metres, target at the origin
        obs, _, done, _, info = env.step(env.action_space.sample())
        if done:
            obs, info = env.reset()
    with pytest.raises(EnvConfigError, match="pose"):
        EnvConfig(pose="yes")


def test_the_batched_and_vector_envs_carry_it_in_both_autoreset_modes(table):
    env = BatchedAODEnv(table, "train", 8, POSE, seed=0)
    obs = env.reset()
    assert "pose" not in BatchedAODEnv(table, "train", 2, seed=0).reset()
    for _ in range(6):
        np.testing.assert_array_equal(obs["pose"].numpy(), view_coords(obs["view"].numpy()))
        obs, *_ = env.step(torch.randint(0, 7, (8,)), torch.randint(0, 4, (8,)))
    for mode in ("same_step", "next_step"):
        venv = gym.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", table=table, config=POSE,
                            autoreset_mode=mode)
        obs, _ = venv.reset(seed=2)
        for _ in range(8):
            assert venv.observation_space.contains(obs) and obs["pose"].shape == (4, 3)
            assert all(coords_to_view(*p) >= 0 for p in obs["pose"].tolist())  # grid points, metres
            obs, _, term, _, info = venv.step(np.stack([np.full(4, 3), np.zeros(4, int)], 1))  # right, 1 step
            if "view" in info:  # (the next-step env's reset step reports none)
                going = ~term & info["_view"]
                np.testing.assert_array_equal(obs["pose"][going], view_coords(info["view"][going]))
            if mode == "same_step" and term.any():
                i = int(np.flatnonzero(term)[0])
                np.testing.assert_array_equal(info["final_obs"][i]["pose"], view_coords(info["final_view"][i]))


def test_sb3_and_the_offline_flat_view_see_it(table):
    pytest.importorskip("stable_baselines3")
    from uevavd.env.sb3 import SB3VecEnv

    venv = SB3VecEnv(gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", table=table,
                                  config=POSE))
    obs = venv.reset()
    assert obs["pose"].shape == (3, 3) and venv.observation_space["pose"].shape == (3,)
    batched = BatchedAODEnv(table, "train", 5, POSE, seed=0).reset()
    flat = flat_observation(batched)
    d = table.feature_dim
    assert flat.shape == (5, d + 4 + 3 + 1 + 7 * 4)  # [features, box, pose, t, mask]
    np.testing.assert_array_equal(flat[:, d + 4:d + 7], batched["pose"].numpy())
    assert flat_observation({k: v for k, v in batched.items() if k != "pose"}).shape == (5, d + 4 + 1 + 7 * 4)


def test_a_minari_export_records_the_pose(table, tmp_path, monkeypatch):
    pytest.importorskip("minari")
    from uevavd.paths import tables_dir
    from uevavd.policy.minari_export import export_minari

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    folder = table.save(tables_dir() / table.key)
    data = export_minari(folder, "train", "pose_seek", "uevavd/pose-v0", episodes=4, config=POSE, progress=False)
    ep = next(iter(data.iterate_episodes()))
    assert ep.observations["pose"].shape == (len(ep.rewards) + 1, 3)
    assert set(ep.observations["pose"][:, 2]) <= {60.0, 70.0, 80.0, 90.0, 100.0}
    from uevavd.env import flat_dataset

    flat = flat_dataset(data)  # the flat view carries its parts, and its policy their width
    assert flat.parts == ("features", "box", "pose", "t", "action_mask")
    policy = flat.policy(lambda x: np.full(len(x), 6 * 4))
    assert policy.width == flat.observations.shape[1] and policy.max_range == 4
    with pytest.raises(ValueError, match=r"evaluate with EnvConfig\(pose=True\)"):
        evaluate_policy(folder, "train", policy, EnvConfig())


def _flat_routes(table, config):
    """The same state's flat vector through every flat route: the env's observation="flat",
    MaskedFlatObservation (Tianshou), observation="masked" (RLlib) and the flat view of the
    batched interface (FlatPolicy, flat_dataset)."""
    from uevavd.env import MaskedFlatObservation

    kw = {"table": table, "split": "train", "config": config}
    flat = gym.make(ENV_ID, observation="flat", actions="flat", **kw)
    masked = MaskedFlatObservation(gym.make(ENV_ID, **kw))
    rllib = gym.make(ENV_ID, observation="masked", actions="flat", **kw)
    start = {"options": {"scene": 1, "view": 302}}
    out = {"flat": flat.reset(**start)[0], "tianshou": masked.reset(**start)[0]["obs"],
           "rllib": rllib.reset(**start)[0]["observations"]}
    batched = BatchedAODEnv(table, "train", 1, config)
    out["flat_policy"] = flat_observation(batched.reset(scenes=[1], views=[302]))[0]
    widths = {"flat": flat.observation_space.shape[0], "tianshou": masked.observation_space["obs"].shape[0],
              "rllib": rllib.observation_space["observations"].shape[0]}
    return out, widths


@pytest.mark.parametrize("config", [EnvConfig(t_max=3), POSE], ids=["paper", "pose"])
def test_every_flat_route_gives_one_vector_for_one_state(table, config):
    """One flat layout: Tianshou's masked wrapper gave Gymnasium's flatten (mask first, t one-hot:
    1,318 floats on the quick table against 1,313), so a network trained through it could not be
    scored through FlatPolicy. Every route now gives [features, box, (pose,) t, mask]."""
    vectors, widths = _flat_routes(table, config)
    d, extra = table.feature_dim, (3 if config.pose else 0)
    assert set(widths.values()) == {d + 4 + extra + 1 + 7 * config.max_range}
    for name, vector in vectors.items():
        assert vector.dtype == np.float32, name
        np.testing.assert_array_equal(vector, vectors["flat"], err_msg=name)


def test_a_flat_policy_built_with_the_pose_is_refused_without_it_by_name(table):
    """A network trained with pose=True and scored by evaluate_policy(table, split, FlatPolicy(...))
    failed inside torch (mat1 and mat2 shapes cannot be multiplied). A FlatPolicy given its width
    (FlatTransitions.policy gives it) refuses the other layout in one line naming the setting."""
    from uevavd.env import FlatPolicy
    from uevavd.env.spaces import flat_observation_space

    width = flat_observation_space(table.feature_dim, POSE).shape[0]
    stop = 6 * 4  # the flat index of stop, range 0

    def act(x):
        assert x.shape[1] == width  # never called with the other layout
        return np.full(len(x), stop)

    policy = FlatPolicy(act, max_range=4, width=width)
    with pytest.raises(ValueError, match=r"built with the pose \(3 floats\) and this env has none; evaluate with "
                                         r"EnvConfig\(pose=True\)"):
        evaluate_policy(table, "hard", policy, EnvConfig(t_max=3))
    assert evaluate_policy(table, "hard", policy, POSE).stopped.all()
    plain = FlatPolicy(act, max_range=4, width=width - 3)
    with pytest.raises(ValueError, match=r"built without the pose .* EnvConfig\(pose=False\)"):
        evaluate_policy(table, "hard", plain, POSE)
    with pytest.raises(ValueError, match="another encoder"):
        evaluate_policy(table, "hard", FlatPolicy(act, max_range=4, width=width + 5), POSE)
    space = gym.make(ENV_ID, table=table, config=POSE, observation="flat", actions="flat").observation_space
    assert FlatPolicy(act, max_range=4, width=space).width == width  # an observation space gives its width


def test_an_sb3_model_of_the_pose_is_refused_without_it_by_name(table):
    sb3 = pytest.importorskip("stable_baselines3")
    from uevavd.env import DiscreteActions
    from uevavd.env.sb3 import SB3Policy

    model = sb3.DQN("MultiInputPolicy", DiscreteActions(gym.make(ENV_ID, table=table, config=POSE)), device="cpu")
    with pytest.raises(ValueError, match=r"SB3 model: it was built with the pose .* EnvConfig\(pose=True\)"):
        evaluate_policy(table, "hard", SB3Policy(model, 4), EnvConfig(t_max=3))
    assert len(evaluate_policy(table, "hard", SB3Policy(model, 4), POSE).ret) > 0


# -- pose_seek -------------------------------------------------------------------------------------
def _hidden_everywhere_but(visible_views, n_scenes=2, splits=("train", "hard")) -> ObservationTable:
    """A table whose target box is empty except at ``visible_views`` (recognised exactly there)."""
    rng = np.random.default_rng(0)
    boxes = np.zeros((n_scenes, N_VIEWS, 4), np.float32)
    probs = np.full((n_scenes, N_VIEWS, 5), 0.2, np.float32)
    for v in visible_views:
        boxes[:, v] = (0.4, 0.4, 0.6, 0.6)
        probs[:, v] = (0.9, 0.025, 0.025, 0.025, 0.025)
    return ObservationTable.from_arrays(rng.normal(size=(n_scenes, N_VIEWS, 4)), probs, boxes,
                                        scenes=[f"{i + 1:03d}" for i in range(n_scenes)],
                                        contexts=list(range(1, n_scenes + 1)), targets=[0] * n_scenes,
                                        splits=list(splits))


def _act(policy, views, t=0, box_visible=False):
    views = torch.as_tensor(views)
    box = torch.full((len(views), 4), 0.5 if box_visible else 0.0)
    return policy.act({"view": views, "box": box, "t": torch.full((len(views),), t)})


def test_pose_seek_flies_toward_the_column_above_the_target_by_its_written_rule():
    from uevavd.data.grid import coords_to_view, move

    policy = PoseSeekPolicy(moves=2, max_range=4)
    cases = {  # (x, y, z) -> (type, range index): the larger offset's axis, never past the column
        (30, -10, 80): (2, 2),   # left (-x) 3 steps to x = 0
        (-10, 40, 60): (1, 3),   # backward (-y) 4 steps
        (-50, 0, 100): (3, 3),   # right (+x), at most A = 4 of the 5 steps
        (20, 20, 70): (2, 1),    # a tie goes to x
        (0, 0, 90): (6, 0),      # above the target's column: stop
    }
    views = [coords_to_view(*xyz) for xyz in cases]
    a_type, a_range = _act(policy, views)
    assert list(zip(a_type.tolist(), a_range.tolist(), strict=True)) == list(cases.values())
    for v, ty, r in zip(views, a_type.tolist(), a_range.tolist(), strict=True):
        if ty != 6:
            nxt, _, _, clamped = move(v, ty, r)
            assert not clamped and abs(view_coords(nxt)[:2]).sum() < abs(view_coords(v)[:2]).sum()
    assert set(_act(policy, views, box_visible=True)[0].tolist()) == {6}  # the box is in view: stop
    assert set(_act(policy, views, t=2)[0].tolist()) == {6}  # its moves are spent: stop


def test_pose_seek_reaches_a_hidden_target_and_chooses_its_moves_on_the_training_split_only():
    from uevavd.env import PassivePolicy

    # the target is in view from the two vertical planes through it (x = 0 or y = 0), hidden elsewhere
    xyz = view_coords(np.arange(N_VIEWS))
    cross = np.flatnonzero((xyz[:, 0] == 0) | (xyz[:, 1] == 0)).tolist()
    table = _hidden_everywhere_but(cross)
    cfg = EnvConfig()
    moves, returns = pose_seek_moves(table, cfg)
    # one move reaches a plane from an offset of at most 40 m; from 50 m a second, from (50, 50) a third
    assert moves == 3 and set(returns) == set(range(1, cfg.t_max + 1)) and returns[3] > returns[2] > returns[1]
    res = evaluate_policy(table, "hard", build_pose_seek(table=table, config=cfg), cfg)
    assert res.recognized.all() and (res.decisions[res.start_box] == 1).all()
    assert res.ret.mean() > evaluate_policy(table, "hard", PassivePolicy(), cfg).ret.mean()
    # the hard split's data does not move the choice: only the training contexts are read
    other = _hidden_everywhere_but(cross[:5])
    mixed = ObservationTable.from_arrays(
        np.concatenate([np.asarray(table.features)[:1], np.asarray(other.features)[1:]]),
        np.concatenate([np.asarray(table.probs)[:1], np.asarray(other.probs)[1:]]),
        np.concatenate([np.asarray(table.boxes)[:1], np.asarray(other.boxes)[1:]]),
        scenes=["001", "002"], contexts=[1, 2], targets=[0, 0], splits=["train", "hard"])
    assert pose_seek_moves(mixed, cfg)[1] == returns

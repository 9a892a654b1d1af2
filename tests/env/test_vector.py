"""The batched env behind Gymnasium's make_vec, SB3's VecEnv, MaskablePPO and flat actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from uevavd.env import ENV_ID, AODEnv, BatchedAODEnv, DiscreteActions, EnvConfig
from uevavd.env.vector import AODVectorEnv


def _torchrl():
    """TorchRL, where it runs: it refuses gymnasium 1.0 (the d3rlpy extra's pin) at import."""
    if not hasattr(gym.vector, "AutoresetMode"):
        pytest.skip("TorchRL refuses gymnasium 1.0 (installed here for d3rlpy)")
    pytest.importorskip("torchrl")


def _vec(table, n=6, **kw):
    return gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", table=table, **kw)


def test_make_vec_is_the_batched_env_step_for_step(table):
    venv = _vec(table, n=6, split="train", config=EnvConfig(t_max=3), autoreset_mode="same_step")
    assert isinstance(venv, AODVectorEnv) and venv.num_envs == 6
    ref = BatchedAODEnv(table, "train", 6, EnvConfig(t_max=3))
    twin = _vec(table, n=6, split="train", config=EnvConfig(t_max=3)).unwrapped
    twin._rngs = [gym.utils.seeding.np_random(5 + i)[0] for i in range(6)]  # what reset(seed=5) seeds
    ref.start_sampler = twin._draw_starts  # the vector env's starts: its per-env generators, seeded alike
    obs, _ = venv.reset(seed=5)
    robs = ref.reset()
    rng = np.random.default_rng(0)
    finished = 0
    for _ in range(30):
        assert venv.observation_space.contains(obs)
        np.testing.assert_array_equal(obs["features"], robs["features"].numpy())
        np.testing.assert_array_equal(obs["t"], robs["t"].numpy())
        np.testing.assert_array_equal(obs["action_mask"], robs["mask"].numpy().astype(np.int8))
        actions = np.stack([rng.integers(0, 7, 6), rng.integers(0, 4, 6)], 1)
        obs, reward, term, trunc, infos = venv.step(actions)
        robs, rreward, rdone, rinfo = ref.step(torch.as_tensor(actions[:, 0]), torch.as_tensor(actions[:, 1]))
        # float64, as Gymnasium's sync mode gives it (the batched env's float32 for training)
        assert reward.dtype == np.float64
        np.testing.assert_array_equal(reward.astype(np.float32), rreward.numpy())
        np.testing.assert_array_equal(term, rdone.numpy())
        assert not trunc.any()
        for i in np.flatnonzero(term):  # same-step autoreset: the last observation in infos
            finished += 1
            assert infos["_final_obs"][i] and infos["final_return"][i] == float(rinfo["final_return"][i])
            last = infos["final_obs"][i]
            s, v = int(rinfo["final_scene"][i]), int(rinfo["final_view"][i])
            np.testing.assert_array_equal(last["features"], np.asarray(table.features[s, v], np.float32))
            assert last["t"] == int(rinfo["final_decisions"][i])
    assert finished > 20


def test_flat_actions_match_the_pairs_and_masks_follow_the_space(table):
    multi = _vec(table, n=4, config=EnvConfig(), autoreset_mode="same_step")
    flat = _vec(table, n=4, config=EnvConfig(), actions="flat", autoreset_mode="same_step")
    assert flat.single_action_space == gym.spaces.Discrete(28)
    om, _ = multi.reset(seed=1)
    of, _ = flat.reset(seed=1)
    rng = np.random.default_rng(1)
    for _ in range(12):
        np.testing.assert_array_equal(of["action_mask"], om["action_mask"].reshape(4, -1))
        np.testing.assert_array_equal(flat.action_masks(), om["action_mask"].reshape(4, -1).astype(bool))
        per_dim = multi.action_masks()
        assert per_dim.shape == (4, 7 + 4) and per_dim[:, 6].all() and per_dim[:, 7:].all()
        a = rng.integers(0, 28, 4)
        om, rm, tm, _, _ = multi.step(np.stack([a // 4, a % 4], 1))
        of, rf, tf, _, _ = flat.step(a)
        np.testing.assert_array_equal(rm, rf)
        np.testing.assert_array_equal(tm, tf)
    with pytest.raises(ValueError, match=r"expected \(4,\) indices of Discrete\(28\)"):
        flat.step(np.array([0, 1, 28, 2]))
    with pytest.raises(ValueError, match=r"expected \(4, 2\)"):
        multi.step(np.zeros(4, np.int64))


def test_single_env_takes_the_flat_index_and_offers_masks(table):
    a, b = AODEnv(table, "train"), AODEnv(table, "train")
    a.reset(seed=3)
    b.reset(seed=3)
    for flat in (5, 13, 26):
        ra = a.step(np.int64(flat))
        rb = b.step(np.array([flat // 4, flat % 4]))
        assert ra[1] == rb[1] and ra[2] == rb[2] and ra[4]["view"] == rb[4]["view"]
        if ra[2]:
            break
    obs, _ = a.reset(seed=0)
    with pytest.raises(ValueError, match="or a flat index 0..27"):
        a.step(28)
    assert a.action_masks().shape == (11,)
    wrapped = DiscreteActions(AODEnv(table, "train"))
    obs, _ = wrapped.reset(seed=0)
    np.testing.assert_array_equal(wrapped.action_masks(), obs["action_mask"].astype(bool))


@pytest.mark.parametrize("algo", ["dqn", "ppo"])
def test_sb3_trains_on_the_vector_form(table, algo):
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import VecMonitor

    from uevavd.env.sb3 import SB3VecEnv

    venv = VecMonitor(SB3VecEnv(_vec(table, n=16, actions="flat" if algo == "dqn" else "multi")))
    if algo == "dqn":
        model = sb3.DQN("MultiInputPolicy", venv, learning_starts=200, train_freq=1, seed=0, device="cpu",
                        policy_kwargs={"net_arch": [32]})
    else:
        model = sb3.PPO("MultiInputPolicy", venv, n_steps=64, batch_size=256, n_epochs=2, seed=0, device="cpu",
                        policy_kwargs={"net_arch": [32]})
    import tempfile
    from pathlib import Path

    from uevavd.env.sb3 import silent_logger

    litter = set(Path(tempfile.gettempdir()).glob("SB3-*"))
    model.set_logger(silent_logger())
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model.learn(total_timesteps=3000)
    finally:
        torch.set_num_threads(threads)
    assert set(Path(tempfile.gettempdir()).glob("SB3-*")) <= litter  # no empty SB3-<date> folder left behind
    assert model.num_timesteps >= 3000
    assert len(model.ep_info_buffer) == model.ep_info_buffer.maxlen  # VecMonitor saw >= 100 episodes end
    obs = venv.reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == ((16,) if algo == "dqn" else (16, 2))


def test_maskable_ppo_runs_on_both_forms(table):
    pytest.importorskip("sb3_contrib")
    from sb3_contrib import MaskablePPO

    from uevavd.env.sb3 import SB3VecEnv, silent_logger

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for env in (SB3VecEnv(_vec(table, n=8, actions="flat")), DiscreteActions(AODEnv(table, "train"))):
            model = MaskablePPO("MultiInputPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0,
                                device="cpu", policy_kwargs={"net_arch": [16]})
            model.set_logger(silent_logger())
            model.learn(total_timesteps=256)
            assert model.num_timesteps >= 256
    finally:
        torch.set_num_threads(threads)


def test_torchrl_wraps_the_env_and_its_spec_check_passes(table):
    """TorchRL's GymWrapper turns MultiDiscrete([7, A]) into one categorical of 7 * A and steps
    with the flat index, which AODEnv accepts."""
    _torchrl()
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    env = GymWrapper(gym.make(ENV_ID, table=table, split="train"))
    assert env.action_spec.shape[-1] == 28
    check_env_specs(env)
    rollout = env.rollout(12)
    assert rollout["next", "done"].any()  # episodes end (stop or T_max) through the flat actions


def test_torchrl_gymenv_makes_the_env_by_its_id(table):
    """``torchrl.envs.GymEnv("uevavd/AOD-v0", table=...)`` passes ``frameskip=`` and drops it
    on the standard TypeError, which AODEnv raises for an unexpected keyword."""
    _torchrl()
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv(ENV_ID, table=table, split="train")
    check_env_specs(env)
    assert env.rollout(12)["next", "done"].any()


def test_the_vector_env_states_its_autoreset_mode_and_refuses_use_after_close(table):
    """Gymnasium 1.x conventions: ``autoreset_mode`` as an attribute (TorchRL reads it there)
    beside the metadata key; ``close()`` sets ``closed`` and a later step or reset is an error."""
    env = AODVectorEnv(table, "train", num_envs=4)
    if hasattr(gym.vector, "AutoresetMode"):  # Gymnasium 1.1 on: its own vector envs' default
        assert env.autoreset_mode == gym.vector.AutoresetMode.NEXT_STEP == env.metadata["autoreset_mode"]
        assert _vec(table, n=2).autoreset_mode == gym.vector.AutoresetMode.NEXT_STEP  # make_vec's too
        env.use_autoreset_mode("same_step")
        assert env.autoreset_mode == gym.vector.AutoresetMode.SAME_STEP == env.metadata["autoreset_mode"]
    env.reset(seed=0)
    with pytest.raises(RuntimeError, match="before the first reset"):
        env.use_autoreset_mode("next_step")
    env.close()
    assert env.closed
    with pytest.raises(RuntimeError, match="closed"):
        env.step(np.zeros((4, 2), np.int64))
    with pytest.raises(RuntimeError, match="closed"):
        env.reset(seed=0)


def test_the_vector_env_follows_gymnasium_1_conventions_like_the_single_env(table):
    """Rewards equal the single env's (float64), float actions equal to integers are taken,
    every step reports the single env's info (going-on envs at the top level, ended ones in
    ``final_info`` with its masks), a list of seeds uses all its entries, no seed is not
    always seed 0, and make_vec takes ``render_mode``."""
    cfg = EnvConfig(t_max=3)
    venv = _vec(table, n=4, split="train", config=cfg, autoreset_mode="same_step")
    singles = [AODEnv(table, "train", cfg) for _ in range(4)]
    obs, _ = venv.reset(seed=3)
    scenes = venv.unwrapped._batched.tensors.scenes[venv.unwrapped._batched._scene].tolist()
    views = venv.unwrapped._batched._view.tolist()
    for env, s, v in zip(singles, scenes, views, strict=True):
        env.reset(options={"scene": s, "view": v})
    rng = np.random.default_rng(0)
    seen_final = seen_going = 0
    for _ in range(6):
        actions = np.stack([rng.integers(0, 6, 4), rng.integers(0, 4, 4)], 1)
        obs, reward, term, _, infos = venv.step(actions.astype(np.float32))  # floats equal to integers
        for i, env in enumerate(singles):
            _, r, done, _, info = env.step(actions[i])
            assert reward[i] == r and term[i] == done  # float64, bit for bit
            where = infos["final_info"] if done else infos
            assert where["_return"][i] and where["return"][i] == info["return"]
            for key in ("recognized", "correct", "stopped", "view", "t", "scene", "steps"):
                assert where[key][i] == info[key], key
            if done:
                seen_final += 1
                assert infos["_final_info"][i]
                env.reset(options={"scene": int(obs_scene(venv, i)), "view": int(venv.unwrapped._batched._view[i])})
            else:
                seen_going += 1
    assert seen_final and seen_going
    with pytest.raises(ValueError, match="expected integers"):
        venv.step(np.full((4, 2), 0.5))

    def first_views(seed):
        venv.reset(seed=seed)
        return venv.unwrapped._batched._view.tolist()

    assert first_views([1, 2, 3, 4]) == first_views([1, 2, 3, 4]) != first_views([1, 2, 3, 5])
    assert first_views([1, 2, 3, 4])[:3] == first_views([1, 2, 3, 5])[:3]  # one generator per env
    with pytest.raises(ValueError, match="a list of 4"):
        venv.reset(seed=[1, 2])
    fresh = [_vec(table, n=8, split="train", config=cfg) for _ in range(2)]
    starts = [(f.reset()[0], f.unwrapped._batched._view.tolist())[1] for f in fresh]
    assert starts[0] != starts[1]  # seeded from the OS's entropy, as Gymnasium's envs are
    frames = _vec(table, n=2, split="train", render_mode="rgb_array")
    frames.reset(seed=0)
    out = frames.render()
    assert len(out) == 2 and out[0].dtype == np.uint8 and out[0].ndim == 3


def obs_scene(venv, i):
    b = venv.unwrapped._batched
    return b.tensors.scenes[b._scene][i]


def test_torchrl_and_gymnasiums_vector_wrappers_take_the_vector_env(table):
    """TorchRL's GymWrapper over the vector env passes its spec check (it failed on the missing
    ``autoreset_mode``); Gymnasium's RecordEpisodeStatistics reads its infos; FlattenObservation
    takes the default vector env (next-step autoreset, Gymnasium's own) and refuses a same-step
    one, and runs through the sync-mode recipe too."""
    venv = _vec(table, n=4, split="train")
    stats = gym.wrappers.vector.RecordEpisodeStatistics(venv)
    stats.reset(seed=0)
    for _ in range(8):
        _, _, term, _, infos = stats.step(stats.action_space.sample())
    assert "episode" in infos or len(stats.return_queue) > 0
    wrapped = gym.wrappers.vector.RecordEpisodeStatistics(gym.wrappers.vector.FlattenObservation(
        _vec(table, n=3, split="train")))
    obs, _ = wrapped.reset(seed=0)
    assert obs.shape[0] == 3 and obs.ndim == 2
    wrapped.step(wrapped.action_space.sample())
    if hasattr(gym.vector, "AutoresetMode"):  # Gymnasium 1.1 on checks the mode; 1.0's wrappers assume next-step
        # 1.4 refuses with a ValueError naming NEXT_STEP; 1.2 (RLlib's pin) with a bare assert
        with pytest.raises((ValueError, AssertionError), match="NEXT_STEP" if tuple(map(int, gym.__version__.split(".")[:2])) >= (1, 3) else ""):
            gym.wrappers.vector.FlattenObservation(_vec(table, n=2, split="train", autoreset_mode="same_step"))
    flat = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", wrappers=[gym.wrappers.FlattenObservation],
                        table=table, split="train")
    obs, _ = flat.reset(seed=0)
    assert obs.ndim == 2 and obs.shape[0] == 2
    flat.step(flat.action_space.sample())
    _torchrl()
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    with pytest.raises(RuntimeError, match="SAME_STEP"):  # TorchRL asks for same-step, as SB3 does
        GymWrapper(_vec(table, n=4, split="train"))
    env = GymWrapper(_vec(table, n=4, split="train", autoreset_mode="same_step"))
    assert tuple(env.batch_size) == (4,)
    check_env_specs(env)
    assert env.rollout(12)["next", "done"].any()


def _torchrl_env(path):
    from torchrl.envs import GymEnv

    return GymEnv(ENV_ID, table=path, split="train")


def test_torchrl_parallel_env_runs_the_env_in_worker_processes(table, tmp_path):
    """TorchRL's ParallelEnv over GymEnv("uevavd/AOD-v0", table=FOLDER): the worker process
    loads the table from its folder; the spec check passes and episodes end. One worker: each
    one imports TorchRL, torch and uevavd again (about 5 s of CPU); the batching over several
    is TorchRL's, and the batched env in one process is checked above."""
    _torchrl()
    import functools

    from torchrl.envs import ParallelEnv
    from torchrl.envs.utils import check_env_specs

    path = table.save(tmp_path / "table")
    env = ParallelEnv(1, functools.partial(_torchrl_env, str(path)), mp_start_method="spawn")
    try:
        check_env_specs(env)
        assert env.rollout(12)["next", "done"].any()
    finally:
        env.close()


def test_next_step_autoreset_returns_the_last_observation_then_resets_ignoring_the_action(table):
    """autoreset_mode="next_step", Gymnasium's own vector envs' convention: the ending step
    returns the episode's last observation (the same-step env's final_obs), and the env's next
    step starts the next episode (the same-step env's first observation, reward 0, not
    terminated), whatever action it is given."""
    cfg = EnvConfig(t_max=3)
    same = _vec(table, n=1, split="train", config=cfg, autoreset_mode="same_step")
    nxt = _vec(table, n=1, split="train", config=cfg)  # the default
    if hasattr(gym.vector, "AutoresetMode"):
        assert nxt.autoreset_mode == gym.vector.AutoresetMode.NEXT_STEP == nxt.metadata["autoreset_mode"]
    o1, _ = same.reset(seed=3)
    o2, _ = nxt.reset(seed=3)
    rng = np.random.default_rng(0)
    ended = 0
    while ended < 2:  # through the first two episodes (the extra reset step draws a start of its own)
        a = np.stack([rng.integers(0, 7, 1), rng.integers(0, 4, 1)], 1)
        o1, r1, t1, _, i1 = same.step(a)
        o2, r2, t2, _, i2 = nxt.step(a)
        assert r1[0] == r2[0] and t1[0] == t2[0] and "final_obs" not in i2
        if t1[0]:
            ended += 1
            for k in o2:
                np.testing.assert_array_equal(o2[k][0], i1["final_obs"][0][k])
            assert i2["return"][0] == i2["final_return"][0] == i1["final_return"][0]
            if ended == 2:  # the next start: drawn a step later here, so from another draw
                break
            o2, r2, t2, _, i2 = nxt.step(np.array([[6, 0]]))  # the reset step: its action is ignored
            assert r2[0] == 0.0 and not t2[0] and not i2.get("_return", [False])[0]
        for k in o1:
            np.testing.assert_array_equal(o1[k], o2[k])


def test_gymnasiums_vector_wrappers_run_over_next_step_autoreset(table):
    """FlattenObservation refused the vector env (same-step only); over next-step it runs, and
    RecordEpisodeStatistics counts each episode's return as the env reports it."""
    venv = _vec(table, n=3, split="train", config=EnvConfig(t_max=4), autoreset_mode="next_step")
    flat = gym.wrappers.vector.FlattenObservation(venv)
    stats = gym.wrappers.vector.RecordEpisodeStatistics(flat)
    obs, _ = stats.reset(seed=0)
    assert obs.shape == (3, gym.spaces.flatdim(venv.single_observation_space))
    summed, recorded = [], []
    running, resetting = np.zeros(3), np.zeros(3, bool)
    for _ in range(40):
        obs, reward, term, _, infos = stats.step(stats.action_space.sample())
        assert obs.shape[0] == 3 and not reward[resetting].any()
        running = np.where(resetting, 0.0, running + reward)
        summed += [(i, running[i]) for i in np.flatnonzero(term)]
        if "episode" in infos:
            recorded += [(i, float(infos["episode"]["r"][i])) for i in np.flatnonzero(infos["_episode"])]
        resetting = term
    assert len(summed) > 10 and len(recorded) == len(summed)
    assert np.allclose(np.array(sorted(recorded)), np.array(sorted(summed)), atol=1e-5)


def test_sb3_vec_env_asks_for_same_step_autoreset_itself(table):
    pytest.importorskip("stable_baselines3")
    from uevavd.env.sb3 import SB3VecEnv

    venv = SB3VecEnv(_vec(table, n=2, split="train"))  # make_vec's default, next-step
    assert not venv.venv._next_step
    started = _vec(table, n=2, split="train")
    started.reset(seed=0)
    with pytest.raises(ValueError, match="same-step autoreset .* wrap it before its first reset"):
        SB3VecEnv(started)
    with pytest.raises(ValueError, match="autoreset_mode='every_step'"):
        _vec(table, n=2, split="train", autoreset_mode="every_step")


@pytest.mark.parametrize("seed", [-1, 1.5, True, "3", [1, -2]])
def test_a_seed_that_is_not_one_is_named(table, seed):
    venv = _vec(table, n=2, split="train")
    with pytest.raises(ValueError, match=r"reset\(seed=.*\): expected an int >= 0, or a list of 2 of them"):
        venv.reset(seed=seed)
    venv.reset(seed=2**64)  # numpy's seeding takes any size, as the single env's


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_env_i_of_a_vector_env_seeded_s_is_the_single_env_seeded_s_plus_i(table, mode):
    """Gymnasium's convention (its SyncVectorEnv's): env i of a vector env reset with seed=s
    behaves as gym.make(...) reset with seed=s + i, and then, episode after episode, as that
    env reset without a seed. The vector env's envs used to share one stream."""
    cfg = EnvConfig(t_max=3)
    n = 3
    venv = _vec(table, n=n, split="train", config=cfg, autoreset_mode=mode)
    singles = [gym.make(ENV_ID, table=table, split="train", config=cfg) for _ in range(n)]
    obs, _ = venv.reset(seed=7)
    sobs = [env.reset(seed=7 + i)[0] for i, env in enumerate(singles)]
    rng = np.random.default_rng(0)
    restart = np.zeros(n, bool)  # next-step: the vector env's next step is env i's reset
    episodes = 0
    for _ in range(25):
        for i in range(n):
            for key in ("features", "box", "t", "action_mask"):
                np.testing.assert_array_equal(obs[key][i], sobs[i][key], err_msg=f"env {i}, {key}")
        actions = np.stack([rng.integers(0, 7, n), rng.integers(0, 4, n)], 1)
        obs, _, term, _, infos = venv.step(actions)
        for i, env in enumerate(singles):
            if restart[i]:
                sobs[i], _ = env.reset()
                restart[i] = False
                continue
            sobs[i], _, done, _, _ = env.step(actions[i])
            if done:
                episodes += 1
                if mode == "same_step":
                    np.testing.assert_array_equal(infos["final_obs"][i]["features"], sobs[i]["features"])
                    sobs[i], _ = env.reset()
                else:
                    restart[i] = True
    assert episodes >= 6
    assert [venv.reset(seed=[7, None, 9])[0]["features"][i].tolist() for i in (0, 2)] == [
        singles[0].reset(seed=7)[0]["features"].tolist(), singles[2].reset(seed=9)[0]["features"].tolist()]

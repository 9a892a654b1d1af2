"""BatchedAODEnv agrees exactly with AODEnv; auto-reset, explicit starts, resume, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.env import AODEnv, BatchedAODEnv, EnvConfig


def drive_both(table, split, config, n=12, steps=40, seed=0, device="cpu"):
    """Same random actions through N AODEnvs and one BatchedAODEnv; compare every step."""
    benv = BatchedAODEnv(table, split, n, config, device=device, seed=seed)
    envs = [AODEnv(table, split, config) for _ in range(n)]
    rng = np.random.default_rng(seed)
    obs = benv.reset()

    def restart(i, o):
        return envs[i].reset(options={"scene": int(o["scene"][i]), "view": int(o["view"][i])})[0]

    singles = [restart(i, obs) for i in range(n)]
    n_done = 0
    for _ in range(steps):
        for i, o in enumerate(singles):
            np.testing.assert_array_equal(obs["features"][i].cpu().numpy(), o["features"])
            np.testing.assert_array_equal(obs["box"][i].cpu().numpy(), o["box"])
            np.testing.assert_array_equal(obs["mask"][i].cpu().numpy(), o["action_mask"].astype(bool))
            assert int(obs["t"][i]) == o["t"]
        a_type = rng.integers(0, 7, n)
        a_type[rng.random(n) < 0.6] = rng.integers(0, 6)  # mostly moves, so T_max is reached too
        a_range = rng.integers(0, config.max_range, n)
        obs, reward, done, info = benv.step(torch.as_tensor(a_type), torch.as_tensor(a_range))
        assert reward.dtype == torch.float32 and done.dtype == torch.bool
        for i in range(n):
            o, r, term, trunc, inf = envs[i].step(np.array([a_type[i], a_range[i]]))
            assert np.float32(r) == reward[i].item()
            assert bool(done[i]) == term and not trunc
            if term:
                n_done += 1
                assert int(info["final_view"][i]) == inf["view"]
                assert int(info["final_scene"][i]) == inf["scene"]
                assert bool(info["final_recognized"][i]) == inf["recognized"]
                assert bool(info["final_correct"][i]) == inf["correct"]
                assert bool(info["final_stopped"][i]) == inf["stopped"]
                assert float(info["final_return"][i]) == inf["return"]
                assert float(info["final_distance_m"][i]) == inf["distance_m"]
                assert int(info["final_steps"][i]) == inf["steps"]
                assert int(info["final_decisions"][i]) == inf["t"]
                assert int(obs["t"][i]) == 0  # auto-reset: obs is the next episode's first
                o = restart(i, obs)
            singles[i] = o
    return n_done


def test_batched_matches_single_env(table):
    assert drive_both(table, "train", EnvConfig()) > 50
    assert drive_both(table, "test", EnvConfig(t_max=2, max_range=3, C=0.05, thre=0.4), seed=1) > 100
    # reward magnitudes that float32 cannot hold exactly: the returns still agree bit for bit
    assert drive_both(table, "train", EnvConfig(xi1=0.3, xi2=0.07, C=0.03), seed=2) > 50


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_batched_matches_single_env_cuda(table):
    assert drive_both(table, "train", EnvConfig(), device="cuda") > 50


def test_explicit_starts_and_split(table):
    env = BatchedAODEnv(table, "hard", 4, seed=3)
    obs = env.reset()
    assert set(obs["scene"].tolist()) <= {4, 5}
    obs = env.reset(scenes=torch.tensor([4, 5, 5, 4]), views=torch.tensor([0, 1, 2, 604]))
    assert obs["scene"].tolist() == [4, 5, 5, 4] and obs["view"].tolist() == [0, 1, 2, 604]
    np.testing.assert_array_equal(obs["features"][1].numpy(), table.features[5, 1].astype(np.float32))
    assert obs["t"].tolist() == [0] * 4 and obs["mask"].shape == (4, 7, 4)
    with pytest.raises(ValueError, match="split 'hard'"):
        env.reset(scenes=torch.tensor([0, 4, 4, 4]))
    with pytest.raises(ValueError, match="view indices"):
        env.reset(views=torch.tensor([605, 0, 0, 0]))
    only = BatchedAODEnv(table, "train", 8, contexts=[2])
    assert only.reset()["scene"].tolist() == [1] * 8


def test_state_dict_resumes_exactly(table):
    def actions(k):
        g = torch.Generator().manual_seed(k)
        return torch.randint(0, 7, (16,), generator=g), torch.randint(0, 4, (16,), generator=g)

    a = BatchedAODEnv(table, "train", 16, seed=7)
    a.reset()
    for k in range(5):
        a.step(*actions(k))
    state = a.state_dict()
    b = BatchedAODEnv(table, "train", 16, seed=99)
    b.load_state_dict(state)
    for k in range(5, 15):
        oa, ra, da, _ = a.step(*actions(k))
        ob, rb, db, _ = b.step(*actions(k))
        assert torch.equal(ra, rb) and torch.equal(da, db) and torch.equal(oa["view"], ob["view"])
    with pytest.raises(ValueError, match="n_envs"):
        BatchedAODEnv(table, "train", 8).load_state_dict(state)


def test_bad_actions_and_sizes(table):
    env = BatchedAODEnv(table, "train", 3)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(torch.zeros(3, dtype=torch.long), torch.zeros(3, dtype=torch.long))
    env.reset()
    with pytest.raises(ValueError, match=r"action \(7, 0\) of env 1"):
        env.step(torch.tensor([0, 7, 0]), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="range index 0..3"):
        env.step(torch.zeros(3, dtype=torch.long), torch.tensor([0, 0, 4]))
    with pytest.raises(ValueError, match=r"expected \(3,\)"):
        env.step(torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long))
    with pytest.raises(ValueError, match="n_envs"):
        BatchedAODEnv(table, "train", 0)


def test_float16_features_match(table):
    a = BatchedAODEnv(table, "train", 5, seed=1)
    b = BatchedAODEnv(table, "train", 5, seed=1, features_dtype=torch.float16)
    assert torch.equal(a.reset()["features"], b.reset()["features"])

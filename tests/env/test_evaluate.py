"""Exhaustive evaluation harness, baselines and the DP oracle (vs brute force)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from uevavd.data.grid import N_VIEWS, STOP, transitions
from uevavd.env import (
    AODEnv,
    EnvConfig,
    OraclePolicy,
    PassivePolicy,
    RandomPolicy,
    evaluate_policy,
    flight_pays,
    oracle_values,
)
from uevavd.env.batched import EnvTensors

from .conftest import make_table


class ScriptPolicy:
    """Deterministic, state-dependent: type/range from a hash of (view, t, scene)."""

    calls = 0

    def reset(self, n):
        self.calls = 0

    def act(self, obs):
        self.calls += 1
        h = obs["view"] * 7 + obs["t"] * 13 + obs["scene"] * 3
        a_type = torch.where(h % 5 == 0, STOP, h % 6)
        return a_type, (h // 6) % 4


@pytest.mark.parametrize("cfg", [EnvConfig(t_max=3), EnvConfig(t_max=3, xi1=0.3, C=0.03)], ids=["default", "xi1-0.3"])
def test_harness_equals_single_env_episodes(table, cfg):
    res = evaluate_policy(table, "hard", ScriptPolicy(), cfg)
    assert len(res) == 2 * N_VIEWS
    assert res.scene.tolist() == [4] * N_VIEWS + [5] * N_VIEWS
    assert res.start_view.tolist() == list(range(N_VIEWS)) * 2
    env = AODEnv(table, "hard", cfg)
    pol = ScriptPolicy()
    for i in range(0, len(res), 37):
        obs, info = env.reset(options={"scene": int(res.scene[i]), "view": int(res.start_view[i])})
        views, term = [info["view"]], False
        while not term:
            o = {"view": torch.tensor([info["view"]]), "t": torch.tensor([info["t"]]), "scene": torch.tensor([info["scene"]])}
            a_type, a_range = pol.act(o)
            obs, _, term, _, info = env.step(np.array([int(a_type[0]), int(a_range[0])]))
            if not info.get("stopped", False):
                views.append(info["view"])
        assert res.ret[i] == pytest.approx(info["return"], abs=1e-12)
        assert res.final_view[i] == info["view"] and res.decisions[i] == info["t"]
        assert res.metres[i] == info["distance_m"] and res.steps[i] == info["steps"]
        assert res.recognized[i] == info["recognized"] and res.correct[i] == info["correct"]
        assert res.stopped[i] == info["stopped"] and res.context[i] == info["context"]
        traj = res.trajectories[i]
        assert traj[traj >= 0].tolist() == views


def test_passive_and_random_baselines(table):
    cfg = EnvConfig()
    res = evaluate_policy(table, "train", PassivePolicy(), cfg)
    s = res.summary()
    assert s["path_m"] == 0 and s["stop_rate"] == 1 and s["steps_per_episode"] == 1
    reco = cfg.recognized(table.true_class_probs())[:3].ravel()
    assert s["recognition_rate"] == pytest.approx(reco.mean())
    assert s["mean_return"] == pytest.approx(np.where(reco, 0.5, -0.5).mean())
    assert s["accuracy"] == pytest.approx(table.argmax_correct()[:3].mean())
    r1 = evaluate_policy(table, "train", RandomPolicy(seed=1), cfg)
    r2 = evaluate_policy(table, "train", RandomPolicy(seed=1), cfg)
    np.testing.assert_array_equal(r1.ret, r2.ret)
    # same seed, same episodes; every episode ends within T_max; it mixes stops and moves
    assert r1.decisions.max() <= cfg.t_max and 0 < r1.summary()["stop_rate"] < 1
    assert r1.summary()["path_steps"] > 0


def test_breakdowns_and_json(table, tmp_path):
    res = evaluate_policy(table, "test", PassivePolicy())
    ctx = res.per_context()
    assert ctx["context"].tolist() == [4, 5, 6] and ctx["episodes"].tolist() == [N_VIEWS] * 3
    assert ctx["target"].tolist() == [table.class_names[t] for t in table.targets[3:]]
    tgt = res.per_target()
    assert tgt["episodes"].sum() == 3 * N_VIEWS
    assert (tgt.set_index("target")["mean_return"] <= 0.5).all()
    path = tmp_path / "eval" / "hard.json"
    data = json.loads(res.to_json(path))
    assert json.loads(path.read_text()) == data
    assert data["summary"]["episodes"] == 3 * N_VIEWS and len(data["per_context"]) == 3


def test_prepared_tensors_and_context_subset(table):
    cfg = EnvConfig()
    tb = EnvTensors(table, "train", cfg, contexts=[3, 1])
    res = evaluate_policy(tb, "train", PassivePolicy())
    assert sorted(set(res.context.tolist())) == [1, 3] and len(res) == 2 * N_VIEWS


def brute_force(table, cfg: EnvConfig) -> np.ndarray:
    """(S, 605) best return by enumerating every distinct action sequence (open loop is
    optimal: the CMDP is deterministic). Sequences: k moves then stop (k < T_max), or
    T_max moves; stop's range is irrelevant."""
    tr = transitions(cfg.max_range)
    reco = cfg.recognized(table.true_class_probs())
    term = np.where(reco, cfg.xi1, -cfg.xi1)
    moves = [(a, r) for a in range(6) for r in range(cfg.max_range)]
    best = np.full(reco.shape, -np.inf)
    starts = np.arange(N_VIEWS)
    for k in range(cfg.t_max + 1):
        for seq in itertools.product(moves, repeat=k):
            v, ret = starts, np.zeros(reco.shape)
            for t, (a, r) in enumerate(seq):
                v = tr.next_view[v, a, r]
                last = t == cfg.t_max - 1
                ret = ret + cfg.gamma**t * ((term[:, v] if last else -cfg.xi2) - cfg.C * (r + 1))
            if k < cfg.t_max:
                ret = ret + cfg.gamma**k * term[:, v]  # stop
            best = np.maximum(best, ret)
    return best


@pytest.mark.parametrize(
    ("n_scenes", "cfg"),
    [(2, EnvConfig(t_max=2)), (1, EnvConfig(t_max=3, max_range=2, C=0.05, thre=0.3)), (1, EnvConfig(t_max=1))],
)
def test_oracle_equals_brute_force(n_scenes, cfg):
    table = make_table(n_scenes, splits=("train",) * n_scenes, seed=11)
    ora = oracle_values(table, cfg)
    np.testing.assert_allclose(ora.value[:, cfg.t_max], brute_force(table, cfg), atol=1e-12)
    # the oracle policy run through the harness achieves exactly V(start, T_max)
    res = evaluate_policy(table, "train", OraclePolicy(table, cfg), cfg)
    np.testing.assert_allclose(res.ret, ora.value[:, cfg.t_max].ravel(), atol=1e-12)


def test_a_flight_pays_exactly_where_the_oracle_flies():
    """flight_pays: the best reachable return beats stopping, with k + 1 decisions left, wherever
    the oracle's action with k + 1 left is a move, and never where the recognizer already
    recognises the view (stopping there is the best reward)."""
    table = make_table(2, splits=("train",) * 2, seed=5)
    cfg = EnvConfig(t_max=3)
    reco = cfg.recognized(table.true_class_probs())
    pays = flight_pays(reco, cfg)
    ora = oracle_values(table, cfg)
    assert pays.shape == (3, 2, 605) and pays.any() and not pays.all()
    for k in range(cfg.t_max):
        np.testing.assert_array_equal(pays[k], ora.best_type[:, k + 1] != STOP)
    assert not pays[:, reco].any()


def test_oracle_bounds_every_policy(table):
    cfg = EnvConfig()
    bound = oracle_values(table, cfg).value[:3, cfg.t_max].ravel()
    for pol in (PassivePolicy(), RandomPolicy(seed=0), ScriptPolicy()):
        res = evaluate_policy(table, "train", pol, cfg)
        assert (res.ret <= bound + 1e-12).all()
    res = evaluate_policy(table, "train", OraclePolicy(table, cfg), cfg)
    assert res.summary()["recognition_rate"] >= evaluate_policy(table, "train", PassivePolicy()).summary()["recognition_rate"]


def test_oracle_q_values_agree_with_values(table):
    cfg = EnvConfig(t_max=3)
    ora = oracle_values(table, cfg, with_q=True)
    q = ora.q[:, 1:].reshape(len(table), cfg.t_max, N_VIEWS, -1)
    np.testing.assert_allclose(q.max(-1), ora.value[:, 1:])
    flat = ora.q.reshape(len(table), cfg.t_max + 1, N_VIEWS, -1)
    chosen = np.take_along_axis(flat, (ora.best_type * cfg.max_range + ora.best_range)[..., None], -1)[..., 0]
    np.testing.assert_allclose(chosen[:, 1:], ora.value[:, 1:])  # the policy's action attains V
    assert oracle_values(table, cfg).q is None


def test_the_recognition_rule_is_the_env_configs():
    """One rule, one place: recognised means the true class's probability is above thre
    (strictly), read by the env, the batched env, the oracle and the trajectories alike."""
    from uevavd.env.config import EnvConfig

    np.testing.assert_array_equal(EnvConfig(thre=0.4).recognized(np.array([0.39, 0.4, 0.41])), [False, False, True])

"""Online clients without a flattener of their own, each in one line: the env's flat observation
(``observation="flat"``, the layout FlatPolicy reads, the joint mask at its end) and the
``"masked"`` form (RLlib's ``observations`` / ``action_mask``), CleanRL's DQN loop, skrl's DQN
and RLlib's PPO with action masking (skrl and RLlib skip without their extras)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import uevavd.env
from uevavd.data.grid import N_TYPES
from uevavd.env import IMPORTABLE_ID, FlatPolicy, evaluate_policy, flat_observation
from uevavd.testing.policy import toy_table

A = 4
K = N_TYPES * A


@pytest.fixture(scope="module")
def table():
    return toy_table(n_train=3, n_hard=2, feature_dim=8)


@pytest.mark.parametrize("pose", [False, True])
def test_the_flat_forms_carry_the_dict_observation_in_flat_policys_layout(table, pose):
    plain = gym.make(uevavd.env.ENV_ID, table=table, pose=pose)
    flat = gym.make(uevavd.env.ENV_ID, table=table, pose=pose, actions="flat", observation="flat")
    masked = gym.make(uevavd.env.ENV_ID, table=table, pose=pose, actions="flat", observation="masked")
    for env in (flat, masked):
        check_env(env.unwrapped, skip_render_check=True)
    o, _ = plain.reset(seed=3)
    f, _ = flat.reset(seed=3)
    m, _ = masked.reset(seed=3)
    assert f.dtype == np.float32 and flat.observation_space.contains(f) and masked.observation_space.contains(m)
    np.testing.assert_array_equal(f, flat_observation(o))  # FlatPolicy's layout
    np.testing.assert_array_equal(m["observations"], f)
    np.testing.assert_array_equal(m["action_mask"], o["action_mask"].reshape(-1))
    np.testing.assert_array_equal(f[-K:], flat.unwrapped.action_masks())
    assert f.shape == (8 + 4 + 3 * pose + 1 + K,)
    with pytest.raises(ValueError, match="observation='image'"):
        gym.make(uevavd.env.ENV_ID, table=table, observation="image")


def test_gymnasiums_vector_wrappers_take_the_default_and_the_flat_vector_env(table):
    from gymnasium.wrappers.vector import FlattenObservation, RecordEpisodeStatistics

    for kw in ({}, {"actions": "flat", "observation": "flat"}):
        env = gym.make_vec(uevavd.env.ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", table=table, **kw)
        env = RecordEpisodeStatistics(FlattenObservation(env) if not kw else env)
        env.reset(seed=0)
        stop = np.full(3, K - A) if kw else np.tile([N_TYPES - 1, 0], (3, 1))
        obs, _, term, _, info = env.step(stop)
        assert term.all() and np.allclose(info["episode"]["l"], 1)
        assert obs.dtype == (np.float32 if kw else np.float64)  # Gymnasium's FlattenObservation: float64


def test_cleanrls_dqn_loop_trains_through_the_flat_env_and_scores_with_flat_policy(table):
    """CleanRL's dqn.py, cut to its loop: make_vec in one line, a Q MLP over the flat
    observation, epsilon-greedy over the allowed actions (the mask is the last 7 x A entries),
    a replay buffer and a target net; the trained network then scores with evaluate_policy."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    envs = gym.make_vec(uevavd.env.ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", table=table,
                        actions="flat", observation="flat")
    n_obs = envs.single_observation_space.shape[0]
    q = torch.nn.Sequential(torch.nn.Linear(n_obs, 64), torch.nn.ReLU(), torch.nn.Linear(64, K))
    target = torch.nn.Sequential(torch.nn.Linear(n_obs, 64), torch.nn.ReLU(), torch.nn.Linear(64, K))
    target.load_state_dict(q.state_dict())
    opt = torch.optim.Adam(q.parameters(), lr=1e-3)
    buf: list[tuple] = []
    obs, _ = envs.reset(seed=0)
    envs.single_action_space.seed(0)
    forbidden, ended = 0, np.zeros(4, bool)
    for step in range(400):
        mask = obs[:, -K:] > 0
        with torch.no_grad():
            greedy = q(torch.as_tensor(obs)).masked_fill(~torch.as_tensor(mask), -torch.inf).argmax(1).numpy()
        explore = rng.random(4) < max(0.05, 1 - step / 200)
        random = np.array([envs.single_action_space.sample(mask=m) for m in mask.astype(np.int8)])  # as the docs
        actions = np.where(explore, random, greedy)
        forbidden += int((~mask[np.arange(4), actions]).sum())
        nxt, reward, term, trunc, _ = envs.step(actions)
        for i in np.flatnonzero(~ended):  # next-step autoreset: the step after an end only resets
            buf.append((obs[i], actions[i], reward[i], nxt[i], term[i] or trunc[i]))
        obs, ended = nxt, term | trunc
        if len(buf) > 64:
            batch = [buf[j] for j in rng.integers(0, len(buf), 32)]
            o, a, r, n, d = (np.array([b[k] for b in batch]) for k in range(5))
            with torch.no_grad():
                nq = target(torch.as_tensor(n)).masked_fill(~torch.as_tensor(n[:, -K:] > 0), -torch.inf).max(1).values
                y = torch.as_tensor(r, dtype=torch.float32) + 0.9 * nq * (1 - torch.as_tensor(d, dtype=torch.float32))
            loss = torch.nn.functional.mse_loss(q(torch.as_tensor(o)).gather(1, torch.as_tensor(a)[:, None])[:, 0], y)
            opt.zero_grad()
            loss.backward()
            opt.step()
        if step % 50 == 0:
            target.load_state_dict(q.state_dict())
    assert forbidden == 0
    # the trained network scores as it is: FlatPolicy feeds it the same flat observation
    res = evaluate_policy(table, "hard", FlatPolicy(lambda x: q(torch.as_tensor(x)).detach().numpy(), max_range=A))
    assert res.summary()["episodes"] == 2 * 605 and np.isfinite(res.ret).all()


class _Forbidden(gym.vector.VectorWrapper):
    """Counts the actions a client sends that the observation it acted on forbids."""

    def __init__(self, env):
        super().__init__(env)
        self.count = 0

    def reset(self, **kwargs):
        self.obs, info = self.env.reset(**kwargs)
        return self.obs, info

    def step(self, actions):
        a = np.asarray(actions).reshape(-1).astype(int)
        self.count += int((self.obs[:, -K:][np.arange(len(a)), a] == 0).sum())
        self.obs, *rest = self.env.step(actions)
        return (self.obs, *rest)


@pytest.mark.parametrize("masked", [True, False])
def test_skrls_dqn_trains_on_the_flat_vector_env_and_keeps_to_the_mask(table, masked):
    """skrl's DQN draws its random actions from the model's random_act and its greedy ones and
    TD targets from compute: a Q model that masks both with the observation's last 7 x A
    entries (docs/environment.md's lines) takes no forbidden action; skrl's default takes some."""
    pytest.importorskip("skrl", reason="skrl is not installed (pip install skrl)")
    from skrl.agents.torch.dqn import DQN
    from skrl.envs.wrappers.torch import wrap_env
    from skrl.memories.torch import RandomMemory
    from skrl.models.torch import DeterministicMixin, Model
    from skrl.trainers.torch import SequentialTrainer

    class QNet(DeterministicMixin, Model):
        def __init__(self, observation_space, action_space, device):
            Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
            DeterministicMixin.__init__(self)
            self.net = torch.nn.Sequential(torch.nn.Linear(observation_space.shape[0], 32), torch.nn.ReLU(),
                                           torch.nn.Linear(32, action_space.n))

        def compute(self, inputs, role=""):
            return self.net(inputs["observations"]), {}

    class MaskedQNet(QNet):  # the mask is the observation's last 7 * A entries
        def compute(self, inputs, role=""):
            x, n = inputs["observations"], self.action_space.n
            return self.net(x).masked_fill(x[:, -n:] == 0, torch.finfo(x.dtype).min), {}

        def random_act(self, inputs, *, role=""):
            x, n = inputs["observations"], self.action_space.n
            return torch.multinomial((x[:, -n:] > 0).float(), 1), {}

    torch.manual_seed(0)
    counted = _Forbidden(gym.make_vec(uevavd.env.ENV_ID, num_envs=4, vectorization_mode="vector_entry_point",
                                      table=table, actions="flat", observation="flat"))
    env = wrap_env(counted)
    assert env.observation_space.dtype == np.float32
    net_class = MaskedQNet if masked else QNet
    models = {"q_network": net_class(env.observation_space, env.action_space, env.device),
              "target_q_network": net_class(env.observation_space, env.action_space, env.device)}
    agent = DQN(models=models, memory=RandomMemory(memory_size=500, num_envs=4, device=env.device),
                cfg={"learning_starts": 20, "discount_factor": 0.9, "batch_size": 32},
                observation_space=env.observation_space, action_space=env.action_space, device=env.device)
    before = [p.detach().clone() for p in models["q_network"].parameters()]
    SequentialTrainer(cfg={"timesteps": 80, "headless": True, "disable_progressbar": True}, env=env,
                      agents=agent).train()
    net = models["q_network"].net
    assert any(not torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))  # it learned
    assert (counted.count == 0) if masked else (counted.count > 0), counted.count
    res = evaluate_policy(table, "hard", FlatPolicy(lambda x: net(torch.as_tensor(x)).detach().numpy(), max_range=A,
                                                    width=counted.single_observation_space))
    assert np.isfinite(res.ret).all()


def test_the_importable_id_makes_the_env_in_a_fresh_process(table, tmp_path):
    import subprocess
    import sys

    path = table.save(tmp_path / "table")
    code = (f"import gymnasium as gym; env = gym.make({IMPORTABLE_ID!r}, table={str(path)!r}, observation='flat'); "
            "print(env.reset(seed=0)[0].shape)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == f"({8 + 4 + 1 + K},)"


def _rllib():
    try:
        from ray.rllib.algorithms.ppo import PPOConfig  # noqa: F401
    except ImportError as e:  # ray without the rllib extra's dependencies (dm_tree, lz4, ...)
        pytest.skip(f"RLlib is not installed ({e}): pip install -e '.[rllib]'")


def _allowed_everywhere(episodes) -> int:
    """The actions of RLlib's sampled episodes that the observation's action mask forbade."""
    bad = 0
    for ep in episodes:
        obs, actions = ep.get_observations(), ep.get_actions()
        masks = obs["action_mask"] if isinstance(obs, dict) else np.stack([o["action_mask"] for o in obs])
        bad += int(sum(masks[i][int(a)] == 0 for i, a in enumerate(actions)))
    return bad


def _train_in_a_remote_env_runner(config, table, tmp_path, module_class, samples: int):
    """``config`` on the table's masked flat env with ``module_class``, trained 2 iterations
    with one remote env runner, then ``samples`` steps sampled there: none may take an action
    the mask forbade. Returns the trained module."""
    import ray
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    path = table.save(tmp_path / "table")
    config = (config
              .environment(IMPORTABLE_ID, env_config={"table": str(path), "actions": "flat", "observation": "masked"})
              .env_runners(num_env_runners=1, num_envs_per_env_runner=2)
              .rl_module(rl_module_spec=RLModuleSpec(module_class=module_class,
                                                     model_config={"fcnet_hiddens": [32], "head_fcnet_hiddens": [32]}))
              .debugging(seed=0))
    ray.init(num_cpus=2, include_dashboard=False, ignore_reinit_error=True, log_to_driver=False)
    try:
        algo = config.build_algo()
        for _ in range(2):
            result = algo.train()
        assert result["env_runners"]["num_episodes"] > 0
        episodes = [ep for eps in algo.env_runner_group.foreach_env_runner(
            lambda r: r.sample(num_timesteps=samples), local_env_runner=False) for ep in eps]
        assert episodes and _allowed_everywhere(episodes) == 0
        module = algo.get_module()
        algo.stop()
    finally:
        ray.shutdown()
    return module


def _masked_batch(x):
    """FlatPolicy's observations as the masked form's batch: the vector and its mask (its last K)."""
    return {"obs": {"observations": torch.as_tensor(x), "action_mask": torch.as_tensor(x[:, -K:])}}


def test_rllibs_ppo_trains_with_the_action_mask_in_a_remote_env_runner(table, tmp_path):
    _rllib()
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.examples.rl_modules.classes.action_masking_rlm import ActionMaskingTorchRLModule

    config = PPOConfig().training(train_batch_size_per_learner=128, minibatch_size=64, num_epochs=1, gamma=0.9)
    module = _train_in_a_remote_env_runner(config, table, tmp_path, ActionMaskingTorchRLModule, samples=200)

    def scores(x):  # the trained module's masked logits over FlatPolicy's observation
        with torch.no_grad():
            return module.forward_inference(_masked_batch(x))["action_dist_inputs"].numpy()

    res = evaluate_policy(table, "hard", FlatPolicy(scores, max_range=A, masked=False))
    assert np.isfinite(res.ret).all()


def test_rllibs_dqn_with_the_librarys_masked_module_never_takes_a_forbidden_action(table, tmp_path):
    _rllib()
    from ray.rllib.algorithms.dqn import DQNConfig

    from uevavd.env.rllib import MaskedDQNTorchRLModule

    config = (DQNConfig()
              .training(train_batch_size_per_learner=32, num_steps_sampled_before_learning_starts=32, gamma=0.9,
                        epsilon=[(0, 1.0), (10_000, 0.05)])  # mostly random actions: they must keep to the mask
              .reporting(min_sample_timesteps_per_iteration=100))
    module = _train_in_a_remote_env_runner(config, table, tmp_path, MaskedDQNTorchRLModule, samples=300)

    def q_values(x):
        with torch.no_grad():
            return module.compute_q_values(_masked_batch(x))["qf_preds"].numpy()

    res = evaluate_policy(table, "hard", FlatPolicy(q_values, max_range=A, masked=False))
    assert np.isfinite(res.ret).all()

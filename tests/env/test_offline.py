"""The flat view for offline-RL libraries: an exported dataset as Box observations, Discrete
actions and masks, and a flat policy scored by the evaluation. d3rlpy's DiscreteBC trains on
it where d3rlpy is installed (its own extra: it pins gymnasium 1.0)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

minari = pytest.importorskip("minari", reason="the clients extra: pip install -e '.[clients]'")


@pytest.fixture(scope="module")
def oracle_dataset(tmp_path_factory):
    """The oracle's 200 episodes on the env tests' table, exported once for the module (the
    tests only read it)."""
    from uevavd.paths import tables_dir
    from uevavd.policy.minari_export import export_minari

    from .conftest import make_table

    table = make_table(6, splits=("train", "train", "train", "simple", "hard", "hard"))
    tmp = tmp_path_factory.mktemp("offline")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("UEVAVD_CACHE", str(tmp / "cache"))
        mp.setenv("MINARI_DATASETS_PATH", str(tmp / "datasets"))
        folder = table.save(tables_dir() / table.key)
        yield export_minari(folder, "train", "oracle", "uevavd/flat-oracle-v0", episodes=200, progress=False)


def test_the_flat_view_holds_every_decision_its_action_and_mask(table, oracle_dataset):
    from uevavd.env.offline import flat_dataset

    flat = flat_dataset(oracle_dataset)
    episodes = list(oracle_dataset.iterate_episodes())
    n = sum(len(e.rewards) for e in episodes)
    a = table.feature_dim + 4 + 1
    assert flat.observations.shape == (n, a + flat.n_actions) and flat.observations.dtype == np.float32
    assert flat.actions.shape == (n,) and flat.max_range == 4 and flat.n_actions == 28
    first = episodes[0]
    np.testing.assert_array_equal(flat.observations[0, :table.feature_dim], first.observations["features"][0])
    assert flat.observations[0, table.feature_dim + 4] == first.observations["t"][0]
    assert flat.actions[0] == first.actions[0][0] * 4 + first.actions[0][1]
    np.testing.assert_array_equal(flat.masks[0], first.observations["action_mask"][0].reshape(-1) > 0)
    assert flat.terminals.sum() == len(episodes) and not flat.timeouts.any()
    assert np.isclose(flat.rewards.sum(), sum(e.rewards.sum() for e in episodes))


def test_a_flat_policy_is_scored_by_the_evaluation_as_its_actions_say(table, oracle_dataset):
    """A flat policy that always stops is the passive baseline, number for number; one fitted
    on the oracle's decisions (a linear classifier in torch) is scored like any policy."""
    from uevavd.env import EnvConfig, PassivePolicy, evaluate_policy
    from uevavd.env.offline import FlatPolicy, flat_dataset

    stop = FlatPolicy(lambda x: np.full(len(x), 6 * 4), max_range=4)
    np.testing.assert_equal(evaluate_policy(table, "hard", stop, EnvConfig()).summary(),  # NaN where no start hides
                            evaluate_policy(table, "hard", PassivePolicy(), EnvConfig()).summary())
    flat = flat_dataset(oracle_dataset)
    x, y = torch.as_tensor(flat.observations), torch.as_tensor(flat.actions)
    torch.manual_seed(0)
    clf = torch.nn.Linear(x.shape[1], flat.n_actions)
    opt = torch.optim.Adam(clf.parameters(), 1e-2)
    for _ in range(300):
        loss = torch.nn.functional.cross_entropy(clf(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    agree = float((clf(x).argmax(1) == y).float().mean())
    assert agree > 0.6
    policy = FlatPolicy(lambda obs: clf(torch.as_tensor(obs)).argmax(1).numpy(), max_range=flat.max_range)
    summary = evaluate_policy(table, "hard", policy, EnvConfig()).summary()
    assert summary["episodes"] == 2 * 605 and np.isfinite(summary["mean_return"])
    with pytest.raises(ValueError, match=r"expected \(\d+,\) indices of Discrete\(28\)"):
        evaluate_policy(table, "hard", FlatPolicy(lambda x: np.full(len(x), 99), max_range=4), EnvConfig())


def test_d3rlpy_discrete_bc_trains_on_the_flat_view_and_is_evaluated(table, oracle_dataset, tmp_path, monkeypatch):
    """d3rlpy's DiscreteBC on the flat view, then scored by uevavd's evaluation beside the
    oracle it cloned and the random policy."""
    d3rlpy = pytest.importorskip("d3rlpy", reason="the d3rlpy extra: pip install -e '.[d3rlpy]' (it pins gymnasium "
                                                  "1.0, which TorchRL refuses, so the test extra leaves it out)")
    from uevavd.env import EnvConfig, OraclePolicy, RandomPolicy, evaluate_policy
    from uevavd.env.offline import flat_dataset

    flat = flat_dataset(oracle_dataset)
    data = d3rlpy.dataset.MDPDataset(flat.observations, flat.actions[:, None], flat.rewards, flat.terminals,
                                     timeouts=flat.timeouts, action_space=d3rlpy.constants.ActionSpace.DISCRETE,
                                     action_size=flat.n_actions)
    d3rlpy.seed(0)
    bc = d3rlpy.algos.DiscreteBCConfig(batch_size=64, learning_rate=3e-3).create(device="cpu:0")
    monkeypatch.chdir(tmp_path)  # d3rlpy writes its logs under the working folder
    bc.fit(data, n_steps=1500, n_steps_per_epoch=1500, show_progress=False, save_interval=10**9,
           logger_adapter=d3rlpy.logging.NoopAdapterFactory())
    agree = float((bc.predict(flat.observations) == flat.actions).mean())
    assert agree > 0.6, agree
    cfg = EnvConfig()
    cloned = evaluate_policy(table, "train", flat.policy(bc.predict), cfg).summary()  # as the docs score it
    random = evaluate_policy(table, "train", RandomPolicy(0), cfg).summary()
    oracle = evaluate_policy(table, "train", OraclePolicy(table, cfg), cfg).summary()
    assert random["mean_return"] < cloned["mean_return"] <= oracle["mean_return"] + 1e-9, (cloned, random, oracle)


def test_the_flat_view_refuses_what_the_env_refuses(table, oracle_dataset):
    """FlatPolicy(max_range=3) on a table of 4 ranges evaluated every index split by 3; a predict
    returning 3.7 was truncated to 3; max_range=0 was taken; another dataset was an AttributeError."""
    from uevavd.env import EnvConfig, evaluate_policy
    from uevavd.env.offline import FlatPolicy, flat_dataset

    with pytest.raises(ValueError, match=r"FlatPolicy\(max_range=3\) on an env whose actions have 4 ranges"):
        evaluate_policy(table, "hard", FlatPolicy(lambda x: np.full(len(x), 18), max_range=3), EnvConfig())
    with pytest.raises(ValueError, match=r"returned \[3.7, .*integer indices"):
        evaluate_policy(table, "hard", FlatPolicy(lambda x: np.full(len(x), 3.7), max_range=4), EnvConfig())
    stop = FlatPolicy(lambda x: np.full(len(x), 24.0), max_range=4)  # a float equal to an integer: the env's rule
    assert evaluate_policy(table, "hard", stop, EnvConfig()).summary()["stop_rate"] == 1.0
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="an integer >= 1"):
            FlatPolicy(lambda x: x, max_range=bad)

    class Episode:  # a dataset of another env: a flat Box observation
        observations, rewards = np.zeros((3, 5)), np.zeros(2)

    with pytest.raises(ValueError, match=r"is not one `uevavd export-minari` wrote: its observations hold ndarray"):
        flat_dataset([Episode()])
    assert flat_dataset(oracle_dataset).max_range == 4


def test_a_flat_policy_keeps_to_the_action_mask_by_default(table):
    """The mask is recorded in every export and was never used offline: BC clones took clamped
    moves in 164 of 3,873 hard decisions."""
    from uevavd.data.grid import coords_to_view, transitions
    from uevavd.env import BatchedAODEnv, EnvConfig
    from uevavd.env.offline import FlatPolicy

    right_4 = 3 * 4 + 3  # right (+x), 4 steps
    views = [coords_to_view(50, 0, 80), coords_to_view(20, 0, 80), coords_to_view(-50, 0, 80)]
    obs = BatchedAODEnv(table, "train", 3, EnvConfig(), seed=0).reset(views=views)
    a_type, a_range = FlatPolicy(lambda x: np.full(len(x), right_4), max_range=4).act(obs)
    assert a_type.tolist() == [6, 3, 3] and a_range.tolist() == [0, 2, 3]  # stop at the edge; 3 steps; 4 steps
    a_type, a_range = FlatPolicy(lambda x: np.full(len(x), right_4), max_range=4, masked=False).act(obs)
    assert a_type.tolist() == [3, 3, 3] and a_range.tolist() == [3, 3, 3]  # as asked, clamped at the edge
    scores = np.zeros((3, 28))
    scores[:, right_4], scores[:, 2 * 4 + 0] = 2.0, 1.0  # right 4 first, then left 1
    a_type, a_range = FlatPolicy(lambda x: scores, max_range=4).act(obs)
    assert a_type.tolist() == [2, 2, 3] and a_range.tolist() == [0, 0, 3]  # the best allowed
    tr = transitions(4)
    assert not any(tr.clamped[v, t, r] for v, t, r in zip(views, a_type.tolist(), a_range.tolist(), strict=True))


def test_several_datasets_flatten_in_one_call(oracle_dataset):
    from uevavd.env.offline import flat_dataset

    one, two = flat_dataset(oracle_dataset), flat_dataset(oracle_dataset, oracle_dataset)
    assert len(two.actions) == 2 * len(one.actions) and two.max_range == one.max_range
    np.testing.assert_array_equal(two.observations[len(one.actions):], one.observations)


def test_the_flat_view_read_from_the_file_is_minaris_episodes_in_any_number_of_processes(oracle_dataset):
    """flat_dataset read every episode through Minari's reader, which decodes each one's infos
    and spaces: 15 s for 2,000 episodes, slower than the 1,000-step fit it fed. It now reads the
    HDF5 file itself (benchmarks/bench_offline.py); the arrays are Minari's, in its order, for
    a filtered dataset too, however many processes read them."""
    from uevavd.env.offline import flat_dataset

    fields = ("observations", "actions", "rewards", "terminals", "timeouts", "masks")
    some = oracle_dataset.filter_episodes(lambda ep: ep.id % 3 != 1)
    for data in (oracle_dataset, some):
        episodes = list(data.iterate_episodes())
        minaris = flat_dataset(episodes)
        for flat in (flat_dataset(data), flat_dataset(data, workers=2)):
            for field in fields:
                np.testing.assert_array_equal(getattr(flat, field), getattr(minaris, field), err_msg=field)
        assert len(minaris.actions) == sum(len(e.rewards) for e in episodes)
    assert len(flat_dataset(some).actions) < len(flat_dataset(oracle_dataset).actions)
    from types import SimpleNamespace

    posed = [SimpleNamespace(observations={**e.observations, "pose": np.zeros((len(e.rewards) + 1, 3), np.float32)},
                             actions=e.actions, rewards=e.rewards, terminations=e.terminations,
                             truncations=e.truncations) for e in oracle_dataset.iterate_episodes([0, 1, 2])]
    assert flat_dataset(posed).observations.shape[1] == flat_dataset(oracle_dataset).observations.shape[1] + 3
    with pytest.raises(ValueError, match=r"holds the observation parts .*'pose'.* one env config together"):
        flat_dataset(oracle_dataset, posed)
    narrow = [SimpleNamespace(**{**vars(e), "observations": {**e.observations,
                                                              "action_mask": e.observations["action_mask"][..., :3]}})
              for e in posed]
    with pytest.raises(ValueError, match=r"dataset list has 3 ranges where dataset .* has 4: flatten datasets of one "
                                         "action space together"):
        flat_dataset(oracle_dataset, narrow)


@pytest.fixture
def damaged(oracle_dataset, tmp_path, monkeypatch):
    """A copy of the exported dataset, loaded from its own folder after ``edit(h5py.File)``."""
    import shutil

    import h5py

    source = Path(oracle_dataset.storage.data_path).parents[2]  # <MINARI_DATASETS_PATH>/uevavd/<name>-v0/data
    copy = tmp_path / "datasets"
    shutil.copytree(source, copy)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(copy))
    dataset_id = oracle_dataset.spec.dataset_id

    def load(edit):
        path = next(copy.rglob("main_data.hdf5"))
        with h5py.File(path, "r+") as f:
            edit(f)
        return minari.load_dataset(dataset_id), path

    return load


def _replace(group, key, value):
    del group[key]
    group[key] = value


@pytest.mark.parametrize("edit, message", [
    (lambda f: _replace(f["episode_3"], "actions", f["episode_3/actions"][()] - 0.3),
     r"episode_3, key actions: float64 .* expected integral \(type, range\) pairs"),
    (lambda f: f["episode_4/actions"].__setitem__((0, 0), 9), r"episode_4, key actions: step 0 is \[9, .*type in 0..6"),
    (lambda f: f["episode_4/actions"].__setitem__((0, 1), -3), r"episode_4, key actions: step 0 is .*range in 0..3"),
    (lambda f: _replace(f["episode_5"], "actions", f["episode_5/actions"][()][:-1]),
     r"episode_5, key actions: \d+ rows where rewards has \d+"),
    (lambda f: _replace(f["episode_6/observations"], "box", f["episode_6/observations/box"][()].astype(np.int8)),
     r"episode_6, key observations/box: int8 \(4,\) per row; the dataset's observation space records float32"),
    (lambda f: f["episode_7/rewards"].__setitem__(0, np.nan), r"episode_7, key rewards: holds NaN"),
    (lambda f: f.__delitem__("episode_8"), r"episode_8: no such episode group"),
])
def test_a_damaged_minari_file_is_refused_naming_the_file_the_episode_and_the_key(damaged, edit, message):
    """Each of these passed through, or was another action's index, or a raw h5py error."""
    from uevavd.data.episodes import EpisodeError
    from uevavd.env.offline import flat_dataset

    dataset, path = damaged(edit)
    for workers in (1, 2):  # in this process and from worker processes alike
        with pytest.raises(EpisodeError, match=message) as info:
            flat_dataset(dataset, workers=workers)
        assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_truncated_file_bad_workers_and_foreign_episodes_are_one_line(damaged, oracle_dataset):
    from uevavd.data.episodes import EpisodeError
    from uevavd.env.offline import flat_dataset

    dataset, path = damaged(lambda f: None)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(EpisodeError, match=r"main_data.hdf5: cannot be opened as HDF5"):
        flat_dataset(dataset)
    for bad in ("2", 2.5, 0, -1, True):
        with pytest.raises(ValueError, match=r"workers=.*expected an integer >= 1"):
            flat_dataset(oracle_dataset, workers=bad)
    with pytest.raises(EpisodeError, match=r"episode 0: a dict, not an episode"):
        flat_dataset([{"a": 1}])

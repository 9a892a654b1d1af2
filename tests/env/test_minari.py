"""Minari datasets of the oracles' episodes: written by `uevavd export-minari`, reloaded on
another path with `minari.load_dataset`, and `recover_environment` gives a working env."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

minari = pytest.importorskip("minari", reason="the clients extra: pip install -e '.[clients]'")


def test_oracle_datasets_are_portable_and_reload_on_another_path(table, tmp_path, monkeypatch, capsys):
    from uevavd.cli import main
    from uevavd.env.aod_env import AODEnv

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    from uevavd.paths import tables_dir

    folder = table.save(tables_dir() / table.key)
    for policy in ("oracle", "visibility_oracle", "passive"):
        assert main(["export-minari", str(folder), "--split", "train", "--policy", policy, "--episodes", "12",
                     "--id", f"uevavd/test-{policy.replace('_', '')}-v0", "--out", str(tmp_path / "made")]) == 0
    assert "wrote uevavd/test-oracle-v0: 12 episodes" in capsys.readouterr().out
    shutil.copytree(tmp_path / "made", tmp_path / "moved")
    shutil.rmtree(tmp_path / "made")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "moved"))
    ds = minari.load_dataset("uevavd/test-oracle-v0")
    assert ds.total_episodes == 12
    assert str(tmp_path) not in str(ds.spec.env_spec.kwargs)  # names the table by key: portable
    assert f"recover_environment() loads table {table.key}" in ds.storage.metadata["description"]  # and how to get it
    env = AODEnv(table, "train")
    for ep in ds.iterate_episodes():
        n = len(ep.rewards)
        assert ep.actions.shape == (n, 2) and ep.observations["features"].shape == (n + 1, table.feature_dim)
        assert ep.terminations[-1] and not ep.terminations[:-1].any() and not ep.truncations.any()
        # the discounted sum of the recorded rewards is the env's return at the end
        assert np.isclose(sum(0.9**t * r for t, r in enumerate(ep.rewards)), ep.infos["return"][-1])
        assert set(ep.infos) >= {"recognized", "correct", "stopped", "return", "visible"}
        # replaying the recorded actions in the env gives the recorded rewards
        env.reset(options={"scene": int(ep.infos["scene"][0]), "view": int(ep.infos["view"][0])})
        assert [env.step(a)[1] for a in ep.actions] == list(ep.rewards)
    oracle = np.mean([ep.infos["return"][-1] for ep in ds.iterate_episodes()])
    passive = np.mean([ep.infos["return"][-1] for ep in minari.load_dataset("uevavd/test-passive-v0").iterate_episodes()])
    assert oracle > passive  # same starts (same seed): the class-knowing oracle does better
    recovered = ds.recover_environment()  # from the key, through $UEVAVD_CACHE/tables
    obs, _ = recovered.reset(seed=0)
    assert recovered.unwrapped.table.key == table.key and obs["features"].shape == (table.feature_dim,)
    assert minari.load_dataset("uevavd/test-visibilityoracle-v0").total_episodes == 12


def test_export_minari_refuses_an_unknown_policy_in_one_line(table, tmp_path, monkeypatch, capsys):
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    folder = table.save(tmp_path / "t")
    assert main(["export-minari", str(folder), "--policy", "orcale", "--id", "uevavd/x-v0",
                 "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--policy 'orcale': expected one of" in err, err


def test_a_trained_run_exports_like_a_baseline(table, tmp_path, monkeypatch):
    """`--policy RUN_FOLDER`: a trained run's greedy policy, recorded step by step."""
    from uevavd.config import load_method
    from uevavd.policy.minari_export import export_minari
    from uevavd.policy.trainer import train

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    from uevavd.paths import tables_dir

    folder = table.save(tables_dir() / table.key)
    spec = load_method("map", overrides={"train.episodes": 120, "train.learning_starts": 40, "train.n_envs": 16,
                                         "train.batch_size": 16, "train.epoch_episodes": 120,
                                         "train.eval_contexts": 1, "state.input_dim": 64, "state.state_dim": 32,
                                         "head.hidden": 32})
    run = tmp_path / "run"
    train(spec.with_overrides({"env.thre": 0.5, "env.C": 0.05}), table, out=run, device="cpu", progress=False)
    trained = export_minari(folder, "train", str(run), "uevavd/trained-v0", episodes=8, progress=False)
    assert trained.total_episodes == 8 and "trained run" in trained.storage.metadata["algorithm_name"]
    # recorded under the run's own reward (thre 0.5, C 0.05), not the default's; --set changes it
    env = trained.recover_environment()
    assert (env.unwrapped.config.thre, env.unwrapped.config.C) == (0.5, 0.05)
    from uevavd.cli import main

    assert main(["export-minari", str(folder), "--split", "train", "--policy", str(run), "--id", "uevavd/c0-v0",
                 "--episodes", "4", "--set", "env.C=0"]) == 0
    assert minari.load_dataset("uevavd/c0-v0").recover_environment().unwrapped.config.C == 0.0
    assert main(["export-minari", str(folder), "--policy", str(run), "--id", "uevavd/x-v0", "--episodes", "4",
                 "--set", "train.lr=1"]) == 2


def test_minari_data_collector_records_infos_with_a_portable_spec(table, tmp_path, monkeypatch):
    """`minari.DataCollector(env, record_infos=True)` failed (the info keys changed from step to
    step); it records now, and with the table named by key the dataset's spec holds no path."""
    pytest.importorskip("jax", reason="minari's DataCollector needs minari[create] (jax)")
    import gymnasium as gym

    import uevavd.env  # noqa: F401 - registers the env id

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    from uevavd.paths import tables_dir

    table.save(tables_dir() / table.key)
    env = minari.DataCollector(gym.make("uevavd/AOD-v0", table=table.key, split="train"), record_infos=True)
    env.reset(seed=0)
    for _ in range(40):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    ds = env.create_dataset("uevavd/collected-v0", algorithm_name="random")
    assert ds.total_steps >= 40 and "return" in next(ds.iterate_episodes()).infos
    assert ds.spec.env_spec.kwargs["table"] == table.key


def test_behaviour_cloning_on_an_oracle_dataset_is_evaluated_by_uevavd_evaluate(table, tmp_path, monkeypatch, capsys):
    """docs/environment.md's example: the class-knowing oracle's episodes exported, a method's
    network cloned on them with cross-entropy on both branches, written with save_network and
    evaluated by `uevavd evaluate FILE --table` beside the baselines; a network of another
    method is refused when saved, naming the tensors."""
    import json

    import torch

    from uevavd.api import policy_network, save_network
    from uevavd.cli import main
    from uevavd.config import load_method

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    from uevavd.paths import tables_dir

    folder = table.save(tables_dir() / table.key)
    assert main(["export-minari", str(folder), "--split", "train", "--policy", "oracle", "--episodes", "60",
                 "--id", "uevavd/bc-oracle-v0"]) == 0
    small = {"state.input_dim": 64, "state.state_dim": 32, "head.hidden": 32}
    method = load_method("map", overrides=small)
    episodes = list(minari.load_dataset("uevavd/bc-oracle-v0").iterate_episodes())
    x = torch.cat([torch.as_tensor(e.observations["features"][:-1]) for e in episodes]).float()
    b = torch.cat([torch.as_tensor(e.observations["box"][:-1]) for e in episodes])
    a = torch.cat([torch.as_tensor(e.actions) for e in episodes])
    torch.manual_seed(0)
    net = policy_network(method, folder)
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    losses = []
    for _ in range(150):
        q_type, q_range = (q[:, 0] for q in net(x[:, None], b[:, None]))
        loss = torch.nn.functional.cross_entropy(q_type, a[:, 0]) + torch.nn.functional.cross_entropy(q_range, a[:, 1])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss))
    assert losses[-1] < 0.5 * losses[0]
    path = save_network(net, tmp_path / "bc.safetensors", method=method, table=folder)
    capsys.readouterr()
    assert main(["evaluate", str(path), "--table", str(folder), "--split", "hard"]) == 0
    out = capsys.readouterr().out
    assert "bc " in out and "passive" in out and "oracle" in out
    rows = json.loads((tmp_path / "bc.eval_hard.json").read_text())
    assert {"bc", "passive", "random", "oracle"} <= set(rows)
    gru = policy_network(load_method("ibe_map", overrides=small), folder)
    with pytest.raises(ValueError, match="bc2.safetensors"):
        save_network(gru, tmp_path / "bc2.safetensors", method=method, table=folder)
    assert not (tmp_path / "bc2.safetensors").exists()
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["evaluate", str(path), "--split", "hard"]) == 2
    assert "pass --table" in capsys.readouterr().err


def test_the_random_policys_stream_runs_on_across_exported_episodes(table):
    """collect_episodes resets the policy per episode; the random policy reseeded on each reset, so
    2,000 episodes held a few dozen distinct action sequences and stopped far less often than the
    same policy does in an evaluation."""
    from uevavd.env import EnvConfig, RandomPolicy, evaluate_policy
    from uevavd.policy.minari_export import collect_episodes

    buffers, _ = collect_episodes(table, "train", RandomPolicy(seed=0), episodes=300, progress=False)
    sequences = {tuple(map(tuple, b.actions.tolist())) for b in buffers}
    assert len(sequences) > 250
    first = np.array([b.actions[0][0] for b in buffers])
    stop_share = float(np.mean(first == 6))
    want = evaluate_policy(table, "train", RandomPolicy(seed=0), EnvConfig())
    first_eval = (want.trajectories[:, 1] < 0).mean()  # the first decision was a stop
    assert abs(stop_share - first_eval) < 0.06


def test_a_table_outside_the_cache_is_refused_before_collecting_and_nothing_is_left(table, tmp_path, monkeypatch,
                                                                                   capsys):
    """It failed after collecting every episode with a wrong "not an observation table" message,
    leaving a dataset folder that blocked a rerun with the same id; a write that fails midway
    leaves nothing either, and recover_environment's missing table says how to get it back."""
    from uevavd.cli import main
    from uevavd.paths import tables_dir
    from uevavd.policy import minari_export

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    outside = table.save(tmp_path / "elsewhere" / "t")
    collected = []
    monkeypatch.setattr(minari_export, "collect_episodes",
                        lambda *a, **k: collected.append(1) or (_ for _ in ()).throw(AssertionError("collected")))
    assert main(["export-minari", str(outside), "--policy", "passive", "--id", "uevavd/out-v0", "--episodes", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"table {table.key} is not in the table cache" in err and not collected
    assert not (tmp_path / "datasets" / "uevavd").exists()
    monkeypatch.undo()
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    cached = table.save(tables_dir() / table.key)

    def broken(**kwargs):  # the folder made, then the write fails
        from minari.storage import get_dataset_path

        (get_dataset_path(kwargs["dataset_id"]) / "data").mkdir(parents=True)
        raise OSError("disk full")

    monkeypatch.setattr(minari, "create_dataset_from_buffers", broken)
    with pytest.raises(OSError, match="disk full"):
        minari_export.export_minari(cached, "hard", "passive", "uevavd/half-v0", episodes=3, progress=False)
    assert not (tmp_path / "datasets" / "uevavd" / "half-v0").exists()
    assert not [p for p in (tmp_path / "datasets" / "uevavd").iterdir() if p.name != ".half-v0.lock"]
    monkeypatch.undo()
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    from uevavd.table import TableError, load_table

    with pytest.raises(TableError, match="neither a folder nor in the table cache .*rebuild it with `uevavd prepare`"):
        load_table("0123456789abcdef01234567")


@pytest.mark.parametrize("dataset_id", ["uevavd/noversion", "uevavd/bad-vX", "", "../../outside-v0", "uevavd/../x-v0",
                                        "uevavd/a b-v0"])
def test_a_dataset_id_that_is_not_one_is_refused_before_anything_is_written(table, tmp_path, monkeypatch, capsys,
                                                                            dataset_id):
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    folder = table.save(tmp_path / "t")
    assert main(["export-minari", str(folder), "--policy", "passive", "--id", dataset_id, "--out",
                 str(tmp_path / "ds" / "inner")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"--id {dataset_id!r}: expected a dataset id namespace/name-vN" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t"]  # no folder made, inside or outside


KILLED_EXPORT = """
import os, signal, sys
import minari
from uevavd.cli import main
from uevavd.policy import minari_export

def die(*a, **k):
    os.kill(os.getpid(), signal.SIGKILL)

point = sys.argv[1]
if point == "collecting":
    minari_export.collect_episodes = die
elif point == "writing":  # Minari has made the dataset's folder and half its files
    def half(**kw):
        from minari.storage import get_dataset_path
        (get_dataset_path(kw["dataset_id"]) / "data").mkdir(parents=True)
        (get_dataset_path(kw["dataset_id"]) / "data" / "metadata.json").write_text("{")
        die()
    minari.create_dataset_from_buffers = half
else:  # written whole, killed before it is put in place
    real = minari.create_dataset_from_buffers
    def then_die(**kw):
        out = real(**kw)
        os.replace = die
        return out
    minari.create_dataset_from_buffers = then_die
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("point", ["collecting", "writing", "renaming"])
def test_an_export_killed_at_any_point_leaves_no_dataset_and_the_rerun_writes_it(table, tmp_path, point,
                                                                                 monkeypatch, capsys):
    """kill -9 while export-minari wrote left a dataset Minari loaded as 0 episodes without an
    error, and the rerun was refused as "already exists". (The rerun runs in this process: what
    it finds is on disk.)"""
    import os
    import subprocess
    import sys

    from uevavd.cli import main
    from uevavd.paths import tables_dir

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "ds"))
    folder = table.save(tables_dir() / table.key)
    args = ["export-minari", str(folder), "--policy", "passive", "--episodes", "3", "--id", "uevavd/kill-v0"]
    p = subprocess.run([sys.executable, "-c", KILLED_EXPORT, point, *args], env=dict(os.environ),
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == -9, p.stderr
    assert not (tmp_path / "ds" / "uevavd" / "kill-v0").exists()
    assert main(args) == 0
    assert "wrote uevavd/kill-v0: 3 episodes" in capsys.readouterr().out
    assert sorted(f.name for f in (tmp_path / "ds" / "uevavd").iterdir()) == [".kill-v0.lock", "kill-v0"]


def test_a_dataset_past_the_free_space_or_the_file_size_limit_is_one_line_before_hdf5_writes(table, tmp_path,
                                                                                             monkeypatch, capsys):
    """A full disk, or `ulimit -f`, ended in a segmentation fault (exit 139) after HDF5 tracebacks."""
    import os
    import resource
    import subprocess
    import sys
    from collections import namedtuple

    from uevavd.cli import main
    from uevavd.paths import tables_dir
    from uevavd.policy import minari_export

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    cached = table.save(tables_dir() / table.key)
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(minari_export.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 10**5, 10**5))
    assert main(["export-minari", str(cached), "--policy", "passive", "--id", "uevavd/full-v0", "--episodes", "50"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # below the finished progress bar, on a line of its own
    assert err.startswith("uevavd export-minari: error: [Errno 28]") and "the disk has 100,000 bytes free" in err
    assert not (tmp_path / "datasets" / "uevavd" / "full-v0").exists()
    monkeypatch.undo()
    # a real file-size limit, in a process of its own
    env = {**os.environ, "UEVAVD_CACHE": str(tmp_path / "cache"), "MINARI_DATASETS_PATH": str(tmp_path / "datasets")}
    env.pop("UEVAVD_DEBUG", None)
    limit = 20_000  # bytes: the table's files are read, not written
    run = subprocess.run([sys.executable, "-m", "uevavd.cli", "export-minari", str(cached), "--policy", "passive",
                          "--id", "uevavd/limit-v0", "--episodes", "50"], env=env, capture_output=True, text=True,
                         preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)), timeout=300)
    lines = [line for line in run.stderr.splitlines() if "error" in line]
    assert run.returncode == 2, run.stderr[-2000:]
    assert len(lines) == 1 and "past this process's file-size limit of 20,000 bytes" in lines[0]
    assert not (tmp_path / "datasets" / "uevavd" / "limit-v0").exists()

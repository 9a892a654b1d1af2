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

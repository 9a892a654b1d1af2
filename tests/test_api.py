"""The README's Python API script, run exactly as written on the tiny test world (its
dataset root and preset name swapped for the tiny ones)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from uevavd.testing.worlds import tiny_preset

TINY_PRESET = tiny_preset(overrides="""\
"state.input_dim" = 40
"state.state_dim" = 32
"head.hidden" = 32
"train.threads" = 1
""")


def _readme_script() -> str:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    section = readme.split("## The Python API", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_readme_script_runs_and_its_policy_file_reloads(tmp_path, monkeypatch, capsys, ablation_world):
    import uevavd

    world = ablation_world
    (tmp_path / "tiny.toml").write_text(TINY_PRESET)
    script = _readme_script()
    assert 'root = "data/quick"' in script and 'uevavd.load_preset("quick")' in script
    script = script.replace('"data/quick"', repr(str(world))).replace('load_preset("quick")',
                                                                     f'load_preset({str(tmp_path / "tiny.toml")!r})')
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(script, "README.md", "exec"), namespace)  # noqa: S102 - the README's own example
    out = capsys.readouterr().out
    for name in ("ibe_map", "random", "passive", "visibility_oracle", "oracle"):
        assert name in out
    run = namespace["run"]
    assert run.finished and run.env_config.thre == 0.2
    frame = run.evaluate("hard")
    assert list(frame.index) == ["ibe_map", "random", "passive", "box_gate", "pose_seek", "departure_ceiling",
                                 "departure_ceiling2", "visibility_oracle", "oracle"]
    assert frame.loc["oracle", "mean_return"] >= frame["mean_return"].max() - 1e-9
    policy, cfg = uevavd.load_policy_file(tmp_path / "ibe_map.safetensors", table=namespace["table"])
    from uevavd.env.evaluate import evaluate_policy

    again = evaluate_policy(namespace["table"], "hard", policy, cfg).summary()
    assert again["mean_return"] == pytest.approx(frame.loc["ibe_map", "mean_return"], abs=1e-9)
    assert (tmp_path / "ibe_map.safetensors").stat().st_size < 2_000_000  # no replay buffer
    other = uevavd.build_table(world, "map", classifier=namespace["recognizer"],
                               overrides={k: v for k, v in uevavd.load_preset(tmp_path / "tiny.toml")["overrides"].items()
                                          if k.startswith("perception.")})
    with pytest.raises(ValueError, match="does not fit .*decompose: policy True, table False"):
        uevavd.load_policy_file(tmp_path / "ibe_map.safetensors", table=other)
    # every figure finite, but the gated return: the learned policy's alone (the baselines are not gated)
    assert np.isfinite(frame.drop(columns="gated_return").to_numpy()).all()
    assert np.isfinite(frame.loc["ibe_map", "gated_return"]) and frame["gated_return"].drop("ibe_map").isna().all()


def test_a_misspelled_recipe_setting_is_named_before_any_work(tmp_path):
    import uevavd

    with pytest.raises(ValueError, match="no key 'epoch'; did you mean 'epochs'"):
        uevavd.train_classifier(tmp_path / "no-data", epoch=3)
    # another thread count trains other weights: never under the cache name `ablate` reuses
    with pytest.raises(ValueError, match="threads=4: the cache holds recognizers trained on 2 threads"):
        uevavd.train_classifier(tmp_path / "no-data", threads=4)


def test_a_run_trained_on_a_table_in_memory_evaluates(tmp_path):
    """`uevavd.train(method, table_in_memory)` then `run.evaluate()` was a TypeError (the run
    kept no table path); the Run keeps the table, and a Run loaded later says what to do."""
    import pytest

    import uevavd
    from uevavd.testing.policy import toy_table

    table = toy_table(n_train=4, n_hard=2, feature_dim=16)
    run = uevavd.train("map", table, out=tmp_path / "run", episodes=120, device="cpu", progress=False,
                       overrides={"train.learning_starts": 40, "train.epoch_episodes": 120, "train.eval_contexts": 1,
                                  "train.n_envs": 16, "train.batch_size": 16})
    df = run.evaluate("hard")
    assert {"map", "passive", "oracle"} <= set(df.index if "method" not in df else df["method"])
    with pytest.raises(ValueError, match="trained on a table in memory"):
        uevavd.load_run(tmp_path / "run").evaluate("hard")

import json
import shutil

import pytest

from uevavd.cli import main

from .conftest import small


def test_train_then_evaluate_from_the_command_line(table, tmp_path, capsys):
    path = table.save(tmp_path / "table")
    sets = [a for k, v in small("map").items() for a in ("--set", f"{k}={json.dumps(v)}")]
    argv = ["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
            str(tmp_path / "run"), "--no-progress", "--device", "cpu", *sets]
    assert main(argv) == 0
    assert (tmp_path / "run" / "done.json").is_file()
    assert main(argv) == 0  # the same finished run again: nothing to do, and not an error
    assert "run already finished" in capsys.readouterr().out
    assert main(["evaluate", str(tmp_path / "run"), "--split", "hard"]) == 0
    out = capsys.readouterr().out
    for name in ("map", "random", "passive", "box_gate", "pose_seek", "oracle", "moved_if_box", "gated_return"):
        assert name in out
    result = json.loads((tmp_path / "run" / "eval_hard.json").read_text())
    assert set(result) == {"map", "random", "passive", "box_gate", "pose_seek", "departure_ceiling",
                           "departure_ceiling2", "oracle"}
    # the stopping diagnosis, and the learned policy's return behind the stop gate
    assert {"box_start", "moved_if_box", "box_lost", "reco_lost"} <= set(result["map"]["summary"])
    assert isinstance(result["map"]["gated_return"], float) and result["passive"]["summary"]["moved_if_box"] == 0
    assert main(["train", "--method", "map", "--table", str(path), "--out", str(tmp_path / "x"),
                 "--set", "head.hiden=3"]) == 2
    assert "did you mean 'hidden'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def run(table, tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    path = table.save(root / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
                 str(root / "run"), "--no-progress", "--device", "cpu", *_sets()]) == 0
    return root / "run"


def _sets(**extra):
    return [a for k, v in {**small("map"), **extra}.items() for a in ("--set", f"{k}={json.dumps(v)}")]


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


@pytest.mark.parametrize("split, needles", [
    ("bogus", ("unknown split 'bogus'", "'hard_test'", "train (3 contexts)", "hard (2 contexts)")),
    ("simple", ("no contexts of split 'simple'", "train (3 contexts)", "hard (2 contexts)")),
])
def test_evaluate_a_split_the_table_lacks_is_one_line_and_exit_2(run, capsys, monkeypatch, split, needles):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["evaluate", str(run), "--split", split]) == 2
    _one_line_error(capsys, "uevavd evaluate: error:", *needles)
    assert not (run / f"eval_{split}.json").exists()
    monkeypatch.setenv("UEVAVD_DEBUG", "1")
    with pytest.raises(ValueError, match=split):
        main(["evaluate", str(run), "--split", split])


def test_evaluate_bad_input_is_one_line(run, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["evaluate", str(tmp_path)]) == 2
    _one_line_error(capsys, "not a training run")
    assert main(["evaluate", str(run), "--table", str(tmp_path / "nope")]) == 2
    _one_line_error(capsys, "does not exist")
    assert main(["evaluate", str(run), "--table", str(tmp_path)]) == 2  # a folder but no table
    _one_line_error(capsys, "not an observation table", "TableError")


def test_train_bad_input_is_one_line_and_exit_2(table, tmp_path, capsys, monkeypatch):
    from uevavd.table import TableError

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    out = tmp_path / "run"
    base = ["train", "--method", "map", "--out", str(out), "--episodes", "50", "--no-progress", "--device", "cpu"]
    assert main([*base, "--table", str(path), "--set", "train.lr"]) == 2
    _one_line_error(capsys, "expected KEY=VALUE")
    assert main([*base, "--table", str(path), *_sets(**{"env.gamma": 0.99, "train.gamma": 0.95})]) == 2
    _one_line_error(capsys, "train.gamma = 0.95 and env.gamma = 0.99")
    assert main([*base, "--table", str(tmp_path / "missing"), *_sets()]) == 2
    _one_line_error(capsys, "table folder", "does not exist")
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert main([*base[:3], "--out", str(afile), *base[5:], "--table", str(path), *_sets()]) == 2
    _one_line_error(capsys, f"--out {afile} is a file, not a run directory: choose a new --out")
    assert afile.read_text() == "keep me"
    # a table without the train split
    hard = type(table).from_arrays(table.features, table.probs, table.boxes, scenes=list(table.scenes),
                                   targets=table.targets.tolist(), contexts=table.contexts.tolist(),
                                   splits=["hard"] * len(table))
    hard_path = hard.save(tmp_path / "hard_only")
    assert main([*base, "--table", str(hard_path), *_sets()]) == 2
    _one_line_error(capsys, "split 'train'", "hard", "TableError")
    assert not out.exists()
    monkeypatch.setenv("UEVAVD_DEBUG", "1")
    with pytest.raises(TableError, match="split 'train'"):
        main([*base, "--table", str(hard_path), *_sets()])


def test_train_with_a_preset_and_the_preset_a_table_fits(table, tmp_path, capsys, monkeypatch):
    """``train --preset quick`` loads the method with the quick preset's overrides, as the
    demo's runs are (``--set`` wins); trained without it, a table built for the quick
    preset's perception is refused in one line that names the preset."""
    from uevavd.config import load_method
    from uevavd.presets import load_preset, preset_overrides
    from uevavd.table import ObservationTable

    quick = load_method("map", preset_overrides(load_preset("quick"))).perception.as_dict()
    path = ObservationTable.from_arrays(table.features, table.probs, table.boxes, scenes=table.scenes,
                                        targets=table.targets, splits=table.splits,
                                        config={"perception": quick}).save(tmp_path / "table")
    argv = ["train", "--method", "map", "--table", str(path), "--episodes", "100", "--no-progress",
            "--device", "cpu", *_sets(), "--set", 'train.eval_splits=["train", "hard"]']
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main([*argv, "--out", str(tmp_path / "plain")]) == 2
    _one_line_error(capsys, "built for another perception config", "the presets 'paper64', 'quick' fit this table: "
                    "pass --preset with one of them")
    assert not (tmp_path / "plain" / "done.json").exists()
    assert main([*argv, "--preset", "nosuch", "--out", str(tmp_path / "x")]) == 2
    _one_line_error(capsys, "unknown preset 'nosuch'")
    assert main([*argv, "--preset", "quick", "--set", "train.lr=0.002", "--out", str(tmp_path / "run")]) == 0
    settings = json.loads((tmp_path / "run" / "settings.json").read_text())["train"]
    assert settings["eps_fraction"] == 0.15 and settings["episodes"] == 100  # the preset's; --episodes
    assert settings["lr"] == 0.002 and settings["learning_starts"] == 40  # --set over the preset's 1e-3, 500


def test_train_threads_option_sets_the_runs_thread_count(table, tmp_path, capsys, monkeypatch):
    """``--threads N`` is ``--set train.threads=N``: recorded in the run; a negative count is
    one line and exit 2, before any run directory exists."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    base = ["train", "--method", "map", "--table", str(path), "--episodes", "100", "--no-progress",
            "--device", "cpu", *_sets()]
    assert main([*base, "--out", str(tmp_path / "two"), "--threads", "2"]) == 0
    assert json.loads((tmp_path / "two" / "settings.json").read_text())["threads"] == 2
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "bad"), "--threads", "-1"]) == 2
    _one_line_error(capsys, "train.threads = -1", "expected an integer >= 0")
    assert not (tmp_path / "bad").exists()


def test_evaluate_never_writes_over_the_run_it_evaluates_nor_into_the_package(run, tmp_path, capsys, monkeypatch):
    """--json pointed at the run's own settings.json (or its checkpoint, its policy file) replaced
    it; a shipped policy's evaluation wrote its JSON into the installed package's folder."""
    from uevavd.policy import cli as policy_cli

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    table = json.loads((run / "settings.json").read_text())["table_path"]
    for own in ("settings.json", "checkpoint.pt", "policy.safetensors", "tb/events.json"):
        before = (run / own).read_bytes() if (run / own).is_file() else None
        assert main(["evaluate", str(run), "--split", "hard", "--json", str(run / own)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "the evaluated run's own file" in err
        assert ((run / own).read_bytes() if (run / own).is_file() else None) == before
    assert main(["evaluate", str(run / "policy.safetensors"), "--table", table, "--split", "hard", "--json",
                 str(run / "policy.safetensors")]) == 2
    assert "the evaluated run's own file" in capsys.readouterr().err
    # a policy file inside the installed package (here a stand-in): the JSON goes to the current folder
    package = tmp_path / "site" / "uevavd"
    shipped = package / "model_zoo" / "pretrained" / "shipped.safetensors"
    shipped.parent.mkdir(parents=True)
    shutil.copy(run / "policy.safetensors", shipped)
    monkeypatch.setattr(policy_cli, "PACKAGE_DIR", package)
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", str(shipped), "--table", table, "--split", "hard"]) == 0
    assert (tmp_path / "shipped.eval_hard.json").is_file()
    assert not shipped.with_name("shipped.eval_hard.json").exists()


def test_evaluate_json_writes_a_new_file_or_its_own_kind_only(run, table, tmp_path, capsys, monkeypatch):
    """--json at a table's meta.json or another run's settings.json replaced it (the table no longer
    loaded); a zoo policy in a git checkout (the package's model_zoo a link to the checkout's) wrote
    its JSON into model_zoo/."""
    from uevavd.policy import cli as policy_cli

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    table_dir = table.save(tmp_path / "table")
    other = tmp_path / "other.json"
    other.write_text('{"key": "not an evaluation"}')
    for target in (table_dir / "meta.json", other, tmp_path):
        before = target.read_bytes() if target.is_file() else None
        assert main(["evaluate", str(run), "--split", "hard", "--json", str(target)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "choose a new path (nothing was evaluated)" in err
        assert (target.read_bytes() if target.is_file() else None) == before
    out = tmp_path / "e.json"
    assert main(["evaluate", str(run), "--split", "hard", "--json", str(out)]) == 0  # a new file
    assert main(["evaluate", str(run), "--split", "hard", "--json", str(out)]) == 0  # its own kind, again
    capsys.readouterr()
    # a git checkout: the package's model_zoo is a link to the checkout's model_zoo/
    checkout = tmp_path / "checkout"
    (checkout / "model_zoo" / "pretrained").mkdir(parents=True)
    (checkout / "uevavd").mkdir()
    (checkout / "uevavd" / "model_zoo").symlink_to(checkout / "model_zoo")
    shipped = checkout / "model_zoo" / "pretrained" / "shipped.safetensors"
    shutil.copy(run / "policy.safetensors", shipped)
    monkeypatch.setattr(policy_cli, "PACKAGE_DIR", checkout / "uevavd")
    monkeypatch.chdir(tmp_path)
    settings = json.loads((run / "settings.json").read_text())
    assert main(["evaluate", str(shipped), "--table", settings["table_path"], "--split", "hard"]) == 0
    assert (tmp_path / "shipped.eval_hard.json").is_file() and not shipped.with_name("shipped.eval_hard.json").exists()


def test_names_too_long_for_the_file_system_are_one_line_before_any_work(run, table, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    long = "x" * 250
    assert main(["evaluate", str(run), "--split", "hard", "--json", str(tmp_path / f"{long}.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "a name in that path is longer than the file system allows" in err
    path = table.save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
                 str(tmp_path / ("y" * 300)), "--no-progress", "--device", "cpu", *_sets()]) == 2
    assert "longer than the file system allows" in capsys.readouterr().err
    assert main(["synth", "--out", str(tmp_path / ("z" * 300)), "--contexts", "1", "--size", "16", "--quiet"]) == 2
    assert "longer than the file system allows" in capsys.readouterr().err

import json

from uevavd.cli import main

from .conftest import small


def test_train_then_evaluate_from_the_command_line(table, tmp_path, capsys):
    path = table.save(tmp_path / "table")
    sets = [a for k, v in small("map").items() for a in ("--set", f"{k}={json.dumps(v)}")]
    argv = ["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
            str(tmp_path / "run"), "--no-progress", "--device", "cpu", *sets]
    assert main(argv) == 0
    assert (tmp_path / "run" / "done.json").is_file()
    assert main(argv) == 1  # a finished run is refused, with a message
    assert "finished run" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "run"), "--split", "hard"]) == 0
    out = capsys.readouterr().out
    for name in ("map", "random", "passive", "oracle"):
        assert name in out
    result = json.loads((tmp_path / "run" / "eval_hard.json").read_text())
    assert set(result) == {"map", "random", "passive", "oracle"}
    assert main(["train", "--method", "map", "--table", str(path), "--out", str(tmp_path / "x"),
                 "--set", "head.hiden=3"]) == 2
    assert "did you mean 'hidden'" in capsys.readouterr().err

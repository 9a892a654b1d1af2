"""docs/tutorial.md as a new user follows it: its files written from the page's blocks alone,
installed as a package whose entry point registers the encoder, checked by `uevavd plugins
--check`, and its study script run as written, but for its budget line (the 16 px test world
and 100 episodes a run instead of the quick world and schedule)."""

from __future__ import annotations

import re
import runpy
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from uevavd.plugins.manager import manager
from uevavd.testing.worlds import tiny_preset

DOCS = Path(__file__).resolve().parents[2] / "docs" / "tutorial.md"
BUDGET = re.compile(r"^PRESET, DATA, SEEDS, EPISODES = .*$", flags=re.M)


def _write_blocks(root: Path) -> dict[str, Path]:
    """Every code block whose first line names a file (``# my_encoders/pool.py``), written there."""
    files = {}
    for block in re.findall(r"```(?:python|toml)\n(.*?)```", DOCS.read_text(encoding="utf-8"), flags=re.S):
        first = block.splitlines()[0]
        if first.startswith("# ") and first[2:].strip().endswith((".py", ".toml")):
            path = root / first[2:].strip()
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(block, encoding="utf-8")
            files[path.name] = path
    assert set(files) == {"pool.py", "__init__.py", "pyproject.toml", "study.py"}, sorted(files)
    return files


@pytest.fixture
def tutorial(tmp_path, monkeypatch):
    source = tmp_path / "src"
    files = _write_blocks(source)
    target = tmp_path / "site"
    cmd = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
           "--target", str(target), str(source)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    monkeypatch.syspath_prepend(str(target))
    monkeypatch.setenv("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "0")  # found through its entry point, as installed
    manager.reset()
    yield files
    manager.reset()
    for mod in [m for m in sys.modules if m == "my_encoders" or m.startswith("my_encoders.")]:
        del sys.modules[mod]


def test_the_tutorial_runs_as_written(tutorial, tmp_path, ablation_world, monkeypatch, capsys):
    from uevavd.cli import main

    assert main(["plugins", "--check", "my_encoders"]) == 0
    assert "tiny_pool" in capsys.readouterr().out
    preset = tmp_path / "tiny.toml"
    preset.write_text(tiny_preset(episodes=100))
    study = tutorial["study.py"]
    text = study.read_text(encoding="utf-8")
    assert len(BUDGET.findall(text)) == 1, "the study's budget is one line"
    study.write_text(BUDGET.sub(f'PRESET, DATA, SEEDS, EPISODES = "{preset}", "{ablation_world}", 2, 100', text))
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(study), run_name="__main__")
    out = capsys.readouterr().out
    assert "perception.encoder.name=tiny_pool" in out and "hard" in out
    arms = pd.read_csv(tmp_path / "study-pool" / "report" / "arms.csv")
    hard = arms[(arms["metric"] == "return") & (arms["split"] == "hard") & (arms["terrain"] == "all")]
    assert len(hard) == 1 and hard["n"].iloc[0] == 2  # two seeds, paired
    report = (tmp_path / "study-pool" / "report" / "report.md").read_text()
    assert "encoder tiny_pool (default weights)" in report

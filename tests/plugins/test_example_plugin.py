"""The example plugin package in examples/ installs with pip and appears through its entry point."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uevavd.plugins.manager import manager

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "uevavd-example-plugin"


def _tree(root: Path) -> dict[str, float]:
    return {str(p.relative_to(root)): p.stat().st_mtime for p in root.rglob("*")}


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    # pip builds in the source folder (build/, *.egg-info): install from a copy, so that the
    # repository's tree is never written to.
    before = _tree(EXAMPLE)
    source = tmp_path_factory.mktemp("src") / EXAMPLE.name
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    target = tmp_path_factory.mktemp("site")
    cmd = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
           "--no-index", "--target", str(target), str(source)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert list(target.glob("uevavd_example_plugin-0.3.0.dist-info"))
    assert _tree(EXAMPLE) == before, "installing the example wrote into examples/"
    return target


@pytest.fixture
def example_loaded(installed, monkeypatch):
    monkeypatch.syspath_prepend(str(installed))
    monkeypatch.setenv("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "0")
    manager.reset()
    yield manager
    manager.reset()


def test_example_plugin_appears_through_its_entry_point(example_loaded):
    reg = example_loaded.registry
    assert reg.get("encoder", "color_hist").plugin == "example"
    assert reg.get("encoder", "color_hist").plugin_version == "0.3.0"
    assert "box" in reg.names("segmenter")
    assert {"memo_map_hist", "memo_map_lstm"} <= set(reg.names("method"))
    assert "lstm" in reg.names("state") and "confident_stop" in reg.names("baseline")
    info = next(p for p in example_loaded.plugins if p.name == "example")
    assert info.status == "loaded" and not info.builtin


def test_example_components_work_and_pass_the_contract(example_loaded):
    import uevavd_example_plugin

    from uevavd.testing import check_plugin_module

    entries = check_plugin_module(uevavd_example_plugin, name="example-under-test")
    assert {e.name for e in entries} == {"color_hist", "box", "lstm", "confident_stop", "memo_map_hist",
                                         "memo_map_lstm"}
    enc = example_loaded.registry.build("encoder", "color_hist", bins=4)
    images = np.random.default_rng(0).integers(0, 256, (3, 16, 16, 3), dtype=np.uint8)
    feats = enc.encode(images)
    assert feats.shape == (3, 12) and feats.dtype == np.float32
    np.testing.assert_allclose(feats.reshape(3, 3, 4).sum(-1), 1.0, rtol=1e-6)
    seg = example_loaded.registry.build("segmenter", "box")
    out = seg.segment(images, np.array([[4, 4, 12, 12]] * 3))
    assert out[0].target.sum() == 64 and not any((m & out[0].target).any() for m in out[0].segments)


def test_plugins_disabled_by_name(installed, monkeypatch):
    monkeypatch.syspath_prepend(str(installed))
    monkeypatch.setenv("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "0")
    monkeypatch.setenv("UEVAVD_DISABLED_PLUGINS", "example")
    manager.reset()
    try:
        assert "color_hist" not in manager.registry.names("encoder")
    finally:
        manager.reset()


def test_the_example_passes_check_plugin(example_loaded):
    """Every component built and run through its kind's rules, both methods trained on a toy
    table and evaluated beside the baselines (the plugin's own among them)."""
    import uevavd_example_plugin

    from uevavd.testing import check_plugin

    report = check_plugin(uevavd_example_plugin)
    assert report.plugin == "example"  # found under its entry point's name, not registered twice
    checked = "\n".join(report.checked)
    for needle in ("state lstm with preset paper64's ['input_dim', 'state_dim']", "baseline confident_stop",
                   "method memo_map_lstm: trained 300 toy episodes", "method memo_map_hist loads with preset quick"):
        assert needle in checked, (needle, checked)
    assert "example" in {p.name for p in example_loaded.plugins}


def test_a_tiny_ablation_with_the_example_from_the_command_line(example_loaded, tmp_path, ablation_world, capsys):
    """As a user who pip-installed the plugin runs it: its method trains beside MAP, its
    baseline joins every evaluation, both under their registered labels. The command runs
    in this process (its entry point found as above); the session's cache holds the
    recognizer of this world and preset."""
    import json

    import pandas as pd

    from uevavd.cli import main
    from uevavd.testing.worlds import tiny_preset

    preset = tmp_path / "tiny.toml"
    preset.write_text(tiny_preset(ablation='methods = ["map", "memo_map_lstm"]\nseeds = 1\nrecognizers = 1\n',
                                  episodes=100))  # one epoch: the rows are what is checked
    out = tmp_path / "out"
    code = main(["ablate", "--preset", str(preset), "--data", str(ablation_world), "--out", str(out), "--workers", "1",
                 "--no-figures"])
    assert code == 0, capsys.readouterr().err[-3000:]
    df = pd.read_csv(out / "results.csv")
    assert {"map", "memo_map_lstm", "confident_stop"} <= set(df["method"])
    roles = json.loads((out / "ablation.json").read_text())["roles"]
    assert "confident_stop" in roles["baselines"] and "memo_map_lstm" not in roles["baselines"]
    report = (out / "report" / "report.md").read_text()
    assert "Memo-MAP (LSTM)" in report and "Confident stop" in report

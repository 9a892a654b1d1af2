"""`uevavd.testing.check_plugin` / `uevavd plugins --check`: one check a plugin author runs
finds every mistake `train`, `evaluate` and `ablate` would meet later. Before it,
`check_plugin_module` passed four broken method TOMLs, a TOML left out of the wheel, a
non-causal estimator, a builder without ``feature_dim`` and baselines the env refuses."""

from __future__ import annotations

import types

import pytest
import torch

from uevavd.cli import main
from uevavd.plugins import hookimpl
from uevavd.plugins.manager import manager
from uevavd.state.gru import build_gru
from uevavd.state.single_view import build_single_view
from uevavd.testing import check_baseline, check_plugin
from uevavd.testing.plugins import check_plugin_module


class _PeekingState(torch.nn.Module):
    """The single-view estimator on the mean of the episode's features: reads the future."""

    recurrent = False

    def __init__(self, feature_dim):
        super().__init__()
        self.inner = build_single_view(feature_dim=feature_dim, input_dim=24, box_dim=8, state_dim=16)
        self.feature_dim, self.state_dim = feature_dim, 16

    def forward(self, features, boxes):
        return self.inner(features.mean(dim=1, keepdim=True).expand_as(features), boxes)

    def initial_hidden(self, n, device="cpu"):
        return self.inner.initial_hidden(n, device)

    def step(self, features, boxes, hidden):
        return self.inner.step(features, boxes, hidden)


def build_non_causal(*, feature_dim, input_dim=24, box_dim=8, state_dim=16):
    return _PeekingState(feature_dim)


def build_learned_start(*, feature_dim, input_dim=24, box_dim=8, state_dim=16, hidden=16):
    gru = build_gru(feature_dim=feature_dim, input_dim=input_dim, box_dim=box_dim, state_dim=state_dim, hidden=hidden)
    gru.initial_hidden = lambda n, device="cpu": torch.full((n, hidden), 0.5, device=device)
    return gru


def build_no_feature_dim(*, input_dim=24, box_dim=8, state_dim=16):
    return build_single_view(feature_dim=8, input_dim=input_dim, box_dim=box_dim, state_dim=state_dim)

GOOD = """_base_ = "memo_map"
name = "{name}"
description = "fine"
"""
BROKEN_TOMLS = {
    "bad_syntax": ('name = "bad_syntax"\n[state\n', "not valid TOML"),
    "bad_section": ('_base_ = "map"\nname = "bad_section"\n[stat]\nname = "gru"\n', "stat"),
    "bad_base": ('_base_ = "memo_mapp"\nname = "bad_base"\n', "_base_ = 'memo_mapp'"),
    "bad_component": ('_base_ = "map"\nname = "bad_component"\n[state]\nname = "lstmm"\n', "unknown state 'lstmm'"),
}


def build_float_actions(*, table, config, seed: int = 0):
    """Gives its actions as floats (the env takes integer indices)."""

    class FloatActions:
        needs_features = False

        def reset(self, n):
            pass

        def act(self, obs):
            n = obs["view"].shape[0]
            return torch.full((n,), 6.0), torch.zeros(n)

    return FloatActions()


def build_unseeded(*, table, config, seed: int = 0):
    from uevavd.env.baselines import RandomPolicy

    return RandomPolicy(int(torch.randint(0, 2**31, ())))


def _plugin(tmp_path, *, tomls=(), states=(), baselines=(), missing_toml=False):
    for name, (text, _) in tomls:
        (tmp_path / f"{name}.toml").write_text(text)

    @hookimpl
    def register_methods(registry):
        for name, _ in tomls:
            registry.add(name, str(tmp_path / f"{name}.toml"))
        if missing_toml:
            registry.add("left_out", str(tmp_path / "left_out.toml"))

    @hookimpl
    def register_state_estimators(registry):
        for name in states:
            registry.add(name, f"{__name__}:build_{name}")

    @hookimpl
    def register_baselines(registry):
        for name in baselines:
            registry.add(name, f"{__name__}:build_{name}")

    return types.SimpleNamespace(register_methods=register_methods, register_baselines=register_baselines,
                                 register_state_estimators=register_state_estimators)


def test_every_broken_method_file_is_listed(tmp_path):
    plugin = _plugin(tmp_path, tomls=list(BROKEN_TOMLS.items()), missing_toml=True)
    check_plugin_module(plugin, name="tomls")  # the old check: passes all five
    with pytest.raises(AssertionError) as err:
        check_plugin(plugin, name="tomls", train_methods=False)
    message = str(err.value)
    assert "5 problem(s)" in message, message
    for name, (_, needle) in BROKEN_TOMLS.items():
        assert needle in message, (name, message)
    assert "left_out.toml does not exist" in message and "package data" in message
    assert "tomls" not in {p.name for p in manager.plugins}  # registered for the check only


def test_a_method_file_left_out_of_the_wheel_is_named_when_used(tmp_path):
    from uevavd.config import ConfigError, load_method

    manager.register_plugin(_plugin(tmp_path, missing_toml=True), name="wheel")
    try:
        with pytest.raises(ConfigError, match="method 'left_out' of plugin 'wheel' names .*which is not installed"):
            load_method("left_out")
    finally:
        manager.unregister_plugin("wheel")


def test_broken_state_estimators_and_baselines_are_listed(tmp_path):
    plugin = _plugin(tmp_path, states=("non_causal", "learned_start", "no_feature_dim"),
                     baselines=("float_actions", "unseeded"))
    with pytest.raises(AssertionError) as err:
        check_plugin(plugin, name="broken")
    message = str(err.value)
    assert "5 problem(s)" in message, message
    for needle in ("state non_causal", "not causal", "state learned_start", "initial_hidden() is not zeros",
                   f"state no_feature_dim: builder {__name__}:build_no_feature_dim does not take ['feature_dim']", "baseline float_actions: evaluating it on the hard split raised",
                   "baseline unseeded: two policies built with seed 0 gave different returns"):
        assert needle in message, (needle, message)


def test_a_good_method_is_trained_and_evaluated(tmp_path):
    plugin = _plugin(tmp_path, tomls=[("fine_memo", (GOOD.format(name="fine_memo"), ""))])
    report = check_plugin(plugin, name="good", episodes=200)
    assert any("trained 200 toy episodes" in line for line in report.checked), str(report)
    assert any("loads with preset paper's overrides" in line for line in report.checked)


def test_check_baseline_says_when_it_does_not_apply():
    from uevavd.env.baselines import build_passive, build_visibility_oracle

    assert check_baseline(build_passive) is True
    assert check_baseline(build_visibility_oracle) is False  # the toy table knows no visible fractions


def test_the_command_line_check(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["plugins", "--check", "no_such_module_xyz"]) == 2
    assert "no module named 'no_such_module_xyz' is importable" in capsys.readouterr().err
    # a plugin module whose own import fails: one line naming it and the error, not a traceback
    (tmp_path / "failing_import_mod.py").write_text("import no_such_dependency_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["plugins", "--check", "failing_import_mod"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "importing 'failing_import_mod' failed: ModuleNotFoundError: No module named " \
        "'no_such_dependency_xyz'" in err
    # a module of hooks: exit 1 listing the problems
    mod = tmp_path / "broken_hooks_mod.py"
    mod.write_text("from uevavd.plugins import hookimpl\n\n@hookimpl\ndef register_state_estimators(registry):\n"
                   f"    registry.add('non_causal', '{__name__}:build_non_causal')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["plugins", "--check", "broken_hooks_mod"]) == 1
    err = capsys.readouterr().err
    assert "1 problem(s)" in err and "not causal" in err and "Traceback" not in err


def test_plugins_check_takes_the_pip_name_and_names_the_entry_point_of_a_package(tmp_path, monkeypatch, capsys):
    """`uevavd plugins --check PKG` on a package whose hooks live in PKG.plugin said "registered
    nothing"; the distribution's pip name was "no module named ..."."""
    from uevavd.cli import main

    site = tmp_path / "site"
    (site / "pkg_with_hooks").mkdir(parents=True)
    (site / "pkg_with_hooks" / "__init__.py").write_text("")
    (site / "pkg_with_hooks" / "plugin.py").write_text(
        "from uevavd.plugins import hookimpl\n"
        "from uevavd.env.baselines import PassivePolicy\n\n"
        "def build(*, table, config, seed=0):\n    return PassivePolicy()\n\n"
        "@hookimpl\ndef register_baselines(registry):\n"
        "    registry.add('still', 'pkg_with_hooks.plugin:build', summary='never moves')\n")
    info = site / "hooks_dist-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hooks-dist\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[uevavd]\nstill = pkg_with_hooks.plugin\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["plugins", "--check", "pkg_with_hooks"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "run `uevavd plugins --check pkg_with_hooks.plugin`" in err, err
    assert main(["plugins", "--check", "hooks-dist"]) == 0  # the pip name
    assert "baseline still: evaluated" in capsys.readouterr().out

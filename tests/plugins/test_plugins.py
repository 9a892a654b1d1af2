"""The plugin system: built-ins, third-party plugins through real entry points, failures."""

from __future__ import annotations

import sys
import textwrap
import warnings

import pytest

from uevavd.plugins.manager import PluginManager, PluginWarning, manager
from uevavd.plugins.registry import DuplicateComponentError, PluginError, UnknownComponentError


def make_dist(root, dist: str, version: str, module: str, source: str, ep_name: str | None = None):
    """Write an installed distribution (module + dist-info with an entry point) under ``root``."""
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{dist.replace('-', '_')}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text(f"[uevavd]\n{ep_name or dist} = {module}\n")


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A fresh site directory on sys.path; autoload on; manager reset before and after."""
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "0")
    for var in ("UEVAVD_STRICT_PLUGINS", "UEVAVD_DISABLED_PLUGINS"):
        monkeypatch.delenv(var, raising=False)
    manager.reset()
    yield tmp_path
    for name in [m for m in sys.modules if m.startswith("fakeplug_")]:
        del sys.modules[name]
    manager.reset()


GOOD = """
from uevavd.plugins import hookimpl

@hookimpl
def register_encoders(registry):
    registry.add("fake_enc", "fakeplug_good:build", summary="a fake encoder")

@hookimpl
def register_heads(registry):
    registry.add("fake_head", "fakeplug_good:build")

def build(*, dim: int = 3):
    return ("built", dim)
"""


def test_builtins_register_through_the_hooks():
    pm = PluginManager()
    names = {p.name for p in pm.plugins}
    assert {"uevavd.perception.plugin", "uevavd.state.plugin", "uevavd.policy.plugin"} <= names
    reg = pm.registry
    assert {"resnet18", "resnet50"} <= set(reg.names("encoder"))
    assert {"single_view", "gru"} <= set(reg.names("state"))
    assert {"dueling_branch", "dueling_joint"} <= set(reg.names("head"))
    assert {"gt", "none", "sam"} <= set(reg.names("segmenter"))
    assert all(p.builtin and p.status == "loaded" for p in pm.plugins)


def test_loading_is_lazy_and_once():
    pm = PluginManager()
    assert not pm._loaded
    first = pm.registry
    assert pm._loaded and pm.registry is first


def test_third_party_plugin_through_entry_point(site):
    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    assert "fakeplug_good" not in sys.modules
    reg = manager.registry
    assert "fake_enc" in reg.names("encoder")
    entry = reg.get("encoder", "fake_enc")
    assert (entry.plugin, entry.plugin_version, entry.summary) == ("fake-good", "1.2.3", "a fake encoder")
    assert reg.build("encoder", "fake_enc", dim=7) == ("built", 7)
    info = next(p for p in manager.plugins if p.name == "fake-good")
    assert info.registered == {"encoder": ["fake_enc"], "head": ["fake_head"]} and not info.builtin


def test_builders_are_imported_only_when_built(site):
    make_dist(site, "fake-lazy", "1.0", "fakeplug_lazy", """
        from uevavd.plugins import hookimpl

        @hookimpl
        def register_encoders(registry):
            registry.add("lazy_enc", "fakeplug_lazybuilder:build")
    """)
    (site / "fakeplug_lazybuilder.py").write_text("def build(*, x=1):\n    return x\n")
    assert "lazy_enc" in manager.registry.names("encoder")
    assert "fakeplug_lazybuilder" not in sys.modules
    assert manager.registry.build("encoder", "lazy_enc") == 1
    assert "fakeplug_lazybuilder" in sys.modules


BROKEN_IMPORT = "raise RuntimeError('boom at import')\n"
BAD_SIGNATURE = """
from uevavd.plugins import hookimpl

@hookimpl
def register_encoders(reg, extra):
    reg.add("never", "x:y")
"""
HALF = """
from uevavd.plugins import hookimpl

@hookimpl
def register_encoders(registry):
    registry.add("half_first", "fakeplug_half:b")

@hookimpl
def register_heads(registry):
    raise ValueError("second hook fails")
"""


MISSPELLED = """
from uevavd.plugins import hookimpl

@hookimpl
def register_encoder(registry):
    registry.add("misspelled_enc", "fakeplug_broken:b")
"""


@pytest.mark.parametrize(
    "source, needle",
    [(BROKEN_IMPORT, "boom at import"), (BAD_SIGNATURE, "extra"), (HALF, "second hook fails"),
     (MISSPELLED, "unknown hook 'register_encoder'")],
    ids=["import-error", "bad-signature", "hook-raises", "misspelled-hook"],
)
def test_broken_plugin_is_skipped_with_a_warning(site, source, needle):
    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", source)
    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    with pytest.warns(PluginWarning) as rec:
        reg = manager.registry
    msg = str(rec[0].message)
    assert "fake-broken" in msg and "0.9" in msg and needle in msg
    assert "fake_enc" in reg.names("encoder")  # the good one still loads
    assert "half_first" not in reg.names("encoder")  # nothing half-registered
    assert "never" not in reg.names("encoder")
    info = next(p for p in manager.plugins if p.name == "fake-broken")
    assert info.status == "failed" and needle in info.error


def test_broken_plugin_is_fatal_in_strict_mode(site, monkeypatch):
    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", BROKEN_IMPORT)
    monkeypatch.setenv("UEVAVD_STRICT_PLUGINS", "1")
    with pytest.raises(PluginError, match="fake-broken.*boom at import"):
        manager.ensure_loaded()


def test_a_strict_failure_is_one_line_from_the_command_line(site, monkeypatch, capsys):
    """`UEVAVD_STRICT_PLUGINS=1` with a broken plugin ended a command in a traceback, exit 1;
    the README promises one line, exit 2."""
    from uevavd.cli import main

    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", BROKEN_IMPORT)
    monkeypatch.setenv("UEVAVD_STRICT_PLUGINS", "1")
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    for argv in (["plugins"], ["train", "--help"], ["train", "--method", "map", "--table", "t", "--out", "o"]):
        manager.reset()  # each command loads the plugins afresh, as a new process does
        assert main(argv) == 2, argv  # train's parser loads them to list the methods: it was a traceback, exit 1
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "fake-broken" in err and "boom at import" in err, err
        assert "UEVAVD_STRICT_PLUGINS is set" in err


def test_a_skipped_plugin_is_named_where_its_component_is_asked_for(site):
    """The warning pointed at a line of uevavd's plugin manager, and asking for a component of
    the plugin that failed said only "did you mean ..."."""
    import warnings

    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", BROKEN_IMPORT)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        manager.ensure_loaded()
    warning = next(w for w in rec if issubclass(w.category, PluginWarning))
    assert warning.filename == "<uevavd plugin fake-broken>"
    with pytest.raises(UnknownComponentError, match="plugin 'fake-broken' failed to load and registered nothing"):
        manager.registry.get("encoder", "broken_enc")


def test_manager_recovers_after_a_strict_failure(site, monkeypatch):
    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", BROKEN_IMPORT)
    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    monkeypatch.setenv("UEVAVD_STRICT_PLUGINS", "1")
    for _ in range(2):  # the same error again, not a DuplicateComponentError on built-in 'none'
        with pytest.raises(PluginError, match="fake-broken.*boom at import") as err:
            manager.ensure_loaded()
        assert not isinstance(err.value, DuplicateComponentError)
    monkeypatch.setenv("UEVAVD_DISABLED_PLUGINS", "fake-broken")  # the user blocks it and carries on
    reg = manager.registry
    assert "none" in reg.names("segmenter") and "fake_enc" in reg.names("encoder")
    names = [p.name for p in manager.plugins]
    assert len(names) == len(set(names))
    assert next(p for p in manager.plugins if p.name == "fake-broken").status == "blocked"


def test_duplicate_name_is_an_error_naming_both(site):
    make_dist(site, "fake-dup", "2.0", "fakeplug_dup", """
        from uevavd.plugins import hookimpl

        @hookimpl
        def register_encoders(registry):
            registry.add("resnet18", "fakeplug_dup:b")
    """)
    with pytest.warns(PluginWarning, match=r"registered twice.*uevavd\.perception\.plugin.*fake-dup"):
        reg = manager.registry
    assert reg.get("encoder", "resnet18").plugin == "uevavd.perception.plugin"


def test_duplicate_from_code_raises():
    pm = PluginManager()
    pm.ensure_loaded()

    import types

    from uevavd.plugins import hookimpl

    @hookimpl
    def register_state_estimators(registry):
        registry.add("gru", "x:y")

    plug = types.SimpleNamespace(register_state_estimators=register_state_estimators)
    with pytest.raises(PluginError, match="registered twice"):
        pm.register_plugin(plug, name="dup-from-code")
    assert pm.registry.get("state", "gru").plugin == "uevavd.state.plugin"


def test_duplicate_error_type():
    from uevavd.plugins.registry import Entry, Registry

    r = Registry()
    r.add_entry(Entry("encoder", "a", "m:a", "", "p1", "1"))
    with pytest.raises(DuplicateComponentError, match="'p1'.*'p2'"):
        r.add_entry(Entry("encoder", "a", "m:b", "", "p2", "1"))


def test_blocked_plugins(site, monkeypatch):
    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    monkeypatch.setenv("UEVAVD_DISABLED_PLUGINS", "other, fake-good")
    assert "fake_enc" not in manager.registry.names("encoder")
    assert "fakeplug_good" not in sys.modules
    info = next(p for p in manager.plugins if p.name == "fake-good")
    assert info.status == "blocked"


def test_autoload_off_skips_entry_points(site, monkeypatch):
    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    monkeypatch.setenv("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "1")
    assert "fake_enc" not in manager.registry.names("encoder")
    assert all(p.builtin for p in manager.plugins)


def test_unknown_component_suggests():
    with pytest.raises(UnknownComponentError, match="did you mean 'resnet50'"):
        manager.registry.get("encoder", "resnet5O")
    with pytest.raises(ValueError, match="unknown component kind"):
        manager.registry.names("encoders")


def test_cli_lists_plugins(site, capsys):
    from uevavd.cli import main

    make_dist(site, "fake-good", "1.2.3", "fakeplug_good", GOOD)
    make_dist(site, "fake-broken", "0.9", "fakeplug_broken", BROKEN_IMPORT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["plugins", "--all"]) == 0
    out = capsys.readouterr().out
    assert "fake-good 1.2.3 (third-party, loaded)" in out and "encoder: fake_enc" in out
    assert "fake-broken 0.9 (third-party, failed)" in out and "boom at import" in out
    manager.reset()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["plugins", "--json"]) == 0
    import json

    rows = json.loads(capsys.readouterr().out)
    assert {r["name"] for r in rows} >= {"fake-good", "uevavd.state.plugin"}
    assert "fake-broken" not in {r["name"] for r in rows}

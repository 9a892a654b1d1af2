"""Contract checks for plugin modules and registry entries.

    from uevavd.testing import check_plugin_module
    import my_plugin
    check_plugin_module(my_plugin)   # hooks valid, every builder importable and keyword-only
"""

from __future__ import annotations

import inspect
from types import ModuleType
from typing import Any

from ..config import load_method
from ..plugins.manager import PluginManager
from ..plugins.registry import KINDS, Entry


def check_registry_entry(entry: Entry) -> None:
    """The entry's builder imports and takes keyword-only arguments (methods: the file loads)."""
    assert entry.kind in KINDS, f"{entry.name}: unknown kind {entry.kind!r}"
    target = entry.load()
    if entry.kind == "method":
        spec = load_method(target)
        assert spec.name, f"method {entry.name}: no name"
        return
    assert callable(target), f"{entry.kind} {entry.name}: {entry.target} is not callable"
    params = inspect.signature(target).parameters.values()
    positional = [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    assert not positional, (
        f"{entry.kind} {entry.name}: builder {entry.target} takes positional parameters {positional}; "
        "make them keyword-only (def build(*, ...)) so method configs can name them"
    )


def check_plugin_module(plugin: ModuleType | Any, name: str = "plugin-under-test") -> list[Entry]:
    """Load ``plugin`` beside the built-ins in a scratch manager and check everything it registers.

    Returns its entries. Raises ``AssertionError`` (or the plugin's own error) on a problem.
    """
    manager = PluginManager(autoload=False)
    manager.ensure_loaded()
    info = manager.register_plugin(plugin, name=name)
    assert info.status == "loaded", f"{name}: {info.error}"
    entries = [
        e for kind in KINDS for e in manager.registry.entries[kind].values() if e.plugin == name
    ]
    assert entries, f"{name}: registered nothing; implement at least one hook from uevavd.plugins.hookspecs"
    for entry in entries:
        if entry.kind != "method":  # methods may inherit configs that need the global registry
            check_registry_entry(entry)
    return entries

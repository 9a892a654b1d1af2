"""Loading plugins: built-ins first, then the ``uevavd`` entry points, lazily and once.

Environment switches (read when the registry first loads):

* ``UEVAVD_STRICT_PLUGINS=1``: a failing third-party plugin is fatal instead of skipped.
* ``UEVAVD_DISABLED_PLUGINS=a,b``: block plugins by name.
* ``UEVAVD_DISABLE_PLUGIN_AUTOLOAD=1``: do not load entry points at all.
"""

from __future__ import annotations

import importlib
import os
import threading
import warnings
from dataclasses import dataclass, field
from importlib import metadata
from types import ModuleType
from typing import Any

import pluggy

from ..version import __version__
from . import ENTRY_POINT_GROUP, PROJECT, hookspecs
from .registry import KINDS, Entry, KindRegistry, PluginError, Registry, StrictPluginError

#: Built-in components register through the same hooks as third-party ones.
DEFAULT_PLUGINS: tuple[str, ...] = (
    "uevavd.perception.plugin",
    "uevavd.state.plugin",
    "uevavd.policy.plugin",
    "uevavd.env.plugin",
    "uevavd.plugins.methods",
)


class PluginWarning(UserWarning):
    """A third-party plugin failed and was skipped."""


@dataclass
class PluginInfo:
    name: str
    version: str
    builtin: bool
    status: str  #: "loaded", "failed", "blocked"
    error: str = ""
    source: str = ""  #: module name or entry point value
    registered: dict[str, list[str]] = field(default_factory=dict)


def _truthy(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() in ("1", "true", "yes", "on")


class PluginManager:
    """Owns the pluggy manager and the component registry; loads on first use."""

    def __init__(self, default_plugins: tuple[str, ...] = DEFAULT_PLUGINS, *, autoload: bool | None = None):
        """``autoload``: load entry points (None: unless UEVAVD_DISABLE_PLUGIN_AUTOLOAD is set)."""
        self._default_plugins = default_plugins
        self._autoload = autoload
        self._lock = threading.RLock()
        self._loaded = False
        self._pm: pluggy.PluginManager | None = None
        self._registry = Registry()
        self._plugins: list[PluginInfo] = []
        self._extra: list[tuple[str, Any]] = []  # plugins registered by code (tests, notebooks)

    # -- public -------------------------------------------------------------------------
    @property
    def registry(self) -> Registry:
        self.ensure_loaded()
        return self._registry

    @property
    def plugins(self) -> list[PluginInfo]:
        self.ensure_loaded()
        return list(self._plugins)

    def register_plugin(self, plugin: ModuleType | object, name: str | None = None) -> PluginInfo:
        """Register a plugin object or module at run time (e.g. in a test or notebook).

        Errors raise: code that registers a plugin directly wants to know.
        """
        self.ensure_loaded()
        pname = name or getattr(plugin, "__name__", None) or type(plugin).__name__
        with self._lock:
            info = self._load_one(pname, plugin, version="local", builtin=False, source="code", strict=True)
            self._extra.append((pname, plugin))
            return info

    def name_of(self, plugin: ModuleType | object) -> str | None:
        """The name ``plugin`` is registered under (an entry point's name, or the one given
        to :meth:`register_plugin`), or None when it is not registered."""
        self.ensure_loaded()
        assert self._pm is not None
        return self._pm.get_name(plugin) if self._pm.is_registered(plugin) else None

    def unregister_plugin(self, name: str) -> None:
        """Remove a plugin and everything it registered."""
        with self._lock:
            assert self._pm is not None
            plugin = self._pm.get_plugin(name)
            if plugin is not None:
                self._pm.unregister(plugin)
            for kind in KINDS:
                for n in [n for n, e in self._registry.entries[kind].items() if e.plugin == name]:
                    del self._registry.entries[kind][n]
            self._plugins = [p for p in self._plugins if p.name != name]
            self._extra = [(n, p) for n, p in self._extra if n != name]

    def reset(self) -> None:
        """Forget everything; the next access loads again (reads the environment again)."""
        with self._lock:
            self._loaded = False
            self._pm = None
            self._registry = Registry()
            self._plugins = []
            self._extra = []

    def ensure_loaded(self) -> None:
        if self._loaded:
            return
        with self._lock:
            if self._loaded:
                return
            try:
                self._load_all()
            except BaseException:
                # A failed load (e.g. a broken plugin in strict mode) leaves nothing behind,
                # so that the next access starts again from scratch instead of tripping over
                # the half-filled registry (built-ins would clash with themselves).
                self._pm = None
                self._registry = Registry()
                self._plugins = []
                raise
            self._loaded = True

    # -- loading ------------------------------------------------------------------------
    def _load_all(self) -> None:
        pm = pluggy.PluginManager(PROJECT)
        pm.add_hookspecs(hookspecs)
        self._pm = pm
        self._registry = Registry()
        self._plugins = []
        blocked = {b.strip() for b in os.environ.get("UEVAVD_DISABLED_PLUGINS", "").split(",") if b.strip()}
        strict = _truthy("UEVAVD_STRICT_PLUGINS")

        for modname in self._default_plugins:
            # A broken built-in is a bug in uevavd: always fatal.
            module = importlib.import_module(modname)
            self._load_one(modname, module, version=__version__, builtin=True, source=modname, strict=True)

        autoload = self._autoload if self._autoload is not None else not _truthy("UEVAVD_DISABLE_PLUGIN_AUTOLOAD")
        if not autoload:
            return
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            version = ep.dist.version if ep.dist is not None else "?"
            if ep.name in blocked:
                self._plugins.append(
                    PluginInfo(ep.name, version, False, "blocked", "UEVAVD_DISABLED_PLUGINS", ep.value)
                )
                continue
            try:
                obj = ep.load()
            except Exception as exc:  # noqa: BLE001 - any import failure is reported
                self._fail(ep.name, version, ep.value, f"import failed: {type(exc).__name__}: {exc}", strict)
                continue
            self._load_one(ep.name, obj, version=version, builtin=False, source=ep.value, strict=strict)

    def _load_one(
        self, name: str, plugin: Any, *, version: str, builtin: bool, source: str, strict: bool
    ) -> PluginInfo:
        assert self._pm is not None
        staged: list[Entry] = []
        try:
            self._pm.register(plugin, name=name)
            # a hook whose name is misspelled (register_encoder for register_encoders) would
            # register nothing without a word: pluggy lists hooks that match no spec
            self._pm.check_pending()
        except Exception as exc:  # noqa: BLE001 - pluggy's validation errors and name clashes
            if self._pm.is_registered(plugin):
                self._pm.unregister(plugin)
            hint = (f"; uevavd's hooks are {sorted(KINDS.values())}" if "unknown hook" in str(exc) else "")
            return self._fail(name, version, source, f"{type(exc).__name__}: {exc}{hint}", strict, builtin)
        try:
            for kind, hook_name in KINDS.items():
                for impl in getattr(self._pm.hook, hook_name).get_hookimpls():
                    if impl.plugin is plugin:
                        impl.function(registry=KindRegistry(kind, name, version, staged))
            # Commit all or nothing.
            committed: list[Entry] = []
            try:
                for entry in staged:
                    self._registry.add_entry(entry)
                    committed.append(entry)
            except Exception:
                for entry in committed:
                    del self._registry.entries[entry.kind][entry.name]
                raise
        except Exception as exc:  # noqa: BLE001
            self._pm.unregister(plugin)
            return self._fail(name, version, source, f"{type(exc).__name__}: {exc}", strict, builtin)
        registered: dict[str, list[str]] = {}
        for e in staged:
            registered.setdefault(e.kind, []).append(e.name)
        info = PluginInfo(name, version, builtin, "loaded", "", source, registered)
        self._plugins.append(info)
        return info

    def _fail(
        self, name: str, version: str, source: str, error: str, strict: bool, builtin: bool = False
    ) -> PluginInfo:
        message = f"uevavd plugin {name!r} (version {version}, from {source}) failed and was skipped: {error}"
        if strict or builtin:
            if builtin:  # a broken built-in is a bug in uevavd: its traceback is wanted
                raise PluginError(message.replace(" and was skipped", ""))
            hint = " (UEVAVD_STRICT_PLUGINS is set; unset it to skip broken plugins)" if source != "code" else ""
            raise StrictPluginError(message.replace(" and was skipped", "") + hint)
        # said as coming from the plugin (its entry point), not from a line of this manager
        warnings.warn_explicit(
            message + ". Block it with UEVAVD_DISABLED_PLUGINS or make this fatal with UEVAVD_STRICT_PLUGINS=1",
            PluginWarning, filename=f"<uevavd plugin {name}>", lineno=0, module="uevavd.plugins.manager",
        )
        info = PluginInfo(name, version, builtin, "failed", error, source)
        self._plugins.append(info)
        self._registry.failed.append(name)
        return info


#: The process-wide manager. ``uevavd.registry`` is its registry (loaded on first use).
manager = PluginManager()


def __getattr__(name: str) -> Any:
    if name == "registry":
        return manager.registry
    raise AttributeError(name)


def build(kind: str, name: str, /, **kwargs: Any) -> Any:
    """Build a registered component: ``build("encoder", "resnet18", weights="random")``."""
    return manager.registry.build(kind, name, **kwargs)

"""Component registries: what plugins register, and how a component is built.

A :class:`Registry` holds, per component kind, ``name -> Entry``. Entries name their
builder by a ``"module:attr"`` string that is imported only by :meth:`Registry.build`,
so listing components never imports torch.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.resources
import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: Component kinds, and the hook that registers each.
KINDS: dict[str, str] = {
    "segmenter": "register_segmenters",
    "encoder": "register_encoders",
    "classifier": "register_classifiers",
    "state": "register_state_estimators",
    "head": "register_heads",
    "method": "register_methods",
    "baseline": "register_baselines",
}


class PluginError(RuntimeError):
    """A plugin could not be loaded, or registered something invalid."""


class StrictPluginError(PluginError):
    """A third-party plugin failed while ``UEVAVD_STRICT_PLUGINS=1`` makes that fatal: the
    installation's state, not a bug of uevavd, so a command reports it in one line (exit 2)."""


class DuplicateComponentError(PluginError):
    """Two providers registered the same (kind, name)."""


class UnknownComponentError(KeyError):
    """No component of that kind has that name."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


@dataclass(frozen=True)
class Entry:
    """One registered component."""

    kind: str
    name: str
    target: str  #: "module:attr" of the builder (or, for methods, of the TOML file)
    summary: str
    plugin: str  #: name of the plugin that registered it
    plugin_version: str
    #: traits the host reads without building the component, e.g. a baseline's "seeded"
    #: (it differs per seed, so ablations run it once per RL seed)
    tags: tuple[str, ...] = ()
    #: display name in reports, tables and figures ("" : the name itself)
    label: str = ""

    def load(self) -> Any:
        """Import and return the builder (or, for methods, the TOML path)."""
        if self.kind == "method":
            return resolve_method_target(self.target)
        return import_target(self.target)


def resolve_method_target(target: str) -> Path:
    """A registered method's TOML path: absolute path, or ``"package:relative/path.toml"``."""
    p = Path(target)
    if p.is_absolute():
        return p
    package, sep, rel = target.partition(":")
    if not sep:
        raise ValueError(f"method target {target!r}: expected an absolute path or 'package:path.toml'")
    return Path(str(importlib.resources.files(package).joinpath(rel)))


def import_target(target: str) -> Any:
    """Import ``"module:attr"`` (attr may be dotted) and return the attribute."""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"builder target {target!r}: expected 'module:attr'")
    obj: Any = importlib.import_module(module_name)
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ImportError(f"builder target {target!r}: module {module_name!r} has no {attr!r}") from None
    return obj


@dataclass
class Registry:
    """All registered components, by kind. Use :data:`uevavd.registry` (lazy, loaded once)."""

    entries: dict[str, dict[str, Entry]] = field(default_factory=lambda: {k: {} for k in KINDS})
    #: third-party plugins that failed to load (skipped): a missing component may be theirs
    failed: list[str] = field(default_factory=list)

    def add_entry(self, entry: Entry) -> None:
        """Add one component; a name its kind already has, or an unknown kind, is refused."""
        if entry.kind not in KINDS:
            raise PluginError(f"unknown component kind {entry.kind!r}: expected one of {list(KINDS)}")
        if not isinstance(entry.name, str) or not entry.name.strip():
            raise PluginError(f"plugin {entry.plugin!r} registered a {entry.kind} with an empty name")
        if not isinstance(entry.target, str) or (entry.kind != "method" and ":" not in entry.target):
            raise PluginError(
                f"plugin {entry.plugin!r}: {entry.kind} {entry.name!r} has target {entry.target!r}; "
                "expected a 'module:attr' string naming its builder"
            )
        old = self.entries[entry.kind].get(entry.name)
        if old is not None:
            raise DuplicateComponentError(
                f"{entry.kind} {entry.name!r} is registered twice: by plugin {old.plugin!r} "
                f"({old.target}) and by plugin {entry.plugin!r} ({entry.target}); rename one of them "
                "or block a plugin with UEVAVD_DISABLED_PLUGINS"
            )
        self.entries[entry.kind][entry.name] = entry

    def names(self, kind: str) -> list[str]:
        """The sorted names of every registered component of ``kind``."""
        self._check_kind(kind)
        return sorted(self.entries[kind])

    def in_order(self, kind: str) -> list[Entry]:
        """The entries of ``kind`` in registration order (built-ins first, then plugins)."""
        self._check_kind(kind)
        return list(self.entries[kind].values())

    def get(self, kind: str, name: str) -> Entry:
        """The :class:`Entry` of component ``name`` of ``kind`` (UnknownComponentError, with the
        names there are, if none)."""
        self._check_kind(kind)
        try:
            return self.entries[kind][name]
        except KeyError:
            known = sorted(self.entries[kind])
            near = difflib.get_close_matches(str(name), known, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            if self.failed:
                hint += (f"; plugin{'s' if len(self.failed) > 1 else ''} {', '.join(map(repr, self.failed))} failed to "
                         f"load and registered nothing (`uevavd plugins --all` shows why): {name!r} may be theirs")
            raise UnknownComponentError(
                f"unknown {kind} {name!r}: registered {kind}s are {known}{hint} "
                "(see `uevavd plugins`)"
            ) from None

    def builder(self, kind: str, name: str) -> Callable[..., Any]:
        """The component's builder, imported now from its "module:attr" target."""
        return self.get(kind, name).load()

    def build(self, kind: str, name: str, /, **kwargs: Any) -> Any:
        """Build component ``name`` of ``kind`` with keyword arguments."""
        builder = self.builder(kind, name)
        return builder(**kwargs)

    def signature(self, kind: str, name: str) -> inspect.Signature:
        """The builder's signature: the keyword arguments a method config section may set."""
        return inspect.signature(self.builder(kind, name))

    def _check_kind(self, kind: str) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown component kind {kind!r}: expected one of {list(KINDS)}")


class KindRegistry:
    """What a hook receives: ``registry.add(name, "module:attr", summary=...)``.

    Bound to one kind and one plugin; entries are staged and committed only when the
    whole plugin loaded, so a failing plugin leaves nothing half-registered.
    """

    def __init__(self, kind: str, plugin: str, plugin_version: str, staged: list[Entry]):
        self.kind = kind
        self._plugin = plugin
        self._version = plugin_version
        self._staged = staged

    def add(self, name: str, target: str, *, summary: str = "", tags: tuple[str, ...] = (), label: str = "") -> None:
        """Register component ``name`` built by ``target`` ("module:attr"); ``tags``: traits
        the host reads without building it (see the kind's hook); ``label``: its display
        name in reports (methods and baselines; an ablation records it when it runs)."""
        self._staged.append(
            Entry(self.kind, name, target, summary, self._plugin, self._version, tuple(tags), str(label))
        )

    def __repr__(self) -> str:
        return f"<KindRegistry {self.kind} for plugin {self._plugin!r}>"

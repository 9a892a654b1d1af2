"""Method configs: TOML files that name registry entries and their arguments.

A method file (``model_zoo/methods/*.toml``) looks like::

    name = "memo_map"
    description = "Memo-MAP: MAP with a GRU over the observation history"
    _base_ = "map"                      # inherit another method; change only what differs

    [perception]
    segmenter = { name = "none" }       # component sections: `name` picks a registry entry,
    encoder = { name = "resnet50", weights = "imagenet" }   # other keys are its builder's
    classifier = { name = "resnet18" }                      # keyword arguments
    decompose = false

    [state]
    name = "gru"

    [head]
    name = "dueling_branch"

    [env]       # checked against uevavd.env.config:EnvConfig's fields
    [train]     # checked against uevavd.policy.config:TrainConfig's fields

:func:`load_method` resolves inheritance, applies dotted overrides, checks every key and
type against the builders' signatures and the dataclasses' fields, and returns a frozen
:class:`MethodSpec` with a stable hash.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .atomic import atomic_write
from .config_layers import component_of, is_shipped, layer_method, merge_sections
from .config_rules import (
    COMPONENT_SECTIONS,
    DATACLASS_SECTIONS,
    MAX_INHERITANCE,
    PERCEPTION_KEYS,
    TOP_KEYS,
    TOP_SECTIONS,
    ConfigError,
    apply_overrides,
    check_type,
    dotted_get,
    freeze,
    parse_override,
    thaw,
    validate,
)
from .hashing import json_digest

# the registry sits below the specs: it resolves a registered method's file itself, and loads
# plugins only when first asked (importing it is light)
from .plugins.manager import manager
from .plugins.registry import UnknownComponentError, import_target, resolve_method_target


# -- locating method files ------------------------------------------------------------------
def is_method_path(name_or_path: str | os.PathLike[str]) -> bool:
    """Whether a method is given as a TOML path (else it is a registered name)."""
    s = str(name_or_path)
    return s.endswith(".toml") or os.sep in s or "/" in s


def _method_path(name_or_path: str | os.PathLike[str], relative_to: Path | None = None) -> Path:
    s = str(name_or_path)
    if is_method_path(s):
        p = Path(s)
        if not p.is_absolute() and relative_to is not None and (relative_to / p).is_file():
            p = relative_to / p
        if not p.is_file():
            raise ConfigError(f"method file {p} does not exist")
        return p.resolve()
    try:
        entry = manager.registry.get("method", s)
    except UnknownComponentError as exc:
        raise ConfigError(str(exc)) from None
    try:
        path = entry.load()
    except ValueError as exc:  # a registered target that is no path
        raise ConfigError(str(exc)) from None
    if not path.is_file():  # a file left out of the plugin's wheel (package-data)
        raise ConfigError(f"method {s!r} of plugin {entry.plugin!r} names {entry.target}, which is not installed "
                          f"({path} does not exist): list the file in the plugin's package data and reinstall it")
    return path


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def _resolve_chain(path: Path, seen: tuple[Path, ...] = ()) -> list[tuple[Path, dict[str, Any]]]:
    """The files of a method's inheritance chain, the root first: ``[(path, its keys), ...]``
    without ``_base_``, and a base's ``description`` dropped (the child describes itself)."""
    if path in seen:
        chain = " -> ".join(str(p) for p in (*seen, path))
        raise ConfigError(f"method inheritance loops: {chain}")
    if len(seen) > MAX_INHERITANCE:
        raise ConfigError(f"method inheritance deeper than {MAX_INHERITANCE} at {path}")
    data = _read_toml(path)
    base_name = data.pop("_base_", None)
    if base_name is None:
        return [(path, data)]
    if not isinstance(base_name, str):
        raise ConfigError(f"{path}: _base_ must be a method name or path, got {base_name!r}")
    try:
        base_path = _method_path(base_name, path.parent)
    except (ConfigError, FileNotFoundError) as exc:  # name the file that holds the _base_
        raise ConfigError(f"{path}: _base_ = {base_name!r}: {exc}") from None
    base = _resolve_chain(base_path, (*seen, path))
    base[-1][1].pop("description", None)
    return [*base, (path, data)]


def method_chain(name_or_path: str | os.PathLike[str]) -> list[Path]:
    """The files of a method's inheritance chain, the root first (``ibe_map``: map.toml,
    memo_map.toml, ibe_map.toml)."""
    return [p for p, _ in _resolve_chain(_method_path(name_or_path))]


def resolve_method_file(path: Path) -> dict[str, Any]:
    """A method file with its inheritance resolved, as one nested dict."""
    data: dict[str, Any] = {}
    for _, keys in _resolve_chain(path):
        data = merge_sections(data, keys)
    return data


# -- the spec -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Component:
    """A component section: the registry ``kind``, the registered ``name`` and the builder's
    keyword arguments from the method file."""

    kind: str
    name: str
    kwargs: Mapping[str, Any]

    def build(self, **runtime: Any) -> Any:
        """The component, built with its config arguments plus ``runtime`` ones."""
        return manager.registry.build(self.kind, self.name, **{**thaw(self.kwargs), **runtime})

    def accepts(self, argument: str) -> bool:
        """Whether the builder takes keyword ``argument``: a runtime value a host may offer
        (the dataset folder, a recognizer's path) is passed only to builders that name it,
        as pluggy passes a hook implementation only the arguments it names."""
        return argument in manager.registry.signature(self.kind, self.name).parameters


@dataclasses.dataclass(frozen=True)
class PerceptionSection:
    """``[perception]``: the components that make a table, and the decomposition settings.
    ``raw`` is the section as written (what tables record and what their keys hash)."""

    segmenter: Component | None
    encoder: Component | None
    classifier: Component | None
    decompose: bool
    gray_seed: int
    raw: Mapping[str, Any]

    @property
    def recognizer_in_state(self) -> bool:
        """The table's features end with the recognizer's class probabilities on the raw view
        (the paper's state has the image features and the box only)."""
        return bool(self.raw.get("recognizer_in_state", False))

    def as_dict(self) -> dict[str, Any]:
        """The section as written, a plain dict (what tables record and their keys hash)."""
        return thaw(self.raw)


def _section_class(section: str) -> Any:
    return import_target(DATACLASS_SECTIONS[section])


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A resolved, validated, immutable method config."""

    name: str
    data: Mapping[str, Any]  #: read-only nested mapping (no `_base_`)
    source: str  #: file it came from
    #: the preset's [overrides] keys not applied, each with the reason (:func:`layer_method`)
    preset_notes: tuple[str, ...] = dataclasses.field(default=(), compare=False)

    @property
    def hash(self) -> str:
        """Stable 16-hex digest of the resolved config (independent of key order and source)."""
        return json_digest(self.to_dict(), 16, compact=True)

    def to_dict(self) -> dict[str, Any]:
        """The spec as plain nested dicts and lists (a copy: editing it changes nothing here)."""
        return thaw(self.data)

    def with_overrides(self, overrides: Mapping[str, Any] | None, *,
                       preset: Mapping[str, Any] | None = None) -> MethodSpec:
        """This spec with a preset's ``[overrides]`` and then dotted ``overrides`` applied
        (each order-independent, see :func:`apply_overrides`) and validated; itself when there
        are none. A resolved spec is one layer: the preset applies to all of it."""
        if not overrides and not preset:
            return self
        data = apply_overrides(self.to_dict(), preset)
        apply_overrides(data, overrides)
        validate(data, _with_overrides(self.source, {**(preset or {}), **(overrides or {})}))
        return MethodSpec(name=data["name"], data=freeze(data), source=self.source)

    def get(self, dotted: str, default: Any = None) -> Any:
        """The value of a dotted key (``"train.lr"``), or ``default`` where the spec has none."""
        value = dotted_get(self.data, dotted)
        return default if value is None else value

    def __getitem__(self, dotted: str) -> Any:
        value = dotted_get(self.data, dotted)
        if value is None:
            raise KeyError(f"method {self.name!r} has no key {dotted!r}")
        return value

    # -- typed sections: what the consumers read (one decoding of the dict, here) -------------
    @property
    def env(self) -> Any:  # EnvConfig, from the env layer above: named by string, never imported
        """``[env]`` as an :class:`~uevavd.env.config.EnvConfig` (the paper's values where unset)."""
        return _section_class("env")().replace(**thaw(self.data.get("env", {})))

    def train_config(self, **runtime: Any) -> Any:  # TrainConfig, from the policy layer above
        """``[train]`` as a :class:`~uevavd.policy.config.TrainConfig`, with the ``runtime``
        values a run adds (``seed``, ``episodes``) over the file's."""
        return _section_class("train").from_dict({**thaw(self.data.get("train", {})), **runtime})

    @property
    def perception(self) -> PerceptionSection:
        raw = thaw(self.data.get("perception", {}))

        def comp(section: str) -> Component | None:
            return self.section(section) if dotted_get(self.data, section) is not None else None

        return PerceptionSection(segmenter=comp("perception.segmenter"), encoder=comp("perception.encoder"),
                                 classifier=comp("perception.classifier"), decompose=bool(raw.get("decompose", False)),
                                 gray_seed=int(raw.get("gray_seed", 0)), raw=freeze(raw))

    @property
    def state(self) -> Component:
        return self.section("state")

    @property
    def head(self) -> Component:
        return self.section("head")

    def section(self, section: str) -> Component:
        """A component section (``"state"``, ``"perception.encoder"``, ...) as a :class:`Component`."""
        name, kwargs = self.component(section)
        return Component(COMPONENT_SECTIONS[section], name, freeze(kwargs))

    def component(self, section: str) -> tuple[str, dict[str, Any]]:
        """``(registry name, builder kwargs)`` of a component section, e.g. ``"state"``."""
        if section not in COMPONENT_SECTIONS:
            raise KeyError(f"{section!r} is not a component section: expected one of {list(COMPONENT_SECTIONS)}")
        value = thaw(dotted_get(self.data, section) or {})
        if "name" not in value:
            raise KeyError(f"method {self.name!r} names no {section}")
        name = value.pop("name")
        return name, value

    def build(self, section: str, /, **runtime: Any) -> Any:
        """Build a component section with its config arguments plus ``runtime`` ones."""
        name, kwargs = self.component(section)
        return manager.registry.build(COMPONENT_SECTIONS[section], name, **{**kwargs, **runtime})

    def to_toml(self) -> str:
        """The spec as a method TOML (what ``uevavd train`` writes to a run's method.toml)."""
        import tomli_w

        return f"# uevavd method spec, hash {self.hash}\n" + tomli_w.dumps(self.to_dict())

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the resolved spec as TOML (atomically); :func:`load_method` reads it back."""
        return atomic_write(path, self.to_toml())


def load_method(
    name_or_path: str | os.PathLike[str],
    overrides: Mapping[str, Any] | None = None,
    *,
    preset: Mapping[str, Any] | None = None,
) -> MethodSpec:
    """Load, resolve and validate a method config.

    ``name_or_path`` is a registered method name (``"ibe_map"``) or a TOML path.
    ``overrides`` maps dotted keys to values, e.g. ``{"state.name": "single_view"}``: what you
    name explicitly, which wins over everything. ``preset`` is a preset's ``[overrides]``
    (:func:`uevavd.presets.preset_overrides`), applied by the precedence rule of
    :func:`layer_method`: it scales uevavd's shipped methods, and never replaces what your own
    method file sets (``spec.preset_notes`` lists the preset keys not applied).
    Unknown keys or wrong types raise :class:`ConfigError`, listing the accepted keys.
    """
    path = _method_path(name_or_path)
    data, notes = layer_method(_resolve_chain(path), preset, overrides)
    both = {**(preset or {}), **(overrides or {})}
    source = _with_overrides(path, both) if both else str(path)
    validate(data, source)
    return MethodSpec(name=data["name"], data=freeze(data), source=str(path), preset_notes=tuple(notes))


def _with_overrides(source: Any, overrides: Mapping[str, Any]) -> str:
    """Where a config error's value comes from: the method file and how many overrides (the key at
    fault is named by the error itself; the whole dict made the line ~1,500 characters long)."""
    return f"{source} with {len(overrides)} override{'s' if len(overrides) != 1 else ''}"


def as_method(spec_or_method: MethodSpec | str | os.PathLike[str],
              overrides: Mapping[str, Any] | None = None, *,
              preset: Mapping[str, Any] | None = None) -> MethodSpec:
    """A :class:`MethodSpec` from a spec, a registered method name or a TOML path, with a
    preset's ``[overrides]`` and dotted ``overrides`` applied by the precedence rule of
    :func:`layer_method` and validated: what an entry point that takes "a method" resolves
    once, before handing its consumers the sections they need."""
    if isinstance(spec_or_method, MethodSpec):
        return spec_or_method.with_overrides(overrides, preset=preset)
    return load_method(spec_or_method, overrides, preset=preset)


def loads_method(text: str, source: str = "<string>") -> MethodSpec:
    """A resolved method spec from TOML text (what :meth:`MethodSpec.to_toml` writes, e.g.
    the ``method.toml`` inside a saved policy); validated like a method file."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML ({exc})") from None
    if "_base_" in data:
        raise ConfigError(f"{source}: a resolved method has no _base_; load a method file with load_method")
    validate(data, source)
    return MethodSpec(name=data["name"], data=freeze(data), source=source)


def known_methods() -> list[str]:
    return manager.registry.names("method")


__all__ = [
    "COMPONENT_SECTIONS", "DATACLASS_SECTIONS", "component_of", "is_method_path", "is_shipped", "layer_method", "method_chain", "resolve_method_file", "PERCEPTION_KEYS", "TOP_KEYS", "TOP_SECTIONS", "Component", "ConfigError",
    "MethodSpec", "PerceptionSection", "apply_overrides", "as_method", "check_type", "known_methods", "load_method", "loads_method",
    "parse_override", "resolve_method_target", "validate",
]

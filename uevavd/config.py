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

import copy
import dataclasses
import difflib
import hashlib
import inspect
import json
import os
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Sections whose `name` picks a registry entry of a kind; other keys go to its builder.
COMPONENT_SECTIONS: dict[str, str] = {
    "perception.segmenter": "segmenter",
    "perception.encoder": "encoder",
    "perception.classifier": "classifier",
    "state": "state",
    "head": "head",
}
#: Sections checked against a dataclass's fields ("module:attr", imported when checked).
DATACLASS_SECTIONS: dict[str, str] = {
    "env": "uevavd.env.config:EnvConfig",
    "train": "uevavd.policy.config:TrainConfig",
}
#: Plain keys of the perception section besides its component sections.
PERCEPTION_KEYS: dict[str, Any] = {"decompose": bool, "gray_seed": int}
TOP_KEYS: dict[str, Any] = {"name": str, "description": str, "_base_": str}
TOP_SECTIONS = ("perception", "state", "head", "env", "train")
MAX_INHERITANCE = 16


class ConfigError(ValueError):
    """A method config is invalid; the message names the file, the key and what is accepted."""


# -- locating method files ------------------------------------------------------------------
def resolve_method_target(target: str) -> Path:
    """A registered method's TOML path: absolute path, or ``"package:relative/path.toml"``."""
    p = Path(target)
    if p.is_absolute():
        return p
    package, sep, rel = target.partition(":")
    if not sep:
        raise ConfigError(f"method target {target!r}: expected an absolute path or 'package:path.toml'")
    import importlib.resources

    return Path(str(importlib.resources.files(package).joinpath(rel)))


def _method_path(name_or_path: str | os.PathLike[str], relative_to: Path | None = None) -> Path:
    s = str(name_or_path)
    if s.endswith(".toml") or os.sep in s or "/" in s:
        p = Path(s)
        if not p.is_absolute() and relative_to is not None and (relative_to / p).is_file():
            p = relative_to / p
        if not p.is_file():
            raise ConfigError(f"method file {p} does not exist")
        return p.resolve()
    from .plugins.manager import manager
    from .plugins.registry import UnknownComponentError

    try:
        return manager.registry.get("method", s).load()
    except UnknownComponentError as exc:
        raise ConfigError(str(exc)) from None


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def _merge(base: dict[str, Any], child: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in child.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            # A component section that picks another `name` starts from scratch: the base's
            # arguments belong to the base's builder.
            if "name" in v and out[k].get("name") not in (None, v["name"]):
                out[k] = copy.deepcopy(dict(v))
            else:
                out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _resolve_file(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    if path in seen:
        chain = " -> ".join(str(p) for p in (*seen, path))
        raise ConfigError(f"method inheritance loops: {chain}")
    if len(seen) > MAX_INHERITANCE:
        raise ConfigError(f"method inheritance deeper than {MAX_INHERITANCE} at {path}")
    data = _read_toml(path)
    base_name = data.pop("_base_", None)
    if base_name is None:
        return data
    if not isinstance(base_name, str):
        raise ConfigError(f"{path}: _base_ must be a method name or path, got {base_name!r}")
    base = _resolve_file(_method_path(base_name, path.parent), (*seen, path))
    base.pop("description", None)
    return _merge(base, data)


# -- overrides ------------------------------------------------------------------------------
def parse_override(text: str) -> tuple[str, Any]:
    """``"head.hidden=256"`` -> ``("head.hidden", 256)``; values are TOML, else strings."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"override {text!r}: expected KEY=VALUE, e.g. state.name=gru")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return key.strip(), value


def apply_overrides(data: dict[str, Any], overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """Apply dotted ``overrides`` to the nested dict ``data`` in place, order-independently:
    a component switch (``section.name`` to another name) first drops the old builder's
    arguments, so every switch is applied before the other keys, shallow sections first
    (``{"perception.encoder.weights": w, "perception.encoder.name": n}`` keeps ``w`` in either
    order). Returns ``data``."""
    items = list((overrides or {}).items())
    items.sort(key=lambda kv: (not kv[0].endswith(".name") and kv[0] != "name", kv[0].count(".")))
    for key, value in items:
        _apply_override(data, key, value)
    return data


def _apply_override(data: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    node = data
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part)
        if nxt is None:
            nxt = node[part] = {}
        if not isinstance(nxt, dict):
            raise ConfigError(f"override {key!r}: {'.'.join(parts[: i + 1])} is a value, not a section")
        node = nxt
    last = parts[-1]
    if last == "name" and isinstance(node.get("name"), str) and node["name"] != value:
        # Switching component: drop arguments meant for the old builder.
        for k in [k for k in node if k != "name"]:
            del node[k]
    node[last] = value


# -- validation -----------------------------------------------------------------------------
def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def check_type(value: Any, tp: Any) -> bool:
    """Whether a TOML value fits an annotation (int, float, bool, str, Literal, unions,
    list/tuple/dict of those). Unknown or ``Any`` annotations accept anything."""
    if tp is Any or tp is inspect.Parameter.empty or tp is None and value is None:
        return True
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return any(check_type(value, a) for a in args)
    if origin is typing.Literal:
        return value in args
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if tp is str:
        return isinstance(value, str)
    if origin in (list, tuple, typing.Sequence) or tp in (list, tuple):
        if not isinstance(value, list | tuple):
            return False
        if not args or (origin is tuple and len(args) == 2 and args[1] is Ellipsis):
            inner = args[0] if args else Any
            return all(check_type(v, inner) for v in value)
        if origin is tuple:
            return len(args) == len(value) and all(check_type(v, a) for v, a in zip(value, args, strict=True))
        return all(check_type(v, args[0]) for v in value)
    if origin is dict or tp is dict:
        return isinstance(value, dict)
    if isinstance(tp, type):
        return isinstance(value, tp)
    return True


def _suggest(key: str, accepted: list[str]) -> str:
    near = difflib.get_close_matches(key, accepted, n=1)
    return f"; did you mean {near[0]!r}?" if near else ""


def _unknown(where: str, key: str, accepted: list[str], source: str) -> ConfigError:
    return ConfigError(
        f"{source}: unknown key {where + '.' if where else ''}{key!r}; accepted keys are "
        f"{sorted(accepted)}{_suggest(key, accepted)}"
    )


def _check_fields(where: str, values: Mapping[str, Any], fields: Mapping[str, Any], source: str) -> None:
    for key, value in values.items():
        if key not in fields:
            raise _unknown(where, key, list(fields), source)
        if not check_type(value, fields[key]):
            raise ConfigError(
                f"{source}: {where + '.' if where else ''}{key} = {value!r} has the wrong type: "
                f"expected {_type_name(fields[key])}"
            )


def _builder_fields(kind: str, name: str, where: str, source: str) -> dict[str, Any]:
    from .plugins.manager import manager
    from .plugins.registry import UnknownComponentError

    try:
        builder = manager.registry.builder(kind, name)
    except UnknownComponentError as exc:
        raise ConfigError(f"{source}: {where}.name: {exc}") from None
    sig = inspect.signature(builder)
    try:
        hints = typing.get_type_hints(builder)
    except Exception:  # noqa: BLE001 - unresolvable annotations: accept any value
        hints = {}
    return {
        p.name: hints.get(p.name, Any)
        for p in sig.parameters.values()
        if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
    }


def _dataclass_fields(target: str) -> dict[str, Any]:
    from .plugins.registry import import_target

    cls = import_target(target)
    hints = typing.get_type_hints(cls)
    return {f.name: hints.get(f.name, Any) for f in dataclasses.fields(cls)}


#: Builder arguments the pipeline passes itself (a value in a method file would be silently
#: replaced), per section, with where they come from.
RUNTIME_ARGS: dict[str, dict[str, str]] = {
    "state": {"feature_dim": "the table's feature size (D), passed when the network is built"},
}


def validate(data: Mapping[str, Any], source: str = "<method>") -> None:
    """Raise :class:`ConfigError` unless every key and type is accepted."""
    allowed_top = list(TOP_KEYS) + list(TOP_SECTIONS)
    for key, value in data.items():
        if key not in allowed_top:
            raise _unknown("", key, allowed_top, source)
        if key in TOP_KEYS and not check_type(value, TOP_KEYS[key]):
            raise ConfigError(f"{source}: {key} = {value!r}: expected {_type_name(TOP_KEYS[key])}")
        if key in TOP_SECTIONS and not isinstance(value, Mapping):
            raise ConfigError(f"{source}: {key} must be a table ([{key}]), got {value!r}")
    if "name" not in data:
        raise ConfigError(f"{source}: a method needs a `name`")
    perception = data.get("perception", {})
    comp_keys = [s.split(".", 1)[1] for s in COMPONENT_SECTIONS if s.startswith("perception.")]
    for key, value in perception.items():
        if key in comp_keys:
            continue
        if key not in PERCEPTION_KEYS:
            raise _unknown("perception", key, comp_keys + list(PERCEPTION_KEYS), source)
        if not check_type(value, PERCEPTION_KEYS[key]):
            raise ConfigError(f"{source}: perception.{key} = {value!r}: expected {_type_name(PERCEPTION_KEYS[key])}")
    for where, kind in COMPONENT_SECTIONS.items():
        section = _get(data, where)
        if section is None:
            continue
        if not isinstance(section, Mapping) or not isinstance(section.get("name"), str):
            raise ConfigError(f"{source}: {where} needs a `name` naming a registered {kind}")
        fields = _builder_fields(kind, section["name"], where, source)
        args = {k: v for k, v in section.items() if k != "name"}
        for key in RUNTIME_ARGS.get(where, ()):
            if key in args:  # the builder takes it, but the trainer passes it: a config value would be ignored
                raise ConfigError(f"{source}: {where}.{key} = {args[key]!r} is not a setting: it comes from "
                                  f"{RUNTIME_ARGS[where][key]}; remove it")
        _check_fields(where, args, fields, source)
    for where, target in DATACLASS_SECTIONS.items():
        section = data.get(where)
        if section:
            _check_fields(where, section, _dataclass_fields(target), source)


def _get(data: Mapping[str, Any], dotted: str) -> Any:
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def _freeze(value: Any) -> Any:
    if isinstance(value, Mapping):
        return types.MappingProxyType({k: _freeze(v) for k, v in value.items()})
    if isinstance(value, list | tuple):
        return tuple(_freeze(v) for v in value)
    return value


def _thaw(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _thaw(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [_thaw(v) for v in value]
    return value


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
        from .plugins.manager import manager  # lazy: the registry loads plugins on first use

        return manager.registry.build(self.kind, self.name, **{**_thaw(self.kwargs), **runtime})


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

    def as_dict(self) -> dict[str, Any]:
        """The section as written, a plain dict (what tables record and their keys hash)."""
        return _thaw(self.raw)


def _section_class(section: str) -> Any:
    from .plugins.registry import import_target  # lazy, as _dataclass_fields: keeps this module light

    return import_target(DATACLASS_SECTIONS[section])


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A resolved, validated, immutable method config."""

    name: str
    data: Mapping[str, Any]  #: read-only nested mapping (no `_base_`)
    source: str  #: file it came from

    @property
    def hash(self) -> str:
        """Stable 16-hex digest of the resolved config (independent of key order and source)."""
        blob = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"), default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def to_dict(self) -> dict[str, Any]:
        return _thaw(self.data)

    def with_overrides(self, overrides: Mapping[str, Any] | None) -> MethodSpec:
        """This spec with dotted ``overrides`` applied (order-independent, see
        :func:`apply_overrides`) and validated; itself when there are none."""
        if not overrides:
            return self
        data = apply_overrides(self.to_dict(), overrides)
        validate(data, f"{self.source} with overrides {dict(overrides)}")
        return MethodSpec(name=data["name"], data=_freeze(data), source=self.source)

    def get(self, dotted: str, default: Any = None) -> Any:
        value = _get(self.data, dotted)
        return default if value is None else value

    def __getitem__(self, dotted: str) -> Any:
        value = _get(self.data, dotted)
        if value is None:
            raise KeyError(f"method {self.name!r} has no key {dotted!r}")
        return value

    # -- typed sections: what the consumers read (one decoding of the dict, here) -------------
    @property
    def env(self) -> Any:
        """``[env]`` as an :class:`~uevavd.env.config.EnvConfig` (the paper's values where unset)."""
        return _section_class("env")().replace(**_thaw(self.data.get("env", {})))

    def train_config(self, **runtime: Any) -> Any:
        """``[train]`` as a :class:`~uevavd.policy.config.TrainConfig`, with the ``runtime``
        values a run adds (``seed``, ``episodes``) over the file's."""
        return _section_class("train").from_dict({**_thaw(self.data.get("train", {})), **runtime})

    @property
    def perception(self) -> PerceptionSection:
        raw = _thaw(self.data.get("perception", {}))

        def comp(section: str) -> Component | None:
            return self.section(section) if _get(self.data, section) is not None else None

        return PerceptionSection(segmenter=comp("perception.segmenter"), encoder=comp("perception.encoder"),
                                 classifier=comp("perception.classifier"), decompose=bool(raw.get("decompose", False)),
                                 gray_seed=int(raw.get("gray_seed", 0)), raw=_freeze(raw))

    @property
    def state(self) -> Component:
        return self.section("state")

    @property
    def head(self) -> Component:
        return self.section("head")

    def section(self, section: str) -> Component:
        """A component section (``"state"``, ``"perception.encoder"``, ...) as a :class:`Component`."""
        name, kwargs = self.component(section)
        return Component(COMPONENT_SECTIONS[section], name, _freeze(kwargs))

    def component(self, section: str) -> tuple[str, dict[str, Any]]:
        """``(registry name, builder kwargs)`` of a component section, e.g. ``"state"``."""
        if section not in COMPONENT_SECTIONS:
            raise KeyError(f"{section!r} is not a component section: expected one of {list(COMPONENT_SECTIONS)}")
        value = _thaw(_get(self.data, section) or {})
        if "name" not in value:
            raise KeyError(f"method {self.name!r} names no {section}")
        name = value.pop("name")
        return name, value

    def build(self, section: str, /, **runtime: Any) -> Any:
        """Build a component section with its config arguments plus ``runtime`` ones."""
        from .plugins.manager import manager

        name, kwargs = self.component(section)
        return manager.registry.build(COMPONENT_SECTIONS[section], name, **{**kwargs, **runtime})

    def to_toml(self) -> str:
        import tomli_w

        return f"# uevavd method spec, hash {self.hash}\n" + tomli_w.dumps(self.to_dict())

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the resolved spec as TOML (atomically); :func:`load_method` reads it back."""
        from .atomic import atomic_write

        return atomic_write(path, self.to_toml())


def load_method(
    name_or_path: str | os.PathLike[str],
    overrides: Mapping[str, Any] | None = None,
) -> MethodSpec:
    """Load, resolve and validate a method config.

    ``name_or_path`` is a registered method name (``"ibe_map"``) or a TOML path.
    ``overrides`` maps dotted keys to values, e.g. ``{"state.name": "single_view"}``.
    Unknown keys or wrong types raise :class:`ConfigError`, listing the accepted keys.
    """
    path = _method_path(name_or_path)
    data = _resolve_file(path)
    apply_overrides(data, overrides)
    source = str(path) + (f" with overrides {dict(overrides)}" if overrides else "")
    validate(data, source)
    return MethodSpec(name=data["name"], data=_freeze(data), source=str(path))


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
    return MethodSpec(name=data["name"], data=_freeze(data), source=source)


def known_methods() -> list[str]:
    from .plugins.manager import manager

    return manager.registry.names("method")

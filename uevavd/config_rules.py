"""The rules a method config obeys: its sections and keys, dotted overrides, and the
validation of every key and type against the registered builders' signatures and the
dataclasses' fields (:func:`validate`). :mod:`uevavd.config` loads files and builds
:class:`~uevavd.config.MethodSpec` with these."""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import os
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from .plugins.manager import manager
from .plugins.registry import UnknownComponentError, import_target

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
PERCEPTION_KEYS: dict[str, Any] = {"decompose": bool, "gray_seed": int, "recognizer_in_state": bool}
TOP_KEYS: dict[str, Any] = {"name": str, "description": str, "_base_": str}
TOP_SECTIONS = ("perception", "state", "head", "env", "train")
MAX_INHERITANCE = 16


class ConfigError(ValueError):
    """A method config is invalid; the message names the file, the key and what is accepted."""


#: The widest layer a shipped component builds (the paper's widest is 544): a width past it
#: is a typo that would fail as an allocation traceback, or allocate gigabytes, mid-build.
MAX_WIDTH = 8192


def check_count(option: str, value: Any, low: int = 1, high: int | None = None, exc: type = ValueError) -> int:
    """A command-line count (``--workers``, ``--threads``, ``--seeds``) as an int, or ``exc``
    naming the option and the accepted range: one rule for every command's counts, checked
    before any work (a negative thread count was a traceback, 10**9 seeds the kernel's kill)."""
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)
    if not ok:
        want = f"an integer in {low}..{high}" if high is not None else f"at least {low}"
        raise exc(f"{option} {value}: expected {want}")
    return value


def check_file(option: str, value: Any, expected: str) -> None:
    """A command-line file that must exist (``--imagenet``, ``--classifier``, ``--checkpoint``),
    refused before any work with a FileNotFoundError naming the option, the path and what is
    expected there; None (the option left out) passes."""
    if value is not None and not os.path.isfile(value):
        raise FileNotFoundError(f"{option} {value}: no such file; expected {expected}")


def check_widths(section: str, **widths: Any) -> None:
    """Refuse a layer width of a component section (``state``, ``head``) that is not an
    integer in 1..MAX_WIDTH, naming the key: a width of 0 builds a network that trains to
    nothing, a negative or huge one fails inside torch."""
    for key, v in widths.items():
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_WIDTH:
            raise ConfigError(f"{section}.{key} = {v!r}: expected a layer width, an integer in 1..{MAX_WIDTH}")


def check_flag(section: str, key: str, value: Any) -> bool:
    """Refuse a switch of a component section that is not a TOML boolean, naming the key (a
    string "false" would switch it on)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{section}.{key} = {value!r}: expected true or false")
    return value


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
    if typing.get_origin(tp) is typing.Literal:  # the accepted values, not "Literal"
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
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


def did_you_mean(key: str, accepted: Sequence[str]) -> str:
    """``"; did you mean 'x'?"`` naming the accepted word nearest ``key``, or "" when none is near."""
    near = difflib.get_close_matches(key, list(accepted), n=1)
    return f"; did you mean {near[0]!r}?" if near else ""


def _unknown(where: str, key: str, accepted: list[str], source: str) -> ConfigError:
    return ConfigError(
        f"{source}: unknown key {where + '.' if where else ''}{key!r}; accepted keys are "
        f"{sorted(accepted)}{did_you_mean(key, accepted)}"
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
    try:
        builder = manager.registry.builder(kind, name)
        sig = manager.registry.signature(kind, name)
    except UnknownComponentError as exc:
        raise ConfigError(f"{source}: {where}.name: {exc}") from None
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
        section = dotted_get(data, where)
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
    if dotted_get(data, "state.pose") is True and dotted_get(data, "env.pose") is not True:
        # the state reads the observation's pose entry, which only env.pose puts there
        raise ConfigError(f"{source}: state.pose = true reads the observation's pose, which env.pose = true adds: "
                          "set env.pose = true too")


def dotted_get(data: Mapping[str, Any], dotted: str) -> Any:
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def freeze(value: Any) -> Any:
    if isinstance(value, Mapping):
        return types.MappingProxyType({k: freeze(v) for k, v in value.items()})
    if isinstance(value, list | tuple):
        return tuple(freeze(v) for v in value)
    return value


def thaw(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: thaw(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [thaw(v) for v in value]
    return value


"""The axes of an ablation as its command line names them: the methods (registered names or
method files by path) and the swept keys with their values (:func:`parse_sweeps`), and how a
swept value compares with a method's own and names its setting."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..config import is_method_path, known_methods, load_method, parse_override, resolve_method_file
from ..config_rules import thaw
from ..hashing import json_digest

#: The paper's two sweeps, by their short names; any other dotted key of a method (env.*,
#: train.*, state.*, head.*, perception.*) sweeps too.
SWEEPABLE = {"thre": "env.thre", "C": "env.C"}


class AblationError(ValueError):
    """Bad ablation input; the message names the value and what is accepted."""


def resolved_value(spec: Any, key: str) -> Any:
    """The value dotted ``key`` has in a resolved spec: the file's, else EnvConfig's or
    TrainConfig's default for env.* and train.* keys, the perception switches' defaults (None
    for a builder argument left unset); a whole component section as a plain dict."""
    section, _, field_name = key.partition(".")
    if section == "env":
        return getattr(spec.env, field_name, None)
    if section == "train":
        return getattr(spec.train_config(), field_name, None)
    if section == "perception" and field_name in PERCEPTION_DEFAULTS:
        return spec.get(key, PERCEPTION_DEFAULTS[field_name])
    return thaw(spec.get(key))


#: The perception switches' values where a method leaves them unset (PerceptionSection's reading).
PERCEPTION_DEFAULTS = {"decompose": False, "gray_seed": 0, "recognizer_in_state": False}


def same_value(a: Any, b: Any) -> bool:
    """Whether a swept value is the method's own (numbers compared as numbers, sections as dicts)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return float(a) == float(b)
    return thaw(a) == thaw(b)


def value_label(value: Any) -> str:
    """A swept value as the setting names it: ``0.4``, ``true``, ``resnet18``, and a whole
    component section as its name and arguments, ``resnet18(weights=random)``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return f"{value:g}"
    if isinstance(value, Mapping):
        args = ",".join(f"{k}={value_label(v)}" for k, v in value.items() if k != "name")
        return f"{value.get('name', '?')}({args})" if args else str(value.get("name", "?"))
    if isinstance(value, list | tuple):
        return "[" + ",".join(value_label(v) for v in value) + "]"
    return str(value)


def file_digest(path: str | os.PathLike[str]) -> str:
    """The content of a method file with its inheritance resolved (what a resumed or merged
    ablation compares: an edited file, or an edited base, is another method)."""
    return json_digest(resolve_method_file(Path(path)), 16)


def split_values(text: str) -> list[str]:
    """``"a,{x=1,y=2},[1,2]"`` -> ``["a", "{x=1,y=2}", "[1,2]"]``: commas inside braces,
    brackets or quotes belong to the value."""
    parts, depth, quote, cur = [], 0, "", []
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "{[":
            depth += 1
        elif ch in "}]":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    parts.append("".join(cur).strip())
    return [p for p in parts if p]


def parse_sweeps(items: Sequence[str] | None) -> dict[str, list[Any]]:
    """``["thre=0.2,0.4", "env.xi2=0.05,0.2"]`` -> ``{"thre": [0.2, 0.4], "env.xi2": [0.05, 0.2]}``.
    thre and C are numbers; a dotted key's values are read like ``--set`` values (TOML:
    ``train.batch_size=32,128`` gives integers). Keys are checked by :func:`make_plan`."""
    sweeps: dict[str, list[Any]] = {}
    for item in items or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise AblationError(f"--sweep {item!r}: expected KEY=V1,V2,... with KEY thre, C or a method's dotted key "
                                "(e.g. env.xi2, train.lr, perception.encoder.name)")
        raw = split_values(values)
        if key in SWEEPABLE:
            try:
                sweeps[key] = [float(v) for v in raw]
            except ValueError:
                raise AblationError(f"--sweep {item!r}: values must be numbers separated by commas") from None
        else:
            sweeps[key] = [parse_override(f"{key}={v}")[1] for v in raw]
        if not sweeps[key]:
            raise AblationError(f"--sweep {item!r}: no values")
    return sweeps


def method_names(items: Sequence[str], files: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
    """``(names, {name: file})`` of methods given by registered name or by TOML path (a file's
    method is named by its ``name`` key); an unknown name, a missing file or two methods of one
    name is an AblationError."""
    files = dict(files or {})
    known, names = known_methods(), []
    for m in items:
        m = str(m)
        if is_method_path(m):
            path = Path(m).expanduser().resolve()
            try:
                name = load_method(path).name
            except ValueError as exc:  # ConfigError: a missing file, bad TOML, an unknown key
                raise AblationError(str(exc)) from None
            if name in known or files.get(name, str(path)) != str(path):
                where = "a registered method" if name in known else files[name]
                raise AblationError(f"method file {m} is named {name!r}, like {where}: give it its own `name`, "
                                    "which names its rows, runs and report lines")
            files[name] = str(path)
            m = name
        elif m not in known and m not in files:
            raise AblationError(f"unknown method {m!r}: known methods are {known} (see `uevavd plugins`), "
                                "or give a method file by its path (my_method.toml)")
        if m in names:
            raise AblationError(f"method {m!r} is given twice")
        names.append(m)
    return names, files


#: The agents ``--sb3`` accepts, by their row name: SB3 class name.
SB3_AGENTS: dict[str, str] = {"sb3_dqn": "DQN", "sb3_ppo": "PPO"}


def parse_sb3(text: str | None) -> tuple[str, ...]:
    """``"dqn,ppo"`` -> ``("sb3_dqn", "sb3_ppo")``; an unknown name is a ValueError naming the accepted ones."""
    if not text:
        return ()
    names = []
    for part in text.split(","):
        name = f"sb3_{part.strip().lower()}"
        if name not in SB3_AGENTS:
            raise ValueError(f"--sb3 {part.strip()!r}: expected a comma-separated list of "
                             f"{[n.removeprefix('sb3_') for n in SB3_AGENTS]}")
        names.append(name)
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise ValueError("--sb3 needs stable-baselines3: pip install -e \".[sb3]\"") from None
    return tuple(dict.fromkeys(names))

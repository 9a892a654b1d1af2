"""Presets (``model_zoo/presets/*.toml``): named bundles of world, perception and
training settings. ``quick`` runs in minutes on a laptop; ``paper64`` is Table 1's data
scale at 64 px, about an hour on 2 cores; ``paper`` is the paper's full protocol."""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .config_rules import did_you_mean, parse_override
from .data.splits import resolve_split, split_of, subset
from .hashing import json_digest
from .paths import cache_dir

ZOO = Path(__file__).resolve().parent / "model_zoo"


def preset_dir() -> Path:
    return ZOO / "presets"


def known_presets() -> list[str]:
    return sorted(p.stem for p in preset_dir().glob("*.toml"))


def load_preset(name_or_path: str | Path) -> dict[str, Any]:
    """The preset as a plain dict. ``name_or_path`` is a preset name or a TOML path.

    An unknown name is a ``ValueError`` that lists the known presets.
    """
    p = Path(name_or_path)
    if p.suffix != ".toml":
        p = preset_dir() / f"{name_or_path}.toml"
        if not p.is_file():
            raise ValueError(f"unknown preset {name_or_path!r}: known presets are {known_presets()}"
                             f"{did_you_mean(str(name_or_path), known_presets())}")
    elif not p.is_file():
        raise FileNotFoundError(f"preset file {p} does not exist")
    with p.open("rb") as f:
        return tomllib.load(f)


def preset_overrides(preset: Mapping[str, Any]) -> dict[str, Any]:
    """A preset's method overrides: its ``[overrides]`` table of dotted method keys, which
    every method of the preset's runs, tables and models is loaded with."""
    return dict(preset.get("overrides", {}))


#: The ``--preset`` option's help, for every command that loads methods.
PRESET_HELP = ("a preset (quick, paper64, paper) or its TOML path: the method is loaded with its [overrides] (encoder, "
               "recognizer, network sizes, schedule), as `uevavd ablate --preset` does; what your own method file sets, "
               "and --set, win over it")


def cli_layers(preset: str | None, sets: list[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(the preset's [overrides], the --set KEY=VALUE keys)`` of a command: two layers of the
    precedence rule (:func:`uevavd.config_layers.layer_method`), the command line's winning; the
    preset's are empty when ``preset`` is None."""
    return (preset_overrides(load_preset(preset)) if preset else {}), dict(parse_override(s) for s in sets)


def world_root(preset: Mapping[str, Any]) -> Path:
    """Where a preset's synthetic world is cached: ``<cache>/worlds/world-<digest of its [world]
    table>``, keyed by the world's content alone (another seed, size or context count is another
    folder; a renamed or edited copy of a preset with the same world shares it)."""
    return cache_dir() / "worlds" / f"world-{json_digest(preset['world'], 12)}"


def world_contexts(preset: Mapping[str, Any], split: str | None = None) -> list[int]:
    """The context ids of a preset's world (``[world] per_block``), only those of ``split``
    (a split name or alias such as "test") when given."""
    contexts = list(subset(preset["world"]["per_block"]))
    if split is None:
        return contexts
    wanted = set(resolve_split(split))
    return [c for c in contexts if split_of(c) in wanted]

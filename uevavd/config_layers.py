"""The precedence rule of a method's keys (:func:`layer_method`): uevavd's shipped method files,
then a preset's ``[overrides]``, then the method's own files, then the command line, and how a
component switched by one layer drops the arguments the layers below gave it."""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .config_rules import COMPONENT_SECTIONS, apply_overrides, dotted_get
from .plugins.manager import manager
from .plugins.methods import METHODS_DIR
from .plugins.registry import UnknownComponentError


def merge_sections(base: dict[str, Any], child: Mapping[str, Any]) -> dict[str, Any]:
    """``child`` over ``base``, section by section (a method file over its ``_base_``)."""
    out = copy.deepcopy(base)
    for k, v in child.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            # A component section that picks another `name` starts from scratch: the base's
            # arguments belong to the base's builder.
            if "name" in v and out[k].get("name") not in (None, v["name"]):
                out[k] = copy.deepcopy(dict(v))
            else:
                out[k] = merge_sections(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out



# -- precedence: shipped methods < a preset's [overrides] < your method files < the command line


def is_shipped(path: str | os.PathLike[str]) -> bool:
    """Whether a method file is one of uevavd's own (``model_zoo/methods``): the paper's
    methods and their variants, whose components a preset may substitute."""
    return Path(path).resolve().parent == METHODS_DIR.resolve()


def component_of(key: str) -> str | None:
    """The component section a dotted key belongs to (``"perception.encoder.weights"`` ->
    ``"perception.encoder"``; ``"state"`` -> ``"state"``), None for other keys (``train.lr``)."""
    for section in sorted(COMPONENT_SECTIONS, key=len, reverse=True):
        if key == section or key.startswith(section + "."):
            return section
    return None


def _names(data: Mapping[str, Any], section: str) -> bool:
    value = dotted_get(data, section)
    return isinstance(value, Mapping) and "name" in value


def preset_switches(preset: Mapping[str, Any]) -> set[str]:
    """The component sections a preset's [overrides] switch (``S.name``, or ``S`` whole)."""
    return {s for s in COMPONENT_SECTIONS if f"{s}.name" in preset or isinstance(preset.get(s), Mapping)}


def layer_method(chain: list[tuple[Path, dict[str, Any]]], preset: Mapping[str, Any] | None,
                 explicit: Mapping[str, Any] | None) -> tuple[dict[str, Any], list[str]]:
    """The method's keys resolved by the precedence rule, and a note per preset key not applied.

    Later layers win: (1) uevavd's shipped method files, (2) the preset's ``[overrides]``,
    (3) the method's own files (any file outside uevavd's ``model_zoo/methods``: yours or a
    plugin's), only the keys they set, (4) the command line (``--set``, ``--sweep``,
    ``--episodes``). A preset substitutes components (the paper's ResNet50 by EfficientNet-Lite0)
    only where a shipped file chose them: where your file names a component the preset also
    switches, the preset's keys of that section are not applied, and a key your file sets keeps
    your value. A layer that switches a component (another ``S.name``, or ``S`` whole) drops the
    lower layers' arguments of that section; the preset's keys of sections it does not switch
    (the network widths) follow the new component where its builder takes them."""
    shipped: dict[str, Any] = {}
    own = []
    for path, keys in chain:
        if is_shipped(path) and not own:
            shipped = merge_sections(shipped, keys)
        else:
            own.append(keys)
    data, notes = shipped, []
    pre = dict(preset or {})
    switched = preset_switches(pre)
    for key in list(pre):
        section = component_of(key)
        if section in switched and any(_names(o, section) for o in own):
            notes.append(f"{key} = {pre.pop(key)!r} (the method file names its own {section})")
        elif any(dotted_get(o, key) is not None for o in own):
            notes.append(f"{key} = {pre.pop(key)!r} (the method file sets {key})")
    apply_overrides(data, pre)
    for keys in own:
        data = merge_sections(data, keys)
    _follow(data, pre, switched)
    if explicit:
        apply_overrides(data, explicit)
        _follow(data, pre, switched)
    return data, notes


def _follow(data: dict[str, Any], preset: Mapping[str, Any], switched: set[str]) -> None:
    """Put back the preset's keys of a component section it does not switch itself (``state.input_dim``)
    where a later layer switched that section's component, if the new builder takes them."""
    for key, value in preset.items():
        section = component_of(key)
        if section is None or section in switched or key == section or dotted_get(data, key) is not None:
            continue
        comp = dotted_get(data, section)
        if not isinstance(comp, Mapping) or not isinstance(comp.get("name"), str):
            continue
        try:
            takes = key.rsplit(".", 1)[1] in manager.registry.signature(COMPONENT_SECTIONS[section],
                                                                        comp["name"]).parameters
        except UnknownComponentError:
            continue  # validate() names the unknown component
        if takes:
            apply_overrides(data, {key: value})

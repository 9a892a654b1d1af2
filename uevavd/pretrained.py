"""The model zoo's policies evaluated as a user asks: ``uevavd evaluate --pretrained METHOD``.

Above the zoo's store (:mod:`uevavd.zoo`: files, manifest, checks): it generates the contexts a
split needs, builds their table with the shipped recognizer, and evaluates the shipped policy
beside the baselines, next to the numbers the zoo published (which this same code computed
when the zoo was built, :mod:`uevavd.experiments.zoo_build`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .config import loads_method
from .data.splits import resolve_split, scene_name
from .data.synthetic import write_world
from .env.baselines import evaluate_beside_baselines
from .perception.prepare import prepare_table
from .policy.acting import load_policy_file
from .policy.checkpoint import read_policy_file
from .presets import load_preset, world_contexts, world_root
from .table import ObservationTable
from .zoo import Zoo, ZooError


def world_of_contexts(preset: Mapping[str, Any], contexts: Sequence[int], label: str, *, workers: int,
              progress: bool) -> Path:
    """A dataset root holding ``contexts`` of the preset's world: the full world when the
    cache holds them already, else just those contexts (no ``00``/``train_605``: the
    recognizer ships) under ``<world root>-<label>``."""

    full = world_root(preset)
    try:
        card = json.loads((full / "uevavd.json").read_text(encoding="utf-8"))
        if {scene_name(c) for c in contexts} <= set(card.get("scenes", [])):
            return full
    except (OSError, ValueError):
        pass
    world = preset["world"]
    return write_world(full.with_name(f"{full.name}-{label}"), contexts=contexts, size=int(world["size"]),
                       seed=int(world["seed"]), workers=workers, include_unoccluded=False, progress=progress)


def evaluate_pretrained(method: str, split: str = "hard", *, preset: str = "quick", workers: int = 2,
                        device: str = "cpu", baselines: bool = True, progress: bool = True,
                        contexts: Sequence[int] | None = None, zoo: Zoo | None = None):
    """Evaluate the zoo's ``method`` policy on ``split`` of the preset's world (or on some
    of its ``contexts``), beside the baselines: ``(DataFrame, published, per_context)``:
    one row per policy; the numbers recorded when the zoo was built, for the same contexts
    (None for a split it was not evaluated on); and the policy's per-context rows."""

    resolve_split(split)  # an unknown split is refused before any work
    zoo = zoo or Zoo.load(preset)
    cfg_preset = load_preset(zoo.manifest["preset"])
    zoo.check(cfg_preset)
    path = zoo.policy(method)
    recognizer = zoo.recognizer()
    in_split = world_contexts(cfg_preset, split)
    label = "+".join(resolve_split(split))
    if contexts is not None:
        outside = sorted(set(contexts) - set(in_split))
        if outside or not contexts:
            raise ZooError(f"contexts {outside or list(contexts)}: expected some of the {split} contexts of the "
                           f"{zoo.manifest['preset']} world, {in_split}")
        in_split, label = sorted(set(contexts)), "-".join(str(c) for c in sorted(set(contexts)))
    spec = loads_method(read_policy_file(path)[0], source=str(path))
    data = world_of_contexts(cfg_preset, in_split, label, workers=workers, progress=progress)
    table = ObservationTable.load(prepare_table(data, spec, classifier_path=recognizer, workers=workers,
                                                progress=progress))
    policy, cfg = load_policy_file(path, table=table, method=method, device=device)
    frame, per_context = evaluate_beside_baselines(table, split, policy, method, cfg, device=device,
                                                   baselines=baselines, contexts=None if contexts is None else in_split)
    return frame, zoo.published(method, split, None if contexts is None else in_split), per_context

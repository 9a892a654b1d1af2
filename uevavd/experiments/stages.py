"""The ablation's build stages, each reusing what exists: the world (cached by its
settings), the recognizers (cached by the train_605 images and the recipe, or taken from the
model zoo), the observation tables (cached by the hash of everything that made them)."""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path

from ..atomic import atomic_write, folder_lock
from ..data.reader import read_dataset
from ..data.splits import VALIDATION, resolve_split, split_of
from ..data.synthetic import write_world
from ..data.synthetic.quality import format_rows, read_visible, split_rows
from ..hashing import json_digest
from ..perception.classifier import classifier_cache_path, data_hash, train_records
from ..perception.prepare import prepare_table
from ..perception.prepare_ray import prepare_table_ray
from ..perception.training.classifier import ClassifierRecipe, train_classifier
from ..presets import world_contexts, world_root
from ..zoo import Zoo
from .plan import AblationError, Plan


class Stage:
    def __init__(self, plan: Plan, name: str, log):
        self.plan, self.name, self.log = plan, name, log

    def __enter__(self):
        self.t0 = time.perf_counter()
        self.log(f"[{self.name}] ...")
        return self

    def __exit__(self, *exc):
        dt = time.perf_counter() - self.t0
        self.plan.stages[self.name] = self.plan.stages.get(self.name, 0.0) + dt
        if exc[0] is None:
            self.log(f"[{self.name}] done in {dt:.1f} s")


def stage_world(plan: Plan, log) -> Path:
    """The dataset root: ``--data`` as given, else the preset's synthetic world (cached)."""
    if plan.data is not None:
        _check_splits(plan, read_dataset(plan.data))  # fails early, naming the files it cannot parse
        return plan.data

    world = plan.preset["world"]
    root = world_root(plan.preset)
    write_world(root, contexts=world_contexts(plan.preset), size=int(world["size"]), seed=int(world["seed"]),
                workers=plan.workers, progress=True)

    log("  visibility per split:\n" + format_rows(split_rows(read_visible(root))))
    return root


def _check_splits(plan: Plan, manifest) -> None:
    """``--data`` must hold every split the runs train or evaluate on (a root without simple
    contexts failed only after the recognizer and the tables were made)."""
    needed = {"train"}
    for m in plan.methods:
        for split in plan.spec(m).train_config().eval_splits:
            needed.update(("train",) if split == VALIDATION else resolve_split(split))
    have = {split_of(c) for c in manifest.contexts()}
    missing = sorted(needed - have)
    if missing:
        raise AblationError(f"--data {plan.data} holds no contexts of split(s) {missing}, which the runs train or "
                            f"are evaluated on (it holds {sorted(have) or 'none'}): use a root holding them, or a "
                            "preset whose train.eval_splits leaves them out")


def stage_classifier(plan: Plan, data: Path, log) -> dict[int, Path]:
    """The recognizers, one per recognizer seed (``ClassifierRecipe.seed``: its initialisation of
    the head, held-out viewpoints and augmentation), each cached by (hash of the dataset's
    train_605 images, training settings): a regenerated world under the same path never
    reuses an old classifier."""

    digest = data_hash(train_records(read_dataset(data)))
    out = {}
    for r in plan.recognizers:
        recipe = ClassifierRecipe.from_preset(plan.preset, seed=r)
        path = classifier_cache_path(digest, recipe)
        with ExitStack() as held:
            if not path.is_file():  # one process makes it: another ablation on this cache waits, then reuses it
                held.enter_context(folder_lock(path, RuntimeError, wait=lambda lock, r=r: log(
                    f"  recognizer {r}: another process is making it ({lock}); waiting for it")))
            if path.is_file():
                log(f"  reusing classifier {path}")
            elif (shipped := _zoo_recognizer(plan, path.name)) is not None:
                atomic_write(path, shipped.read_bytes())
                log(f"  recognizer {r}: the model zoo's ({shipped}, sha256 checked), trained by this preset's recipe "
                    "on these train_605 images (--no-zoo trains it here)")
            else:
                train_classifier(data, path, settings=recipe, workers=plan.workers, progress=True, device=plan.device)
        out[r] = path
    return out


def _zoo_recognizer(plan: Plan, cache_name: str) -> Path | None:
    """The zoo's recognizer when the plan allows it and it has this cache name."""
    if not plan.use_zoo:
        return None
    zoo = Zoo.find(str(plan.preset.get("name", "")))
    return None if zoo is None else zoo.recognizer_for(cache_name)

def stage_tables(plan: Plan, data: Path, classifiers: dict[int, Path], log) -> dict[int, dict]:
    """``{recognizer: {method: table, (method, setting): table}}``: per recognizer, one table per
    distinct perception config among the methods and their settings (MAP and Memo-MAP share; a
    swept encoder value builds its own, once). ``tables[r][m]`` is the method's default table."""
    return {r: _tables_of(plan, data, path, log) for r, path in classifiers.items()}


def _tables_of(plan: Plan, data: Path, classifier: Path, log) -> dict:
    tables: dict = {}
    by_perception: dict[str, Path] = {}
    for m in plan.methods:
        for setting_name, setting in plan.settings(m):
            spec = plan.spec(m, setting)
            key = json_digest(spec.perception.as_dict(), 12)
            if key not in by_perception and plan.backend == "ray":
                by_perception[key] = prepare_table_ray(data, spec, classifier_path=classifier, progress=True)
            elif key not in by_perception:
                by_perception[key] = prepare_table(data, spec, classifier_path=classifier, workers=plan.workers,
                                                   progress=True)
            tables[(m, setting_name)] = by_perception[key]
            if setting_name == "default":
                tables[m] = by_perception[key]
                log(f"  {m}: table {tables[m]}")
            elif by_perception[key] != tables[m]:
                log(f"  {m} at {setting_name}: table {by_perception[key]}")
    return tables

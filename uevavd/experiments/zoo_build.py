"""``uevavd zoo build``: retrain the model zoo's files with the preset's own pipeline and
write them with their manifest (see :mod:`uevavd.zoo`)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..atomic import atomic_write, atomic_write_json
from ..data.reader import read_dataset
from ..hashing import file_sha256
from ..paths import cache_dir
from ..perception.classifier import classifier_cache_path, data_hash, train_records
from ..perception.training.classifier import ClassifierRecipe
from ..policy.checkpoint import read_policy_file
from ..policy.rundir import RunDir
from ..presets import world_contexts, world_root
from ..pretrained import evaluate_pretrained
from ..version import __version__
from ..zoo import (
    FORMAT,
    MANIFEST,
    PUBLISHED,
    REBUILD,
    RECOGNIZER,
    Zoo,
    recognizer_settings,
    scene_digest,
    world_identity,
    zoo_dir,
)
from .runner import make_plan, run_ablation


def build_zoo(out: str | os.PathLike[str] | None = None, *, preset: str = "quick", work: str | os.PathLike[str] | None = None,
              workers: int | None = None, log: Callable[[str], None] = print) -> Path:
    """Train the zoo's models with the preset's own pipeline (``uevavd ablate`` with one RL
    seed and one recognizer, the recognizer trained, not taken from the zoo), evaluate each
    policy on every split and write the files and the manifest to ``out`` (default: the
    package's zoo folder). Resumable: the runs live under ``work``."""

    out = Path(out) if out is not None else zoo_dir(preset)
    work = Path(work) if work is not None else cache_dir() / "zoo-build" / preset
    t0 = time.perf_counter()
    plan = make_plan(preset=preset, out=work, seeds=1, recognizers=1, workers=workers, use_zoo=False)
    run_ablation(plan, log=log)
    cfg = plan.preset
    data = world_root(cfg)
    recognizer = classifier_cache_path(data_hash(train_records(read_dataset(data))),
                                       ClassifierRecipe.from_preset(cfg, seed=0))
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, dict[str, Any]] = {}

    def ship(src: Path, name: str) -> None:
        atomic_write(out / name, src.read_bytes())
        files[name] = {"sha256": file_sha256(out / name), "bytes": (out / name).stat().st_size}

    ship(recognizer, RECOGNIZER)
    manifest: dict[str, Any] = {
        "format": FORMAT, "preset": preset, "built_by": REBUILD, "uevavd": __version__,
        "world": {**world_identity(cfg), "scenes": {
            p.parent.name: scene_digest(p) for p in sorted(data.glob("*/scene.json"))}},
        "recognizer": {"file": RECOGNIZER, "cache_name": recognizer.name, "settings": recognizer_settings(cfg, 0)},
        "policies": {},
    }
    for method in plan.methods:
        name = f"{method}.safetensors"
        ship(RunDir(work / "runs" / method / "default" / "rec0" / "seed0").policy, name)
        settings = read_policy_file(out / name)[1]
        manifest["policies"][method] = {"file": name, "seed": settings["seed"], "spec_hash": settings["spec_hash"]}
    staged = Zoo(out, {**manifest, "files": files})
    for method in plan.methods:  # the published numbers: evaluate_pretrained's own code, on every split
        published = {}
        for split in ("train", "simple", "hard"):
            if world_contexts(cfg, split):
                frame, _, per_context = evaluate_pretrained(method, split, preset=preset, workers=plan.workers,
                                                            baselines=False, progress=False, zoo=staged)
                published[split] = {k: float(frame.loc[method, k]) for k in PUBLISHED}
                published[split]["per_context"] = {
                    str(int(row["context"])): {k: float(row[k]) for k in PUBLISHED}
                    for row in per_context.to_dict("records")}
        manifest["policies"][method]["published"] = published
    manifest["files"] = files
    atomic_write_json(out / MANIFEST, manifest, sort_keys=True)
    log(f"zoo: {len(files)} files, {sum(f['bytes'] for f in files.values()) / 1e6:.1f} MB in {out} "
        f"({time.perf_counter() - t0:.0f} s)")
    return out

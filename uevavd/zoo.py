"""The model zoo: trained models that ship with the package, for the quick preset's world.

``model_zoo/pretrained/<preset>/`` holds the recognizer (recognizer seed 0) and one policy
per method (RL seed 0, default reward setting), each trained by the quick preset's own
pipeline, and ``manifest.json``: every file's sha256 and size, the world they belong to
(generator version, the preset's ``[world]`` table, the hashes of its scenes' files), the
recognizer's cache name and settings, each policy's method spec hash, and each policy's
*published* numbers: its exhaustive evaluation on every split, computed by
:func:`uevavd.pretrained.evaluate_pretrained`'s own code when the zoo was built.

- ``uevavd evaluate --pretrained ibe_map --split hard`` (:mod:`uevavd.pretrained`, above this store)
  generates only that split's contexts (no ``train_605``: the recognizer ships), builds
  their table with the shipped recognizer and evaluates the shipped policy beside the
  baselines, next to its published numbers.
- ``uevavd ablate`` and ``uevavd demo`` take the shipped recognizer instead of training it
  when its cache name matches, i.e. the same ``train_605`` image bytes and the same
  training settings (:meth:`Zoo.recognizer_for`); ``--no-zoo`` trains it.
- ``uevavd zoo build`` (:func:`build_zoo`) rebuilds everything after the world, the
  preset or a method changes; ``uevavd zoo check`` (:meth:`Zoo.problems`) says whether the
  shipped files still match, and a test fails when they do not.

Every file is checked against its sha256 before use; a mismatch is refused naming the file.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .config import load_method
from .data.reader import read_dataset
from .data.synthetic import write_world
from .data.synthetic.writer import VERSION
from .hashing import file_sha256, json_digest
from .perception.classifier import (
    classifier_cache_path,
    data_hash,
    file_weights_hash,
    read_classifier_file,
    train_records,
)
from .perception.training.classifier import ClassifierRecipe, train_classifier
from .presets import ZOO, load_preset, preset_overrides

FORMAT = "uevavd-zoo/1"
MANIFEST = "manifest.json"
RECOGNIZER = "recognizer.safetensors"
#: The summary columns a published number is given for (``EvalResult.summary``).
PUBLISHED = ("mean_return", "accuracy", "recognition_rate", "path_m", "stop_rate")
REBUILD = "uevavd zoo build"


class ZooError(ValueError):
    """A zoo file is missing, altered or stale; the message names it and what to do."""


def zoo_dir(preset: str = "quick") -> Path:
    return ZOO / "pretrained" / preset


def world_identity(preset: Mapping[str, Any]) -> dict[str, Any]:
    """What the shipped models depend on in the world: the generator's version and the
    preset's ``[world]`` table (seed, crop size, contexts)."""

    return {"generator_version": VERSION, "world": dict(preset["world"])}


def scene_digest(scene_json: Path) -> str:
    """sha256 over the file hashes a scene's ``scene.json`` records (its images, boxes and
    segmentations), so a renderer change without a version bump is caught too."""
    return json_digest(json.loads(scene_json.read_text(encoding="utf-8"))["files"])


@dataclass(frozen=True)
class Zoo:
    """A zoo folder and its manifest."""

    root: Path
    manifest: dict[str, Any]

    @classmethod
    def load(cls, preset: str = "quick", root: str | os.PathLike[str] | None = None) -> Zoo:
        root = Path(root) if root is not None else zoo_dir(preset)
        path = root / MANIFEST
        try:
            manifest = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ZooError(f"{path}: no model zoo for preset {preset!r} (build one with `{REBUILD}`)") from None
        except (OSError, ValueError) as exc:
            raise ZooError(f"{path}: unreadable zoo manifest ({exc}); restore it from git or run `{REBUILD}`") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
            raise ZooError(f"{path}: format {found!r}, expected {FORMAT!r}; run `{REBUILD}`")
        _check_manifest(path, root, manifest)
        return cls(root, manifest)

    @classmethod
    def find(cls, preset: str) -> Zoo | None:
        """The preset's zoo, or None when the package ships none for it."""
        return cls.load(preset) if (zoo_dir(preset) / MANIFEST).is_file() else None

    @property
    def methods(self) -> list[str]:
        return sorted(self.manifest["policies"])

    def verified(self, name: str) -> Path:
        """The path of zoo file ``name`` after checking it against the manifest's sha256."""
        record = self.manifest["files"].get(name)
        path = self.root / name
        if record is None:
            raise ZooError(f"{path}: not listed in {self.root / MANIFEST}")
        if not path.is_file():
            raise ZooError(f"{path}: missing (git lfs or a partial checkout?); restore it or run `{REBUILD}`")
        digest = file_sha256(path)
        if digest != record["sha256"]:
            raise ZooError(f"{path}: sha256 {digest[:16]}... does not match the manifest's {record['sha256'][:16]}...; "
                           f"the file was altered or damaged: restore it from git or run `{REBUILD}`")
        return path

    def recognizer(self) -> Path:
        return self.verified(RECOGNIZER)

    def policy(self, method: str) -> Path:
        if method not in self.manifest["policies"]:
            raise ZooError(f"no pretrained {method!r} in the zoo: it ships {self.methods}")
        return self.verified(self.manifest["policies"][method]["file"])

    def published(self, method: str, split: str, contexts: Sequence[int] | None = None) -> dict[str, float] | None:
        """The numbers recorded for ``method`` on ``split`` when the zoo was built (with
        ``contexts``: those of one context as recorded, the mean over several)."""
        rec = self.manifest["policies"].get(method, {}).get("published", {}).get(split)
        if rec is None or contexts is None:
            return None if rec is None else {k: rec[k] for k in PUBLISHED}
        rows = [rec["per_context"][str(c)] for c in contexts]
        return {k: rows[0][k] if len(rows) == 1 else sum(r[k] for r in rows) / len(rows) for k in PUBLISHED}

    def recognizer_for(self, cache_name: str) -> Path | None:
        """The shipped recognizer when it is the one the pipeline would train under
        ``cache_name`` (:func:`~uevavd.perception.classifier.classifier_cache_path`'s file
        name: the ``train_605`` images' hash and the training settings), else None."""
        if self.manifest["recognizer"].get("cache_name") != cache_name:
            return None
        return self.recognizer()

    def problems(self, preset: Mapping[str, Any] | None = None) -> list[str]:
        """Why the shipped files no longer match the current world, preset or methods
        (empty when they do): checked without rendering anything."""

        preset = preset or load_preset(self.manifest["preset"])
        out = []
        for name in self.manifest["files"]:  # a damaged file is a problem too (it printed "match")
            try:
                self.verified(name)
            except ZooError as exc:
                out.append(str(exc))
        want = world_identity(preset)
        if self.manifest["world"]["generator_version"] != want["generator_version"]:
            out.append(f"built for world generator version {self.manifest['world']['generator_version']}, "
                       f"the generator is at version {want['generator_version']}")
        if self.manifest["world"]["world"] != want["world"]:
            out.append(f"built for [world] {self.manifest['world']['world']}, the preset has {want['world']}")
        if self.manifest["recognizer"]["settings"] != recognizer_settings(preset, 0):
            out.append("the preset's [classifier] recipe changed since the recognizer was trained")
        for m, rec in self.manifest["policies"].items():
            spec = load_method(m, preset=preset_overrides(preset))
            if spec.hash != rec["spec_hash"]:
                out.append(f"method {m!r} with the preset's overrides now hashes to {spec.hash}, the shipped "
                           f"policy was trained as {rec['spec_hash']}")
        return out

    def rendered_here(self, scenes: Sequence[str] | None = None, *, workers: int = 1,
                      progress: bool = False) -> dict[str, bool]:
        """Render ``scenes`` (default: every scene the manifest records) of the zoo's world on
        this machine, in a temporary folder, and say for each whether its files hash to the
        manifest's record. The world's bytes are numpy's arithmetic, which can differ from
        machine to machine in the last bit (docs/synthetic_world.md, "The same bytes on every
        machine"); where a scene differs, trained numbers may differ in the last digits."""
        records = self.manifest["world"]["scenes"]
        names = list(records) if scenes is None else list(dict.fromkeys(scenes))
        unknown = [n for n in names if n not in records]
        if unknown:
            raise ValueError(f"scene(s) {unknown} are not in the zoo's records; it records {sorted(records)}")
        contexts = [int(n) for n in names if n not in ("00", "train_605")]
        with tempfile.TemporaryDirectory(prefix="uevavd-zoo-render-") as tmp:
            self._write_world(Path(tmp), contexts, include_unoccluded=len(contexts) < len(names), workers=workers,
                              progress=progress)
            return {n: scene_digest(Path(tmp) / n / "scene.json") == records[n] for n in names}

    def recognizer_trained_here(self, *, workers: int = 1, progress: bool = False) -> tuple[str | None, str]:
        """Render the zoo world's ``train_605`` and train the shipped recognizer's recipe on
        it on this machine's CPU (on the recognizer's fixed thread count), in a temporary
        folder: ``(weights hash trained here, the shipped file's)``, the first None when
        ``train_605`` itself renders otherwise here (then training compares nothing). Equal
        hashes: this machine's torch trains the zoo's recognizer weight for weight."""
        rec = self.manifest["recognizer"]
        shipped = file_weights_hash(*read_classifier_file(self.recognizer()))
        recipe = ClassifierRecipe.from_preset({}, **rec["settings"])
        with tempfile.TemporaryDirectory(prefix="uevavd-zoo-recognizer-") as tmp:
            root = self._write_world(Path(tmp) / "world", [], include_unoccluded=True, workers=workers,
                                     progress=progress)
            if classifier_cache_path(data_hash(train_records(read_dataset(root))), recipe).name != rec["cache_name"]:
                return None, shipped  # other train_605 bytes (or another recipe) than the shipped file's
            out = train_classifier(root, Path(tmp) / RECOGNIZER, settings=recipe, workers=workers, progress=progress,
                                   device="cpu")
            return file_weights_hash(*read_classifier_file(out)), shipped

    def _write_world(self, root: Path, contexts: Sequence[int], *, include_unoccluded: bool, workers: int,
                     progress: bool) -> Path:
        """``contexts`` (and ``train_605`` when asked) of the zoo's world, written under ``root``."""
        world = self.manifest["world"]["world"]
        return write_world(root, contexts=contexts, size=int(world["size"]), seed=int(world["seed"]), workers=workers,
                           include_unoccluded=include_unoccluded, progress=progress)

    def check(self, preset: Mapping[str, Any] | None = None) -> None:
        problems = self.problems(preset)
        if problems:
            raise ZooError(f"the model zoo in {self.root} is stale ({'; '.join(problems)}): rebuild it with "
                           f"`{REBUILD}`")


def _check_manifest(path: Path, root: Path, manifest: dict[str, Any]) -> None:
    """Every file the manifest lists lies inside the zoo and has its sha256 and size, and every
    policy names a listed file: a manifest naming ``/etc/hostname`` or ``../x`` was hashed and
    said "match", and a record without ``bytes`` was a KeyError in ``zoo list``."""
    def bad(what: str) -> ZooError:
        return ZooError(f"{path}: {what}; restore the manifest from git or run `{REBUILD}`")

    files, policies = manifest.get("files"), manifest.get("policies", {})
    if not isinstance(files, dict) or not isinstance(policies, dict):
        raise bad("'files' and 'policies' must be tables")
    inside = root.resolve()
    for name, record in files.items():
        where = Path(name)
        if where.is_absolute() or ".." in where.parts or inside not in (root / where).resolve().parents:
            raise bad(f"file {name!r} lies outside the zoo folder {root}")
        if not (isinstance(record, dict) and isinstance(record.get("sha256"), str) and len(record["sha256"]) == 64
                and isinstance(record.get("bytes"), int) and not isinstance(record.get("bytes"), bool)):
            raise bad(f"file {name!r} needs a sha256 (64 hex digits) and its size in bytes")
    for method, record in policies.items():
        if not isinstance(record, dict) or record.get("file") not in files:
            raise bad(f"policy {method!r} names no file the manifest lists")


def recognizer_settings(preset: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """The recognizer's training settings under a preset (``ClassifierRecipe`` as a dict)."""
    return json.loads(json.dumps(ClassifierRecipe.from_preset(preset, seed=seed).__dict__))

"""``uevavd prepare``: build the observation table of a dataset for a method's perception.

For every context scene (``00`` and ``train_605`` are not RL scenes) and each of its 605
views: encoder features of the (optionally pre-decomposed) view, classifier
probabilities on the raw view, the normalised box, and the visible fraction where known.

The table lives in ``<tables_dir>/<key>/`` where ``key`` hashes everything that produced it
(dataset files, segmenter, decomposition and gray seed, encoder and classifier identities
with their weights hashes, schema version), so a changed input is never served from an
old table. Work is kept scene by scene in ``<key>.partial/`` (each shard written
atomically), so a killed run resumes where it stopped; the final table is assembled and
renamed into place at the end. Images decode in worker threads, overlapping the forward.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Component, MethodSpec, PerceptionSection, as_method
from ..data.grid import N_VIEWS
from ..data.reader import read_dataset
from ..data.splits import TARGETS
from ..data.validate import segmentation_problem
from ..hashing import json_digest, sha256_hex
from ..paths import tables_dir
from ..table import SCHEMA_VERSION, ObservationTable, TableError
from .decompose import check_decomposition, decompose, view_seed
from .images import Decoder
from .shards import (
    SHARD_ARRAYS,
    build_lock,
    cached_array,
    cached_probs,
    features_folder,
    read_shard,
    save_array,
    write_shard,
)

log = logging.getLogger(__name__)


def context_scenes(manifest) -> list[tuple[str, list]]:
    """``[(scene, records sorted by view)]`` for the context scenes, by context id; each
    must hold 605 views of one target."""
    by_scene: dict[str, list] = {}
    for r in manifest.records:
        if r.context is not None:
            by_scene.setdefault(r.scene, []).append(r)
    out = []
    for scene, recs in sorted(by_scene.items(), key=lambda kv: kv[1][0].context):
        recs = sorted(recs, key=lambda r: r.view)
        targets = {r.target for r in recs}
        if len(targets) != 1 or [r.view for r in recs] != list(range(N_VIEWS)):
            raise ValueError(
                f"scene {scene}: expected the {N_VIEWS} views of one target, found {len(recs)} views of "
                f"{sorted(targets)}; check the dataset with `uevavd validate`"
            )
        out.append((scene, recs))
    if not out:
        raise ValueError(f"{manifest.root}: no context scenes (001..150); nothing to put in a table")
    return out


def _scene_fingerprint_bytes(manifest, scene: str, recs: list) -> bytes:
    """What :func:`dataset_fingerprint` hashes of one scene: its categories, then per view
    the target, view, box and visibility, and name, size and modification time of the image
    and segmentation files."""
    chunks = [f"{scene}:{json.dumps(manifest.categories(scene), sort_keys=True)}".encode()]
    for r in recs:
        parts = [r.target, r.view, r.box, r.visible]
        for f in (r.image, r.seg):
            if f is not None:
                st = os.stat(f)
                parts += [os.path.basename(f), st.st_size, st.st_mtime_ns]
        chunks.append(repr(parts).encode())
    return b"".join(chunks)


def _fingerprints(manifest, scenes: list[tuple[str, list]]) -> tuple[str, dict[str, str]]:
    """``(dataset_fingerprint(manifest, scenes), {scene: dataset_fingerprint of that scene
    alone})``, every file stat'ed once."""
    whole = hashlib.sha256()
    per_scene = {}
    for scene, recs in scenes:
        data = _scene_fingerprint_bytes(manifest, scene, recs)
        whole.update(data)
        per_scene[scene] = hashlib.sha256(data).hexdigest()[:16]
    return whole.hexdigest()[:16], per_scene


def dataset_fingerprint(manifest, scenes: list[tuple[str, list]]) -> str:
    """16-hex hash of the files and annotations the table reads: names, sizes and
    modification times of images and segmentations, boxes, visibility, categories."""
    return _fingerprints(manifest, scenes)[0]


def build_components(perception: PerceptionSection, data_root: Path, classifier_path: str | None, *,
                     where: str = "the perception section"):
    """``(segmenter or None, encoder, classifier)`` of a method's perception section;
    ``where`` names the method in errors."""
    def runtime(comp: Component, extra: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in extra.items() if k not in comp.kwargs and comp.accepts(k)}

    for section, comp in (("perception.encoder", perception.encoder), ("perception.classifier", perception.classifier)):
        if comp is None:
            raise ValueError(f"{where} names no {section}; a table needs both an "
                             "encoder and a classifier, e.g. encoder = { name = \"resnet50\" }")
    check_decomposition(perception, where)
    decomposing = perception.decompose
    segmenter = perception.segmenter.build() if decomposing and perception.segmenter is not None else None
    named = classifier_path is not None
    clf_runtime = runtime(perception.classifier, {"data": str(data_root)})
    enc_extra: dict[str, Any] = {"data": str(data_root)}
    if named:
        clf_runtime["path"] = str(classifier_path)  # --classifier wins over the method file
        enc_extra["classifier"] = str(classifier_path)  # weights="classifier" takes this recognizer's backbone
    # a classifier file the user named is read first (cheap), so that a bad one is refused
    # before the encoder loads its weights, or fails for their absence and hides it; the
    # dataset's own recognizer comes last, since it may have to be trained first
    classifier = perception.classifier.build(**clf_runtime) if named else None
    encoder = perception.encoder.build(**runtime(perception.encoder, enc_extra))
    if classifier is None:
        classifier = perception.classifier.build(**clf_runtime)
    return segmenter, encoder, classifier


def table_key(parts: Mapping[str, Any]) -> str:
    return json_digest(parts, 20, compact=True)


def ground_truth_categories(manifest, scene: str, recs: list) -> dict[int, str]:
    """The scene's instance id -> category table for a ground-truth segmenter; an error
    naming the file when the scene's segmentation cannot serve it
    (:func:`uevavd.data.validate.segmentation_problem`, the rule ``validate`` checks too)."""
    problem = segmentation_problem(manifest, scene, recs)
    if problem:
        raise ValueError(problem)
    return manifest.categories(scene)


def _load_scene(decoder: Decoder, manifest, scene: str, recs: list, segmenter, gray_seed: int):
    """Decode a scene (in worker threads); segmenters with a data-only fast path
    (``decompose_views``, e.g. ``gt``) also pre-decompose here, off the model's thread."""
    images = decoder.images([r.image for r in recs])
    maps = cats = decomposed = None
    if segmenter is not None and getattr(segmenter, "needs_ground_truth", False):
        if any(r.seg is None for r in recs):
            raise ValueError(f"scene {scene}: the segmenter needs ground-truth segmentation, which it lacks")
        maps = decoder.instance_maps([r.seg for r in recs])
        cats = [ground_truth_categories(manifest, scene, recs)] * len(recs)
        if hasattr(segmenter, "decompose_views"):
            seeds = [view_seed(gray_seed, scene, r.view, r.target) for r in recs]
            # views are independent: one slice per decoding thread (the decomposition's
            # lookups and OpenCV calls release the GIL)
            decomposed = np.empty_like(images)

            def part(s: slice) -> None:
                decomposed[s] = segmenter.decompose_views(images[s], maps[s], cats[s], seeds[s])

            decoder.map_slices(part, len(recs))
    return images, decomposed, maps, cats


def _probs_path(probs_dir: Path | None, scene: str, fingerprint: str) -> Path | None:
    """Where the classifier's probabilities on a scene's raw views are cached: keyed by the
    classifier's identity (``probs_dir``) and the scene's own files (``fingerprint``, its
    :func:`dataset_fingerprint` alone), so tables that differ only in segmenter or encoder
    (MAP's and IBE-MAP's) classify each raw view once."""
    if probs_dir is None:
        return None
    return probs_dir / f"{scene}-{fingerprint}.npz"


def _compute_scene(scene, recs, loaded, *, segmenter, encoder, classifier, gray_seed, image_hw,
                   probs_path: Path | None = None, features_path: Path | None = None):
    features = cached_array(features_path, (N_VIEWS, encoder.feature_dim), np.float16)
    if features is not None:
        probs = cached_probs(probs_path, len(classifier.classes))
        if probs is None:
            probs = classifier.predict_proba(loaded[0]).astype(np.float32)
            if probs_path is not None:
                save_array(probs_path, probs)
        return _scene_arrays(recs, features, probs, image_hw)
    images, decomposed, maps, cats = loaded
    boxes_px = np.array([r.box for r in recs], np.float32).reshape(-1, 4)
    enc_in = images if decomposed is None else decomposed
    if segmenter is not None and decomposed is None:
        segs = segmenter.segment(images, boxes_px.astype(np.int64), instance_maps=maps, categories=cats)
        enc_in = np.stack([
            decompose(img, s.target, s.segments, seed=view_seed(gray_seed, scene, r.view, r.target))
            for img, s, r in zip(images, segs, recs, strict=True)
        ])
    n_classes = len(classifier.classes)
    if enc_in is images and getattr(classifier, "shares_backbone", lambda e: False)(encoder):
        # the encoder is the recognizer's own backbone on the same raw views: one forward
        features = encoder.encode(images)
        probs = classifier.proba_from_features(features).astype(np.float32)
        if probs_path is not None and cached_probs(probs_path, n_classes) is None:  # a good cache is kept
            save_array(probs_path, probs)
    else:
        features = encoder.encode(enc_in)
        probs = cached_probs(probs_path, n_classes)
        if probs is None:  # missing or damaged: computed, and cached
            probs = classifier.predict_proba(images).astype(np.float32)
            if probs_path is not None:
                save_array(probs_path, probs)
    if features_path is not None:  # the cache was missing or damaged (else returned above)
        save_array(features_path, features.astype(np.float16))
    return _scene_arrays(recs, features, probs, image_hw)


def _scene_arrays(recs, features, probs, image_hw) -> dict[str, np.ndarray]:
    boxes_px = np.array([r.box for r in recs], np.float32).reshape(-1, 4)
    h, w = image_hw
    return {
        "features": features.astype(np.float16),
        "probs": probs.astype(np.float32),
        "boxes": boxes_px / np.array([w, h, w, h], np.float32),
        "visible": np.array([np.nan if r.visible is None else r.visible for r in recs], np.float32),
    }


@dataclass
class TablePlan:
    """Everything a table build needs, and its key (see :func:`plan_table`): the method's
    perception section and its built components; of the rest of the method only
    ``provenance`` (its name and hash, recorded in the table beside the section)."""

    perception: PerceptionSection
    provenance: dict[str, str]
    data_root: Path
    manifest: Any
    scenes: list[tuple[str, list]]
    segmenter: Any
    encoder: Any
    classifier: Any
    gray_seed: int
    parts: dict[str, Any]
    key: str
    scene_fingerprints: dict[str, str]  # scene -> dataset_fingerprint of that scene alone


def plan_table(
    data_root: str | os.PathLike[str],
    spec_or_method: MethodSpec | str | os.PathLike[str],
    *,
    classifier_path: str | os.PathLike[str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    preset: Mapping[str, Any] | None = None,
) -> TablePlan:
    """Read the dataset, build the components and compute the table key (no images decoded).
    The method is resolved here, once; what follows reads its perception section only."""
    data_root = Path(data_root).expanduser().resolve()
    spec = as_method(spec_or_method, overrides, preset=preset)
    perception = spec.perception
    manifest = read_dataset(data_root)
    scenes = context_scenes(manifest)
    segmenter, encoder, classifier = build_components(
        perception, data_root, None if classifier_path is None else str(classifier_path),
        where=f"method {spec.name!r} ({spec.source})")
    if tuple(classifier.classes) != TARGETS:
        raise ValueError(f"classifier classes {list(classifier.classes)}; the table needs {list(TARGETS)}")
    trained_on = (getattr(classifier, "meta", None) or {}).get("input_size")
    if trained_on and manifest.image_size and tuple(trained_on) != tuple(manifest.image_size):
        raise ValueError(
            f"the recognizer {classifier_path or 'of this dataset'} was trained on {trained_on[0]} x {trained_on[1]} "
            f"px crops, but {data_root} holds {manifest.image_size[0]} x {manifest.image_size[1]} px views: train "
            f"one on this dataset (`uevavd train-classifier {data_root}`) or pass the matching --classifier")
    decomposing = segmenter is not None
    if decomposing and getattr(segmenter, "needs_ground_truth", False):
        for scene, recs in scenes:  # fail before any image is decoded
            ground_truth_categories(manifest, scene, recs)
    gray_seed = perception.gray_seed
    fingerprint, scene_fingerprints = _fingerprints(manifest, scenes)
    parts = {
        "schema_version": SCHEMA_VERSION,
        "dataset": fingerprint,
        "segmenter": segmenter.identity() if decomposing else None,
        "decompose": decomposing,
        "gray_seed": gray_seed if decomposing else None,
        "encoder": encoder.identity(),
        "classifier": classifier.identity(),
        **({"recognizer_in_state": True} if perception.recognizer_in_state else {}),  # other tables' keys as before
    }
    return TablePlan(perception, {"method": spec.name, "method_hash": spec.hash}, data_root, manifest, scenes,
                     segmenter, encoder, classifier, gray_seed, parts, table_key(parts), scene_fingerprints)


def prepare_table(
    data_root: str | os.PathLike[str],
    spec_or_method: MethodSpec | str | os.PathLike[str],
    *,
    classifier_path: str | os.PathLike[str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    workers: int = 2,
    preset: Mapping[str, Any] | None = None,
    progress: bool = True,
    only_scenes: Sequence[str] | None = None,
    assemble: bool = True,
) -> Path:
    """Build (or find) the observation table; returns its folder ``<out_dir>/<key>``.

    ``out_dir`` defaults to :func:`uevavd.paths.tables_dir`. A finished table with the same
    key is reused; an interrupted build resumes from its finished scenes.

    ``only_scenes`` computes the shards of those scenes only and ``assemble=False`` stops
    before the table is put together (returning the ``<key>.partial`` folder): this is how
    :func:`prepare_table_ray` spreads the scenes over workers that share ``out_dir``.
    """
    from tqdm.auto import tqdm

    p = plan_table(data_root, spec_or_method, classifier_path=classifier_path, overrides=overrides, preset=preset)
    data_root, manifest, scenes = p.data_root, p.manifest, p.scenes
    segmenter, encoder, classifier, gray_seed = p.segmenter, p.encoder, p.classifier, p.gray_seed
    parts, key = p.parts, p.key
    out_dir = Path(out_dir).expanduser() if out_dir is not None else tables_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    def usable(folder: Path) -> bool:
        try:
            ObservationTable.load(folder, expect_key=key)
            return True
        except (TableError, OSError):
            return False

    # One build per key at a time; Ray shards share the partial folder on purpose and take no lock.
    with build_lock(out_dir, key, usable) if only_scenes is None and assemble else nullcontext():
        final = out_dir / key
        if final.is_dir():
            try:
                ObservationTable.load(final, expect_key=key)
                log.info("prepare: table %s already built", final)
                return final
            except TableError as exc:
                log.warning("prepare: existing table %s is unusable (%s); rebuilding", final, exc)
        partial = out_dir / f"{key}.partial"
        partial.mkdir(parents=True, exist_ok=True)
        probs_dir = out_dir / "probs" / sha256_hex(classifier.identity(), 16)
        features_dir = features_folder(out_dir, parts)
        (partial / "key.json").write_text(json.dumps(parts, indent=1, sort_keys=True), encoding="utf-8")
        k = len(TARGETS)
        shards: dict[str, dict[str, np.ndarray]] = {}
        todo = []
        for scene, recs in scenes:
            done = read_shard(partial / f"{scene}.npz", encoder.feature_dim, k)
            if done is None:
                if only_scenes is None or scene in only_scenes:
                    todo.append((scene, recs))
            else:
                shards[scene] = done
        bar = tqdm(total=len(scenes) * N_VIEWS, initial=len(shards) * N_VIEWS, desc=f"prepare {key[:8]}",
                   unit="view", disable=not progress)
        with Decoder(workers) as dec, bar:  # the bar ends its line also when a scene fails
            nxt = dec.submit(_load_scene, dec, manifest, *todo[0], segmenter, gray_seed) if todo else None
            for i, (scene, recs) in enumerate(todo):
                loaded = nxt.result()
                nxt = dec.submit(_load_scene, dec, manifest, *todo[i + 1], segmenter, gray_seed) if i + 1 < len(todo) else None
                arrays = _compute_scene(scene, recs, loaded, segmenter=segmenter, encoder=encoder,
                                        classifier=classifier, gray_seed=gray_seed, image_hw=manifest.image_size,
                                        probs_path=_probs_path(probs_dir, scene, p.scene_fingerprints[scene]),
                                        features_path=_probs_path(features_dir, scene, p.scene_fingerprints[scene]))
                write_shard(partial / f"{scene}.npz", arrays)
                shards[scene] = arrays
                bar.update(N_VIEWS)
        if not assemble:
            return partial
        names = [s for s, _ in scenes]
        stack = {a: np.stack([shards[s][a] for s in names]) for a in SHARD_ARRAYS}
        config = {**p.provenance, "perception": p.perception.as_dict(), "key_parts": parts, "data_root": str(data_root)}
        if p.perception.recognizer_in_state:  # the state reads the recognizer's probabilities after the image's features
            stack["features"] = np.concatenate([stack["features"], stack["probs"].astype(np.float16)], axis=-1)
        table = ObservationTable.from_arrays(
            stack["features"], stack["probs"], stack["boxes"], visible=stack["visible"],
            scenes=names,
            targets=[recs[0].target for _, recs in scenes],
            splits=[recs[0].split for _, recs in scenes],
            contexts=[recs[0].context for _, recs in scenes],
            config=config, key=key,
        )
        table.save(final)
        shutil.rmtree(partial, ignore_errors=True)
        return final

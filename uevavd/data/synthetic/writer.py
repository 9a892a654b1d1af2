"""Write the synthetic world in the canonical UEVAVD layout (:mod:`uevavd.data.layout`).

One folder per scene ("001".."150", "00", "train_605"). Per view: the RGB crop (PNG), its
box (TXT, one line "x1 y1 x2 y2", XYXY crop pixels, x2/y2 exclusive, "0 0 0 0" when the
target is fully occluded) and the instance segmentation (uint16 PNG under ``seg/``); per
scene ``seg/categories.json`` and ``scene.json``. ``scene.json`` is written last, atomically,
and records the sha256 of every other file of the scene: a scene counts as complete only
when it exists, matches the requested settings and every recorded file hashes to its
record, so an interrupted run resumes by redoing just the incomplete scenes (a hidden
``.verified.json`` keeps each file's size, mtime and ctime when it last matched, so an
unchanged file is not hashed again). The dataset card ``uevavd.json`` and ``manifest.json``
(sha256 and size of every file) come last.

A scene's view files are written in place: its ``scene.json``, written last and atomically
(temp file in the same folder, then ``os.replace``) with the hash of every file, is the
scene's commit record, so a file cut short by a kill fails its hash and the scene is redone
(one rename per scene instead of 1,815 saves a tenth of the generation time). The dataset
card and ``manifest.json`` are written atomically. PNGs use a fixed compression level, so
the same (seed, context, size) gives identical bytes.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, wait
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...atomic import atomic_write, folder_lock
from ...hashing import sha256_hex
from ...runtime import WorkerPool, safe_context, single_threaded_worker
from .. import layout
from ..grid import N_VIEWS, view_coords
from ..splits import CLASSIFIER_SCENE, TARGETS, UNOCCLUDED_SCENE, check_context, scene_name
from .render import PreparedScene, SharedShadows, focal_px, render_unoccluded_view, render_view
from .world import (
    BLOCK_TARGETS,
    TARGET_ID,
    TRAIN_STAGES,
    VALIDITY,
    VERSION,
    Scene,
    build_context,
    build_training_stage,
    build_unoccluded,
    training_stages,
    with_target,
)

log = logging.getLogger(__name__)

FORMAT = "uevavd-synthetic"
_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 3]


def _png(image: np.ndarray, path: Path) -> bytes:
    ok, buf = cv2.imencode(".png", image, _PNG)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode {path} as PNG")
    return buf.tobytes()


def _scene_jobs(contexts: Sequence[int], include_unoccluded: bool) -> list[str]:
    names = [scene_name(c) for c in contexts]
    if include_unoccluded:
        names = [UNOCCLUDED_SCENE, CLASSIFIER_SCENE] + names  # the big ones first
    return names


def _jobs_of(name: str, seed: int) -> Iterator[tuple[int, Scene, np.ndarray, Callable]]:
    """(stage, scene, view indices, render function) that make up scene folder ``name``;
    ``stage`` numbers the train_605 stages (one background for the five targets), else 0."""
    if name == UNOCCLUDED_SCENE:
        for target in TARGETS:
            yield 0, build_unoccluded(target, seed=seed, scene=name), np.arange(N_VIEWS), render_view
    elif name == CLASSIFIER_SCENE:
        stages = training_stages(seed)
        for k in range(TRAIN_STAGES):
            base = build_training_stage(TARGETS[0], seed=seed, stage=k)
            for target in TARGETS:
                yield k, with_target(base, target), np.flatnonzero(stages == k), render_unoccluded_view
    else:
        yield 0, build_context(int(name), seed=seed), np.arange(N_VIEWS), render_view


def _id_shift(categories: dict[int, str], offset: int) -> np.ndarray:
    """Lookup table of new instance ids: 0 (none) and the target keep theirs, every other id
    i becomes i - 1 + offset (the identity for offset 0)."""
    shift = np.arange(max(categories) + 1, dtype=np.int64)
    if offset:
        shift[TARGET_ID + 1:] += offset - 1
    return shift


def _views_in(name: str) -> int:
    return N_VIEWS * (len(TARGETS) if name in (UNOCCLUDED_SCENE, CLASSIFIER_SCENE) else 1)


#: Per scene folder, hidden from the dataset's readers: the size, mtime and ctime of every file
#: ``scene.json`` records, when each last matched its sha256 (and that ``scene.json``'s digest).
_STAMP = ".verified.json"


def _stats(folder: Path, rels) -> dict[str, list[int]]:
    base = f"{folder}{os.sep}"  # os.stat of a joined string: pathlib's joins cost more than the stats
    out = {}
    for rel in rels:
        st = os.stat(base + rel)
        out[rel] = [st.st_size, st.st_mtime_ns, st.st_ctime_ns]
    return out


def _stamp(folder: Path, meta_bytes: bytes, rels) -> None:
    """Record that the files ``rels`` of ``folder`` match ``scene.json`` (``meta_bytes``) now."""
    stamp = {"scene_json": sha256_hex(meta_bytes), "files": _stats(folder, rels)}
    atomic_write(folder / _STAMP, json.dumps(stamp).encode())


def _stamp_holds(folder: Path, meta_bytes: bytes, rels) -> bool:
    """The stamp vouches for this ``scene.json`` and no recorded file changed since: the same
    size, mtime and ctime (which no one can set back: a write with the mtime restored moves it)."""
    try:
        stamp = json.loads((folder / _STAMP).read_bytes())
        return stamp["scene_json"] == sha256_hex(meta_bytes) and stamp["files"] == _stats(folder, rels)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def scene_complete(folder: Path, *, size: int, seed: int) -> bool:
    """True when ``folder/scene.json`` exists, was written by this generator version for
    (size, seed) and every file it records exists with the recorded sha256. A file unchanged
    since it last matched (size, mtime and ctime, as a table's features are checked) is not
    hashed again: a cached world is checked in a stat per file."""
    meta_path = folder / layout.SCENE_META
    try:
        meta_bytes = meta_path.read_bytes()
        meta = json.loads(meta_bytes)
    except (OSError, ValueError):
        return False
    if (meta.get("format"), meta.get("version")) != (FORMAT, VERSION):
        return False  # written by another version of the generator: redo it
    if meta.get("size") != size or meta.get("seed") != seed or not isinstance(meta.get("files"), dict):
        return False
    if _stamp_holds(folder, meta_bytes, meta["files"]):
        return True
    for rel, digest in meta["files"].items():
        try:
            if sha256_hex((folder / rel).read_bytes()) != digest:
                return False
        except OSError:
            return False
    try:
        _stamp(folder, meta_bytes, meta["files"])
    except OSError:
        pass  # a read-only world: checked by its hashes at every call
    return True


def write_scene(root: Path, name: str, *, size: int, seed: int, on_view: Callable[[], None] | None = None) -> dict:
    """Render and write one scene folder; returns its ``scene.json`` record. ``on_view`` is
    called after each view is written (a progress bar's tick)."""
    folder = root / name
    (folder / layout.SEG_DIR).mkdir(parents=True, exist_ok=True)
    for stale in [*folder.glob(".*.tmp*"), *(folder / layout.SEG_DIR).glob(".*.tmp*")]:
        stale.unlink(missing_ok=True)  # left by an interrupted run
    (folder / layout.SCENE_META).unlink(missing_ok=True)  # the scene is incomplete until it is rewritten
    (folder / _STAMP).unlink(missing_ok=True)
    files: dict[str, str] = {}
    visible: dict[str, float] = {}
    categories: dict[int, str] = {}
    stages: list[dict] = []
    order: list[tuple[tuple[int, int], str]] = []
    first = None
    offset, current, shift, shared = 0, None, None, None
    for stage, scene, views, render in _jobs_of(name, seed):
        first = first or scene
        if stage != current:
            # train_605's stages are separate scenes: their object ids are shifted into one id space
            current = stage
            # and a stage's five scenes differ only in their target: its shadows are cast once
            shared = SharedShadows() if name == CLASSIFIER_SCENE else None
            shift = _id_shift(scene.categories, offset)
            categories.update({int(shift[i]): c for i, c in scene.categories.items()})
            offset = max(categories)
            if offset > np.iinfo(np.uint16).max:
                raise RuntimeError(f"scene {name}: instance id {offset} does not fit the uint16 segmentation")
            if name == CLASSIFIER_SCENE:
                stages.append({"terrain": scene.terrain,
                               "sun_direction": [round(float(c), 6) for c in scene.sun_dir]})
        prep = PreparedScene(scene, shared)
        for v in views:
            x, y, z = view_coords(int(v))
            stem = layout.view_stem(x, y, z, scene.target, name)
            view = render(scene, int(v), size, prep)
            for rel, data in (
                (stem + layout.IMAGE_EXT, _png(cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR), folder / stem)),
                (stem + layout.BOX_EXT, (" ".join(str(int(b)) for b in view.box) + "\n").encode()),
                (f"{layout.SEG_DIR}/{stem}{layout.IMAGE_EXT}", _png(shift[view.seg].astype(np.uint16), folder / stem)),
            ):
                (folder / rel).write_bytes(data)  # in place: scene.json below is the commit record
                files[rel] = sha256_hex(data)
            visible[stem] = round(float(view.visible), 6)
            order.append(((TARGETS.index(scene.target), int(v)), stem))
            if on_view is not None:
                on_view()
    visible = {stem: visible[stem] for _, stem in sorted(order)}  # targets' views in grid order
    cats = {str(k): v for k, v in sorted(categories.items())}
    data = (json.dumps(cats, indent=1) + "\n").encode()
    rel = f"{layout.SEG_DIR}/{layout.CATEGORIES}"
    (folder / rel).write_bytes(data)
    files[rel] = sha256_hex(data)
    unocc = name in (UNOCCLUDED_SCENE, CLASSIFIER_SCENE)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "scene": name,
        "context": None if unocc else int(name),
        "split": name if unocc else first.split,
        "target": None if unocc else first.target,
        "targets": list(TARGETS) if unocc else [first.target],
        "terrain": first.terrain,
        **({} if unocc else {"placement": first.placement, "draw": first.draw,
                             "validity": VALIDITY.describe()}),
        "size": size,
        "seed": seed,
        "focal_px": focal_px(size),
        "box_format": "x1 y1 x2 y2, XYXY crop pixels, x2/y2 exclusive; 0 0 0 0 = fully occluded",
        "categories": cats,
        "sun_direction": [round(float(c), 6) for c in first.sun_dir] if not unocc else None,
        **({"stages": stages, "stage_of_view": training_stages(seed).tolist()} if stages else {}),
        "visible": visible,
        "files": files,
    }
    meta_bytes = (json.dumps(meta, indent=1) + "\n").encode()
    atomic_write(folder / layout.SCENE_META, meta_bytes)
    _stamp(folder, meta_bytes, files)  # the files were hashed as they were written
    return meta


#: In a rendering worker: the count of views written, shared with the parent's progress bar.
_views_written: Any = None


def _rendering_worker(counter: Any) -> None:
    """Initializer of the rendering processes: one numpy thread, views counted into ``counter``."""
    global _views_written
    single_threaded_worker()
    _views_written = counter


def _count_view() -> None:
    with _views_written.get_lock():
        _views_written.value += 1


def _job(root: str, name: str, size: int, seed: int) -> tuple[str, int]:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    write_scene(Path(root), name, size=size, seed=seed, on_view=None if _views_written is None else _count_view)
    return name, _views_in(name)


#: What a synthetic world's folder holds besides its card and manifest: its scenes' folders, and
#: the temporary files of a card or manifest whose write was killed.
_WORLD_ENTRY = re.compile(r"^(\d{3}|00|train_605|\.(uevavd|manifest)\.json\..*\.tmp)$")


def _check_foreign(root: Path) -> None:
    """Refuse a folder that holds something other than a synthetic world (a world of its own,
    or one a killed call left unfinished): its files would be overwritten."""
    if not root.is_dir():
        return
    card = root / layout.DATASET_CARD
    try:
        foreign = card.is_file() and json.loads(card.read_text()).get("format") != FORMAT
    except (ValueError, AttributeError, OSError):
        foreign = False  # an unreadable card of ours: rewritten at the end
    others = sorted(p.name for p in root.iterdir()
                    if p.name not in (layout.DATASET_CARD, layout.MANIFEST) and not _WORLD_ENTRY.match(p.name))
    if foreign or others:
        what = f"{card.name} of another format" if foreign else f"{others[0]!r}"
        raise ValueError(f"{root} is not a synthetic world (it holds {what}); writing one there would overwrite "
                         "its files: choose an empty or new folder")


def _check_card(root: Path, size: int, seed: int) -> None:
    card = root / layout.DATASET_CARD
    if not card.is_file():
        return
    try:
        meta = json.loads(card.read_text())
    except ValueError:
        return  # unreadable card: it is rewritten at the end
    if meta.get("format") == FORMAT and (meta.get("size"), meta.get("seed")) != (size, seed):
        raise ValueError(
            f"{root} holds a synthetic world with size={meta.get('size')}, seed={meta.get('seed')}, "
            f"not size={size}, seed={seed}: choose another output folder or delete this one"
        )


def write_world(
    out: Path,
    *,
    contexts: Sequence[int],
    size: int,
    seed: int,
    workers: int = 1,
    include_unoccluded: bool = True,
    progress: bool = True,
) -> Path:
    """Write contexts (ids 1..150), plus scenes "00" and "train_605" when
    ``include_unoccluded``, at ``size`` x ``size`` px into ``out``; returns ``out``.

    Resumable: scenes already complete and verified are skipped. ``workers`` > 1 renders
    scenes in that many processes. Writes ``uevavd.json`` and ``manifest.json`` last. A second
    process writing into the same folder waits for the first, then checks its card (two seeds
    into one folder both "succeeded" over each other's scenes)."""
    root = Path(out)
    if size < 16:
        raise ValueError(f"size={size}: expected a crop size of at least 16 px")
    if workers < 1:
        raise ValueError(f"workers={workers}: expected at least 1")
    contexts = sorted({check_context(c) for c in contexts})

    def waiting(lock_file: str) -> None:
        log.warning("%s is being written by another process (it holds %s): waiting for it", root, lock_file)

    # another writer of the same world (two ablations sharing a cache) is waited for, then its
    # scenes are verified and kept; one of another seed or size is refused by the card after it
    with folder_lock(root, ValueError, wait=waiting):
        return _write_world(root, contexts, size, seed, include_unoccluded, workers, progress)


def _write_world(root: Path, contexts: list[int], size: int, seed: int, include_unoccluded: bool, workers: int,
                 progress: bool) -> Path:
    from tqdm.auto import tqdm

    _check_foreign(root)
    root.mkdir(parents=True, exist_ok=True)
    _check_card(root, size, seed)
    names = _scene_jobs(contexts, include_unoccluded)
    todo = [n for n in names if not scene_complete(root / n, size=size, seed=seed)]
    total = sum(_views_in(n) for n in names)
    # views already written start the bar (initial), so its rate counts this call's views only;
    # it moves view by view (the workers count into a shared integer the parent polls)
    initial = total - sum(_views_in(n) for n in todo)
    bar = tqdm(total=total, initial=initial, unit="view", desc=f"synth {size}px", disable=not progress)
    if workers == 1 or len(todo) <= 1:
        for n in todo:
            write_scene(root, n, size=size, seed=seed, on_view=lambda: bar.update(1))
    else:
        ctx = safe_context()
        counter = ctx.Value("q", 0)
        with WorkerPool(workers, mp_context=ctx, initializer=_rendering_worker, initargs=(counter,)) as pool:
            pending = {pool.submit(_job, str(root), n, size, seed) for n in todo}
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for fut in done:
                    fut.result()
                bar.update(initial + counter.value - bar.n)
    bar.close()
    _write_card_and_manifest(root, names, contexts, size, seed, include_unoccluded)
    return root


def _write_card_and_manifest(root: Path, names, contexts, size, seed, include_unoccluded) -> None:
    card = {
        "format": FORMAT,
        "version": VERSION,
        "generator": "uevavd.data.synthetic",
        "seed": seed,
        "size": size,
        "focal_px": focal_px(size),
        "contexts": contexts,
        "scenes": names,
        "unoccluded": include_unoccluded,
        "block_targets": list(BLOCK_TARGETS),
        "box_format": "x1 y1 x2 y2, XYXY crop pixels, x2/y2 exclusive; 0 0 0 0 = fully occluded",
    }
    card_bytes = (json.dumps(card, indent=1) + "\n").encode()
    atomic_write(root / layout.DATASET_CARD, card_bytes)
    files: dict[str, dict] = {layout.DATASET_CARD: {"sha256": sha256_hex(card_bytes), "size": len(card_bytes)}}
    for n in names:
        folder = root / n
        meta_bytes = (folder / layout.SCENE_META).read_bytes()
        meta = json.loads(meta_bytes)
        base = f"{folder}{os.sep}"
        for rel, digest in meta["files"].items():
            files[f"{n}/{rel}"] = {"sha256": digest, "size": os.stat(base + rel).st_size}
        files[f"{n}/{layout.SCENE_META}"] = {"sha256": sha256_hex(meta_bytes), "size": len(meta_bytes)}
    manifest = {"format": FORMAT, "version": VERSION, "files": dict(sorted(files.items()))}
    atomic_write(root / layout.MANIFEST, (json.dumps(manifest, indent=0) + "\n").encode())

"""Read a UEVAVD-layout root (the real release or the synthetic world) into a manifest.

:func:`read_dataset` walks ``ROOT`` (scene folders directly below it, or nested one
level such as ``ROOT/urban/001``), parses every image name (:mod:`.naming`) and its box
annotation (:mod:`.annotations`) and returns an immutable :class:`Manifest` of
:class:`ViewRecord` in a deterministic order: context scenes by id, then ``"00"``, then
``"train_605"``; within a scene by target (class-index order), then view index.
Nothing is decoded here, so 10^5 views take seconds; :func:`uevavd.data.validate.validate`
decodes every image.

With ``check=True`` every problem (each naming its file and what was expected) is
collected and raised together as one :class:`DatasetError`. Files in a scene folder that
the reader cannot use are named too (kinds in :data:`UNUSED_FILE_KINDS`: an annotation
without its image, a name that does not parse, a file of unknown type); they are
problems for ``uevavd validate`` but only logged as a warning by :func:`read_dataset`,
since the views it did read are complete without them. Obvious non-data files (README,
LICENSE, ``scene.json``, ``manifest.json``, ``uevavd.json``, ``seg/``, hidden files) are
ignored.

An image may carry more than one annotation (``.txt``, ``.json``, ``.xml`` beside it or
in an annotation folder, a row of the scene's table). The reader uses the first of
``.txt``, ``.json``, ``.xml``, then the table row; with ``check=True`` it also reads the
others, and any that gives another box, or does not parse, is a
``conflicting_annotation`` problem naming both files.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections import Counter, defaultdict
from pathlib import Path

from .layout import DATASET_CARD, MANIFEST
from .naming import (
    NameParseError,
    SceneId,
    is_image_name,
    parse_scene_dir,
)
from .records import UNUSED_FILE_KINDS, Manifest, Problem, ViewRecord
from .scene_scan import image_size, scan_scene

# the scene folders a UEVAVD root holds, as the reader's messages name them
_LAYOUT = "ROOT/001 .. ROOT/150, ROOT/00, ROOT/train_605"

__all__ = [
    "DatasetError",
    "Manifest",
    "Problem",
    "UNUSED_FILE_KINDS",
    "ViewRecord",
    "image_size",
    "read_dataset",
    "scan",
]

log = logging.getLogger(__name__)

class DatasetError(ValueError):
    """A dataset with problems; ``problems`` lists them all, each naming its file."""

    def __init__(self, root: Path, problems: list[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        counts = Counter(p.kind for p in self.problems)
        head = f"{len(self.problems)} problem(s) in dataset {self.root} (" + ", ".join(
            f"{k}: {n}" for k, n in sorted(counts.items())
        ) + "); run `uevavd validate ROOT` for a full report:"
        super().__init__("\n  ".join([head, *(str(p) for p in self.problems)]))


def _has_images(path: Path) -> bool:
    try:
        with os.scandir(path) as it:
            return any(e.is_file() and is_image_name(e.name) for e in it)
    except OSError:
        return False


def _subdirs(path: Path) -> list[os.DirEntry]:
    with os.scandir(path) as it:
        return sorted((e for e in it if e.is_dir() and not e.name.startswith(".")), key=lambda e: e.name)


def find_scenes(root: Path, problems: list[Problem]) -> list[tuple[SceneId, Path]]:
    """Scene folders below ``root`` (directly or nested one level), sorted by scene
    order; unrecognised folders holding images and duplicate scenes become problems."""
    found: list[tuple[SceneId, Path]] = []

    def consider(entry: os.DirEntry, depth: int) -> None:
        try:
            found.append((parse_scene_dir(entry.name), Path(entry.path)))
            return
        except NameParseError as e:
            if _has_images(Path(entry.path)):
                problems.append(Problem("unknown_scene", Path(entry.path), str(e)))
                return
        if depth == 0:
            for sub in _subdirs(Path(entry.path)):
                consider(sub, 1)

    for entry in _subdirs(root):
        consider(entry, 0)
    if _has_images(root):
        problems.append(Problem("unknown_scene", root, "images directly in ROOT; expected them in scene folders "
                                "('001'..'150', '00', 'train_605')"))
    by_key: dict[tuple, list[Path]] = defaultdict(list)
    for sid, path in found:
        by_key[(sid.kind, sid.context)].append(path)
    out = []
    for sid, path in sorted(found, key=lambda sp: (sp[0].sort_key, str(sp[1]))):
        paths = by_key[(sid.kind, sid.context)]
        if len(paths) > 1:
            if path != paths[0]:
                continue
            problems.append(Problem("duplicate_scene", path, f"the same scene is also in {[str(p) for p in paths[1:]]}; "
                                    "expected one folder per scene (the others are skipped)"))
        out.append((sid, path))
    if not out:
        problems.append(Problem("no_scenes", root, f"no scene folders found; expected {_LAYOUT} (or nested one level)"))
    return out


def listed_scenes(root: Path) -> dict[str, str]:
    """``{scene folder name: the file that lists it}`` from the dataset card's ``scenes`` and
    the first path component of ``manifest.json``'s files (files at the root excluded);
    unreadable files list nothing (``validate`` reports them)."""

    out: dict[str, str] = {}
    try:
        card = json.loads((root / DATASET_CARD).read_text(encoding="utf-8"))
        for name in card.get("scenes", []) if isinstance(card, dict) else []:
            out.setdefault(str(name), DATASET_CARD)
    except (OSError, ValueError):
        pass
    try:
        raw = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
        files = raw.get("files", raw) if isinstance(raw, dict) else raw
        names = files.keys() if isinstance(files, dict) else (
            f.get("path", "") for f in files if isinstance(f, dict)) if isinstance(files, list) else ()
        for rel in names:
            if isinstance(rel, str) and "/" in rel:
                out.setdefault(rel.split("/", 1)[0], MANIFEST)
    except (OSError, ValueError):
        pass
    return out


def scan(root: str | Path, *, check: bool = True) -> tuple[Manifest, list[Problem]]:
    """Read ``root`` without raising: the manifest of every record that parsed, and the
    list of problems (checks as in :func:`read_dataset`)."""
    root = Path(root).expanduser()
    problems: list[Problem] = []
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} is not a folder; expected a UEVAVD-layout root ({_LAYOUT})")
    records: list[ViewRecord] = []
    sizes: dict[tuple[int, int], list[Path]] = defaultdict(list)
    scene_dirs: dict[str, Path] = {}
    for sid, scene_dir in find_scenes(root, problems):
        recs, size = scan_scene(sid, scene_dir, check, problems)
        records.extend(recs)
        scene_dirs[sid.name] = scene_dir
        if size is not None:
            sizes[size].append(scene_dir)
    if scene_dirs and not records:  # e.g. /etc, whose postgresql/15 is named like scene 15 (named first: the cause)
        named = ", ".join(str(d) for d in list(scene_dirs.values())[:3]) + (", ..." if len(scene_dirs) > 3 else "")
        problems.insert(0, Problem("no_scenes", root, f"no scene holds a view (the folders named like scenes: {named}); "
                                f"expected {_LAYOUT} (or nested one level) holding images and annotations"))
    for name, where in listed_scenes(root).items():
        if name not in scene_dirs:
            problems.append(Problem("missing_scene", root / name, f"scene {name} is listed in {where} but its "
                                    "folder is missing: restore it (or regenerate the dataset)"))
    ranked = sorted(sizes.items(), key=lambda kv: (-len(kv[1]), kv[0]))
    if check and len(ranked) > 1:
        (common, _), rest = ranked[0], ranked[1:]
        for size, dirs in rest:
            for d in dirs:
                problems.append(Problem("mixed_sizes", d, f"images are {size[0]}x{size[1]} (HxW) but most scenes "
                                        f"are {common[0]}x{common[1]}; expected one image size"))
    image_hw = ranked[0][0] if ranked else (0, 0)
    return Manifest(root, records, image_hw, scene_dirs=scene_dirs, problems=problems), problems


#: (root as given, cwd when relative, check) -> (tree signature, manifest, problems); the
#: few roots read last (see read_dataset).
_READ_CACHE: dict[tuple[str, str, bool], tuple[str, Manifest, list[Problem]]] = {}
_READ_CACHE_SIZE = 4


def _tree_signature(root: Path) -> str:
    """A digest of (path, inode, size, mtime, ctime) of every entry under ``root``: it
    changes when a file is added, removed, replaced, renamed, resized or written. Symlinked
    folders are followed (a scene may live elsewhere), each folder once: two self-links hung
    `prepare` for minutes, walking a/a/a/... to the longest path the OS takes."""
    import hashlib

    entries = []
    stack = [str(root)]
    seen = set()  # (device, inode) of the folders walked: a symlink back up (`ln -s . D/a`) is walked once
    with contextlib.suppress(OSError):
        st = os.stat(root)
        seen.add((st.st_dev, st.st_ino))
    while stack:
        folder = stack.pop()
        try:
            with os.scandir(folder) as it:
                for e in it:
                    st = e.stat()
                    if e.is_dir() and (st.st_dev, st.st_ino) not in seen:
                        seen.add((st.st_dev, st.st_ino))
                        stack.append(e.path)
                    entries.append(f"{e.path}\0{st.st_ino}\0{st.st_size}\0{st.st_mtime_ns}\0{st.st_ctime_ns}")
        except OSError as err:  # unreadable folder: no caching, the scan reports it
            entries.append(f"{folder}\0error {err}")
    entries.sort()
    return hashlib.sha1("\n".join(entries).encode("utf-8", "surrogateescape")).hexdigest()


def _scan_cached(root: str | Path, check: bool) -> tuple[Manifest, list[Problem]]:
    path = Path(root).expanduser()
    if not path.is_dir():
        return scan(root, check=check)  # raises, naming the root
    key = (str(path), "" if path.is_absolute() else os.getcwd(), check)
    signature = _tree_signature(path)
    hit = _READ_CACHE.get(key)
    if hit is not None and hit[0] == signature:
        return hit[1], list(hit[2])
    checked = _READ_CACHE.get((*key[:2], True)) if not check else None
    if checked is not None and checked[0] == signature and all(p.kind in UNUSED_FILE_KINDS for p in checked[2]):
        return checked[1], list(checked[2])  # a clean checked read is what an unchecked one would give
    manifest, problems = scan(root, check=check)
    if _tree_signature(path) == signature:  # unchanged while it was read
        _READ_CACHE.pop(key, None)
        _READ_CACHE[key] = (signature, manifest, list(problems))
        while len(_READ_CACHE) > _READ_CACHE_SIZE:
            _READ_CACHE.pop(next(iter(_READ_CACHE)))
    return manifest, problems


def read_dataset(root: str | Path, *, check: bool = True) -> Manifest:
    """Read a UEVAVD-layout root into a :class:`Manifest` (no image decoding).

    ``check=True`` also checks 605 views per (scene, target), one target per context,
    box validity against the image size (read from one header per scene), that every
    image has an annotation, and one image size overall; it raises :class:`DatasetError`
    listing every problem. ``check=False`` returns whatever parsed (``manifest.problems``
    holds what did not).
    """
    manifest, problems = _scan_cached(root, check)
    if check and any(p.kind not in UNUSED_FILE_KINDS for p in problems):
        raise DatasetError(manifest.root, problems)
    unused = [p for p in problems if p.kind in UNUSED_FILE_KINDS]
    if unused:
        kinds = ", ".join(f"{k}: {n}" for k, n in sorted(Counter(p.kind for p in unused).items()))
        log.warning("dataset %s: %d file(s) not used (%s), e.g. %s; `uevavd validate ROOT` lists them all",
                    manifest.root, len(unused), kinds, unused[0])
    return manifest

"""Reading one scene folder of a UEVAVD-layout root: its images, their box annotations (a
.txt/.json/.xml per image, in the folder or an annotation sub-folder, or a table), the
visible fractions and the segmentation, and every problem with them, each naming its file
(:func:`scan_scene`). :mod:`uevavd.data.reader` walks a root with it."""

from __future__ import annotations

import json
import os
import re
import struct
from collections import Counter, defaultdict
from pathlib import Path

from .annotations import (
    ANNOTATION_EXTS,
    ANNOTATION_TABLE_STEMS,
    AnnotationError,
    BoxAnnotation,
    is_annotation_table,
    read_annotation_table,
    read_box_file,
)
from .grid import N_VIEWS, coords_to_view, view_coords
from .layout import CATEGORIES, DATASET_CARD, MANIFEST, SCENE_META, SEG_DIR, view_stem
from .naming import (
    IMAGE_EXTS,
    NameParseError,
    SceneId,
    UnknownTargetError,
    is_image_name,
    normalize_target,
    parse_view_stem,
    scene_matches,
)
from .records import Problem, ViewRecord
from .splits import TARGETS, split_of

# Names (lower-case) and stems that are not data: never reported.
_NOT_DATA_NAMES = frozenset({SCENE_META, MANIFEST, DATASET_CARD, CATEGORIES, "thumbs.db", "desktop.ini"})
_NOT_DATA_STEMS = frozenset({"readme", "license", "licence", "notice", "changelog", "citation"})

#: Sub-folders of a scene that may hold the per-image annotation files.
ANNOTATION_DIRS: tuple[str, ...] = ("annotations", "annotation", "labels", "boxes", "bboxes", "gt")
_MAX_LISTED = 12
# Stems of annotation-extension files that are not per-image boxes (tables, metadata).
_NOT_PER_IMAGE = frozenset({*ANNOTATION_TABLE_STEMS, SCENE_META.rpartition(".")[0], CATEGORIES.rpartition(".")[0]})

# Canonical names (layout.view_stem) take a fast path; everything else goes to naming.
_CANONICAL = re.compile(r"^x([+-]\d{2,3})_y([+-]\d{2,3})_z(\d{3})_([a-z]+)_(\d{2,3}|train_605)$")


def image_size(path: Path) -> tuple[int, int]:
    """(H, W) of a PNG or JPEG read from its header only. Raises ``ValueError`` naming
    the file when the header is missing or not a PNG/JPEG."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24 and head[12:16] == b"IHDR":
            w, h = struct.unpack(">II", head[16:24])
            return int(h), int(w)
        if head[:2] == b"\xff\xd8":
            f.seek(2)
            while True:
                marker = f.read(2)
                if len(marker) < 2 or marker[0] != 0xFF:
                    break
                if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
                    continue
                length_bytes = f.read(2)
                if len(length_bytes) < 2:
                    break
                (length,) = struct.unpack(">H", length_bytes)
                if marker[1] in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                    data = f.read(5)
                    if len(data) < 5:
                        break
                    h, w = struct.unpack(">HH", data[1:5])
                    return int(h), int(w)
                f.seek(length - 2, os.SEEK_CUR)
    raise ValueError(f"{path}: not a readable PNG or JPEG header; expected a .png or .jpg image")


def _parse_name(stem: str):
    m = _CANONICAL.match(stem)
    if m and m.group(4) in TARGETS:
        scene = m.group(5)
        return (int(m.group(1)), int(m.group(2)), int(m.group(3))), m.group(4), (
            scene if scene == "train_605" else str(int(scene)))
    p = parse_view_stem(stem)
    return p.xyz, p.target, p.scene


def _read_visible(scene_dir: Path, problems: list[Problem]) -> dict[str, float]:
    path = scene_dir / SCENE_META
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        problems.append(Problem("unparseable_metadata", path, f"cannot read ({e}); expected a JSON object"))
        return {}
    vis = meta.get("visible") if isinstance(meta, dict) else None
    if isinstance(vis, dict):
        return {str(k): float(v) for k, v in vis.items() if isinstance(v, int | float)}
    return {}


def _is_data_name(name: str) -> bool:
    """False for hidden files and obvious non-data files (README, metadata we write)."""
    low = name.lower()
    return not (low.startswith(".") or low in _NOT_DATA_NAMES or low.partition(".")[0] in _NOT_DATA_STEMS)


def _load_annotation_tables(scene_dir: Path, files: list[str], problems: list[Problem],
                 origin: dict[str, Path] | None = None) -> dict[str, BoxAnnotation]:
    """Boxes of the scene's annotation tables by image stem (first table wins); ``origin``
    receives the table each stem came from."""
    merged: dict[str, BoxAnnotation] = {}
    for name in files:
        if name.partition(".")[0].lower() not in ANNOTATION_TABLE_STEMS or not is_annotation_table(name):
            continue
        path = scene_dir / name
        try:
            boxes, errors = read_annotation_table(path)
        except AnnotationError as e:
            problems.append(Problem("unparseable_annotation", path, str(e).removeprefix(f"{path}: ")))
            continue
        problems.extend(Problem("unparseable_annotation", path, msg.removeprefix(f"{path} ")) for msg in errors)
        for k, v in boxes.items():
            merged.setdefault(k, v)
            if origin is not None:
                origin.setdefault(k, path)
    return merged


def _list_files(path: Path) -> list[str]:
    try:
        with os.scandir(path) as it:
            return sorted(e.name for e in it if e.is_file())
    except OSError:
        return []


def _unused_files(scene_dir: Path, files: list[str], ann_files: dict[str, tuple[int, str]],
                  ann_dir_files: dict[str, list[str]], table: dict[str, BoxAnnotation],
                  table_origin: dict[str, Path], image_stems: set[str], problems: list[Problem]) -> None:
    """Problems for every file of the scene the reader did not use (see UNUSED_FILE_KINDS)."""
    used_ann = {path for stem, (_, path) in ann_files.items() if stem in image_stems}
    known_dirs = {SEG_DIR, *ANNOTATION_DIRS}
    try:
        with os.scandir(scene_dir) as it:
            folders = sorted(e.name for e in it if e.is_dir() and not e.name.startswith("."))
    except OSError:
        folders = []
    for name in folders:
        if name.lower() not in known_dirs:
            problems.append(Problem("unknown_file", scene_dir / name, "folder not read: a scene folder holds its "
                                    f"images and annotations directly, plus {SEG_DIR}/ and optionally one of "
                                    f"{list(ANNOTATION_DIRS)} for the annotations"))
    for sub, names in [("", files), *ann_dir_files.items()]:
        d = scene_dir / sub if sub else scene_dir
        for name in names:
            if not _is_data_name(name):
                continue
            stem, _, ext = name.rpartition(".")
            ext = "." + ext.lower()
            path = d / name
            if not sub and is_image_name(name):
                continue  # images are judged one by one in _scan_scene
            if is_annotation_table(name):
                if sub:
                    problems.append(Problem("unknown_file", path, "annotation table not read: tables are read from "
                                            f"the scene folder itself ({scene_dir / name})"))
                continue  # read by _load_annotation_tables (its rows are checked below)
            if ext not in ANNOTATION_EXTS or not stem:
                problems.append(Problem("unknown_file", path, "not an image (" + ", ".join(IMAGE_EXTS) + "), a box "
                                        "annotation (" + ", ".join(ANNOTATION_EXTS) + ") or an annotation table "
                                        f"({ANNOTATION_TABLE_STEMS[0]}.csv, ...); the reader cannot use it"))
                continue
            if stem.lower() in _NOT_PER_IMAGE or str(path) in used_ann:
                continue
            if stem in ann_files and ann_files[stem][1] != str(path) and stem in image_stems:
                continue  # a second annotation of an image that has a preferred one
            problems.append(_imageless(stem, path, "annotation whose name does not parse",
                                       f"box annotation without its image: expected {stem}{IMAGE_EXTS[0]} "
                                       f"(or {'/'.join(IMAGE_EXTS[1:])}) in {scene_dir}"))
    for stem in sorted(set(table) - image_stems):
        problems.append(_imageless(stem, table_origin.get(stem, scene_dir),
                                   f"row {stem!r}: the image name does not parse",
                                   f"row {stem!r} has no image: expected {stem}{IMAGE_EXTS[0]} in {scene_dir}"))


def _agreeing_duplicates(name: str, used: str, ann: BoxAnnotation, others, row, problems: list[Problem]) -> bool:
    """Whether every other annotation of image ``name`` (files the reader ranks lower, and
    a table row ``(annotation, table path)``) gives the box of the one used; each that
    does not, or cannot be parsed, is a ``conflicting_annotation`` problem."""
    ok = True
    alts = [(Path(p), None) for p in others] + ([(row[1], row[0])] if row is not None else [])
    for where, alt in alts:
        what = f"the row for {name!r}" if alt is not None else "this annotation"
        try:
            alt = alt if alt is not None else read_box_file(where)
        except AnnotationError as e:
            msg = f"cannot be parsed ({str(e).removeprefix(f'{where}: ')})"
        else:
            if alt.box == ann.box:
                continue
            msg = f"says box {alt.box}"
        problems.append(Problem("conflicting_annotation", where, f"{what} {msg}, but {Path(used).name} "
                                f"(which the reader prefers) says {ann.box} for image {name!r}; keep one "
                                "annotation per image, or make them agree"))
        ok = False
    return ok


def _imageless(stem: str, where: Path, unparsed: str, orphan: str) -> Problem:
    """The problem of an annotation (file or table row) that no image of the scene uses:
    its name does not parse, or it parses and the image is missing."""
    try:
        _parse_name(stem)
    except NameParseError as e:
        return Problem("unparseable_annotation_name", where, f"{unparsed}: {e}")
    return Problem("orphan_annotation", where, orphan)


def _scene_size(scene_dir: Path, images: list[str], problems: list[Problem]) -> tuple[int, int] | None:
    """A scene's image size from the headers of its first, middle and last images (the
    majority; a header read is cheap): one odd image is then named as the odd one
    (``mixed_sizes``) instead of making every healthy file's box look outside the image."""
    picks = sorted({0, len(images) // 2, len(images) - 1}) if images else []
    sizes: dict[str, tuple[int, int]] = {}
    for i in picks:
        try:
            sizes[images[i]] = image_size(scene_dir / images[i])
        except (OSError, ValueError) as e:
            problems.append(Problem("unreadable_image", scene_dir / images[i], str(e)))
    if not sizes:
        return None
    counts = Counter(sizes.values())
    size = max(counts, key=lambda s: (counts[s], s))
    for name, other in sizes.items():
        if other != size:
            problems.append(Problem("mixed_sizes", scene_dir / name, f"image is {other[0]}x{other[1]} (HxW) but the "
                                    f"scene's other images are {size[0]}x{size[1]}; re-export it at that size"))
    return size


def scan_scene(sid: SceneId, scene_dir: Path, check: bool, problems: list[Problem]):
    """Records of one scene (sorted), its image size (H, W) or None."""
    files = _list_files(scene_dir)
    # Plain strings in this loop: pathlib costs more than the parsing at 10^5 files.
    ann_files: dict[str, tuple[int, str]] = {}  # stem -> (preference rank, path)
    ann_others: dict[str, list[str]] = defaultdict(list)  # stem -> the other annotation files
    ann_dir_files: dict[str, list[str]] = {}
    base = str(scene_dir)
    for sub in ("", *ANNOTATION_DIRS):
        d = os.path.join(base, sub) if sub else base
        names = files if not sub else _list_files(Path(d))
        if sub and names:
            ann_dir_files[sub] = names
        for name in names:
            stem, _, ext = name.rpartition(".")
            ext = "." + ext.lower()
            if ext in ANNOTATION_EXTS and stem.lower() not in _NOT_PER_IMAGE:
                rank = ANNOTATION_EXTS.index(ext)
                prev = ann_files.get(stem)
                if prev is None or rank < prev[0]:
                    ann_files[stem] = (rank, os.path.join(d, name))
                    if prev is not None:
                        ann_others[stem].append(prev[1])
                else:
                    ann_others[stem].append(os.path.join(d, name))
    table_origin: dict[str, Path] = {}
    table = _load_annotation_tables(scene_dir, files, problems, table_origin)
    seg_names = {n.rpartition(".")[0]: n for n in _list_files(scene_dir / SEG_DIR) if n.lower().endswith(".png")}
    visible = _read_visible(scene_dir, problems)
    images = [n for n in files if is_image_name(n)]
    size = _scene_size(scene_dir, images, problems)
    records: list[ViewRecord] = []
    seen: dict[tuple[str, int], list[Path]] = defaultdict(list)
    split = split_of(sid.context) if sid.context is not None else None
    seg_dir = scene_dir / SEG_DIR
    for name in images:
        path = scene_dir / name
        stem = name.rpartition(".")[0]
        try:
            xyz, target, token = _parse_name(stem)
        except UnknownTargetError as e:
            problems.append(Problem("unknown_target", path, str(e)))
            continue
        except NameParseError as e:
            problems.append(Problem("unparseable_name", path, str(e)))
            continue
        if token is not None and not scene_matches(token, sid):
            problems.append(Problem("scene_mismatch", path, f"the name says scene {token!r} but the file is in "
                                    f"folder {sid.name!r}; expected the folder's scene id"))
            continue
        try:
            view = coords_to_view(*xyz)
        except ValueError as e:
            problems.append(Problem("off_grid", path, f"{e} (coordinates {xyz} from the file name)"))
            continue
        seen[(target, view)].append(path)
        ann_entry = ann_files.get(stem)
        try:
            if ann_entry is not None:
                ann = read_box_file(ann_entry[1])
            elif stem in table:
                ann = table[stem]
            else:
                problems.append(Problem("missing_annotation", path, f"no box annotation: expected {stem}.txt, "
                                        f".json or .xml beside it, or a row for {name!r} in annotations.csv"))
                continue
        except AnnotationError as e:
            where = Path(ann_entry[1]) if ann_entry is not None else path
            problems.append(Problem("unparseable_annotation", where, str(e).removeprefix(f"{where}: ")))
            continue
        if check and ann.label is not None:
            try:
                label_target = normalize_target(ann.label)
            except NameParseError:
                label_target = None
            if label_target is not None and label_target != target:
                where = Path(ann_entry[1]) if ann_entry is not None else path
                problems.append(Problem("label_mismatch", where, f"annotation class {ann.label!r} "
                                        f"disagrees with the target {target!r} in the image name {name!r}"))
                continue
        if check and ann_entry is not None and (stem in ann_others or stem in table):
            if not _agreeing_duplicates(name, ann_entry[1], ann, ann_others.get(stem, ()),
                                        (table[stem], table_origin.get(stem, scene_dir)) if stem in table else None,
                                        problems):
                continue
        seg = seg_dir / seg_names[stem] if stem in seg_names else None
        records.append(ViewRecord(
            scene=sid.name,
            context=sid.context,
            split=split,
            target=target,
            view=view,
            xyz=xyz,
            image=path,
            box=ann.box,
            seg=seg,
            visible=visible.get(stem),
        ))
    _unused_files(scene_dir, files, ann_files, ann_dir_files, table, table_origin,
                  {n.rpartition(".")[0] for n in images}, problems)
    if check:
        _check_scene(sid, scene_dir, records, seen, size, problems)
    # Stable sort: images were visited in sorted name order, so ties stay deterministic.
    records.sort(key=lambda r: (TARGETS.index(r.target), r.view))
    return records, size


def _check_box(rec: ViewRecord, size: tuple[int, int] | None, problems: list[Problem]) -> bool:
    x1, y1, x2, y2 = rec.box
    if rec.box == (0, 0, 0, 0):
        return True
    if x2 <= x1 or y2 <= y1:
        problems.append(Problem("box_inverted", rec.image, f"box {list(rec.box)} is inverted or empty: expected "
                                "x2 > x1 and y2 > y1 (XYXY pixels), or 0 0 0 0 for a fully occluded target"))
        return False
    if size is not None:
        h, w = size
        if x1 < 0 or y1 < 0 or x2 > w or y2 > h:
            problems.append(Problem("box_outside", rec.image, f"box {list(rec.box)} leaves the {w}x{h} image: "
                                    f"expected 0 <= x1 < x2 <= {w} and 0 <= y1 < y2 <= {h}"))
            return False
    return True


def _fmt_view(v: int) -> str:
    x, y, z = (int(c) for c in view_coords(v))
    return f"({x:+d}, {y:+d}, {z})"


def _check_scene(sid, scene_dir, records, seen, size, problems) -> None:
    records[:] = [r for r in records if _check_box(r, size, problems)]
    targets = sorted({t for t, _ in seen}, key=TARGETS.index)
    if sid.kind == "context" and len(targets) > 1:
        counts = Counter(t for t, _ in seen)
        problems.append(Problem("two_targets", scene_dir, f"context scene holds {len(targets)} targets "
                                f"{dict(sorted(counts.items()))}; expected exactly one target per context"))
    for (target, view), paths in sorted(seen.items()):
        if len(paths) > 1:
            problems.append(Problem("duplicate_view", paths[0], f"view {view} {_fmt_view(view)} of {target} also "
                                    f"in {[p.name for p in paths[1:]]}; expected one image per view"))
    for target in targets:
        have = {v for t, v in seen if t == target}
        missing = [v for v in range(N_VIEWS) if v not in have]
        if missing:
            listed = ", ".join(view_stem(*view_coords(v), target, sid.name) for v in missing[:_MAX_LISTED])
            more = f" and {len(missing) - _MAX_LISTED} more" if len(missing) > _MAX_LISTED else ""
            problems.append(Problem("missing_views", scene_dir, f"{target}: {len(have)} of {N_VIEWS} views; "
                                    f"missing {len(missing)}: {listed}{more}"))

"""Parsers for UEVAVD box annotations in the formats the release might use.

A box is ``(x1, y1, x2, y2)`` int, XYXY crop pixels (the paper's ``[x_tl, y_tl, x_lr,
y_lr]``), ``(0, 0, 0, 0)`` meaning fully occluded. Values are taken as written (floats
are rounded to the nearest pixel); the reader checks them against the image.

Per image, beside the image with the same stem:

* ``.txt``: four numbers, whitespace- or comma-separated, optionally in brackets and
  optionally with a class name (``"10 20 30 40"``, ``"sedan,10,20,30,40"``);
* ``.json``: ``[x1, y1, x2, y2]``, ``{"bbox": [...]}``, ``{"box": ...}``, a dict with
  ``x1/y1/x2/y2`` or ``xmin/ymin/xmax/ymax`` keys, or a one-element list of those;
* ``.xml``: Pascal VOC (``<object><name>..</name><bndbox><xmin>..``); a VOC file
  without any ``<object>`` means the target is fully occluded.

Per scene, one table keyed by image file name (with or without extension):
``annotations.csv`` / ``.txt`` / ``.json`` (also ``boxes``, ``bboxes``, ``labels``,
``gt``): CSV with or without a header, text lines ``NAME x1 y1 x2 y2 [class]``, or JSON
``{NAME: box}`` / ``[{"image": NAME, "bbox": box}, ...]``.

Every parser raises :class:`AnnotationError` (a ``ValueError``) saying what it expected.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from .naming import IMAGE_EXTS

Box = tuple[int, int, int, int]
#: Per-image annotation extensions, in the order the reader prefers them.
ANNOTATION_EXTS: tuple[str, ...] = (".txt", ".json", ".xml")
#: Stems of per-scene annotation tables (compared lower-case) and their extensions.
ANNOTATION_TABLE_STEMS: tuple[str, ...] = ("annotations", "annotation", "boxes", "bboxes", "bbox", "labels", "gt")
ANNOTATION_TABLE_EXTS: tuple[str, ...] = (".csv", ".txt", ".json")

_BOX_KEYS = ("bbox", "box", "bndbox", "bounding_box", "boundingbox", "xyxy")
_LABEL_KEYS = ("label", "class", "category", "target", "name", "cls")
_NAME_KEYS = ("image", "file", "filename", "file_name", "image_name", "img", "path", "image_path", "stem")
_CORNER_KEYS = (
    ("x1", "y1", "x2", "y2"),
    ("xmin", "ymin", "xmax", "ymax"),
    ("x_tl", "y_tl", "x_lr", "y_lr"),
    ("left", "top", "right", "bottom"),
)
_EXPECTED = "expected four numbers x1 y1 x2 y2 (XYXY pixels; 0 0 0 0 = fully occluded)"
_NUMBER = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$")


class AnnotationError(ValueError):
    """An annotation that cannot be parsed; the message says what was expected."""


@dataclass(frozen=True)
class BoxAnnotation:
    """One target box ``(x1, y1, x2, y2)`` int XYXY pixels and the class name written
    beside it, if any (as written, not normalised)."""

    box: Box
    label: str | None = None


def is_annotation_table(name: str) -> bool:
    """Whether a file name is a per-scene annotation table (e.g. ``annotations.csv``)."""
    stem, ext = os.path.splitext(os.path.basename(str(name)))
    return ext.lower() in ANNOTATION_TABLE_EXTS and stem.lower() in ANNOTATION_TABLE_STEMS


def _to_int(value, where: str) -> int:
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise AnnotationError(f"{where}: {value!r} is not a number; {_EXPECTED}") from None
    if not math.isfinite(f):
        raise AnnotationError(f"{where}: {value!r} is not finite; {_EXPECTED}")
    return int(round(f))


def _box_from_values(values, where: str) -> Box:
    values = list(values)
    if len(values) != 4:
        raise AnnotationError(f"{where}: found {len(values)} number(s); {_EXPECTED}")
    x1, y1, x2, y2 = (_to_int(v, where) for v in values)
    return (x1, y1, x2, y2)


def parse_box_text(text: str, where: str = "annotation") -> BoxAnnotation:
    """Parse a per-image text annotation: four numbers, optional class name."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise AnnotationError(f"{where}: file is empty; {_EXPECTED}")
    if len(lines) > 1:
        raise AnnotationError(f"{where}: {len(lines)} non-empty lines, expected one box; {_EXPECTED}")
    tokens = [t for t in re.split(r"[\s,;]+", re.sub(r"[\[\](){}]", " ", lines[0])) if t]
    numbers = [t for t in tokens if _NUMBER.match(t)]
    words = [t for t in tokens if not _NUMBER.match(t)]
    if words and not all(re.fullmatch(r"[A-Za-z_-]+", w) for w in words):
        raise AnnotationError(f"{where}: cannot read {lines[0].strip()!r}; {_EXPECTED}")
    return BoxAnnotation(_box_from_values(numbers, where), " ".join(words) or None)


def parse_box_obj(obj, where: str = "annotation") -> BoxAnnotation:
    """Parse a decoded JSON annotation (list of four numbers, or a dict; see module doc)."""
    if isinstance(obj, list | tuple):
        if len(obj) == 1 and isinstance(obj[0], dict | list | tuple):
            return parse_box_obj(obj[0], where)
        if len(obj) == 4 and all(isinstance(v, int | float | str) for v in obj):
            return BoxAnnotation(_box_from_values(obj, where))
        raise AnnotationError(f"{where}: list of {len(obj)} item(s); {_EXPECTED}")
    if not isinstance(obj, dict):
        raise AnnotationError(f"{where}: {type(obj).__name__} value; {_EXPECTED}")
    lower = {str(k).lower(): v for k, v in obj.items()}
    label = next((lower[k] for k in _LABEL_KEYS if isinstance(lower.get(k), str)), None)
    for key in _BOX_KEYS:
        if key in lower:
            inner = parse_box_obj(lower[key], f"{where} [{key!r}]")
            return BoxAnnotation(inner.box, label if label is not None else inner.label)
    for keys in _CORNER_KEYS:
        if all(k in lower for k in keys):
            return BoxAnnotation(_box_from_values([lower[k] for k in keys], where), label)
    for key in ("objects", "annotations", "targets"):
        if isinstance(lower.get(key), list) and len(lower[key]) == 1:
            return parse_box_obj(lower[key][0], f"{where} [{key!r}]")
    raise AnnotationError(
        f"{where}: no box in keys {sorted(obj)[:8]}; expected 'bbox' or 'box' or x1/y1/x2/y2 "
        f"or xmin/ymin/xmax/ymax"
    )


def parse_voc_xml(text: str, where: str = "annotation") -> BoxAnnotation:
    """Parse a Pascal VOC annotation; no ``<object>`` means fully occluded."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise AnnotationError(f"{where}: not well-formed XML ({e}); expected Pascal VOC") from None
    objects = root.findall(".//object")
    if not objects:
        return BoxAnnotation((0, 0, 0, 0))
    if len(objects) > 1:
        raise AnnotationError(f"{where}: {len(objects)} <object> elements, expected one target")
    obj = objects[0]
    bnd = obj.find("bndbox")
    if bnd is None:
        raise AnnotationError(f"{where}: <object> without <bndbox>; expected Pascal VOC")
    values = []
    for tag in ("xmin", "ymin", "xmax", "ymax"):
        el = bnd.find(tag)
        if el is None or el.text is None:
            raise AnnotationError(f"{where}: <bndbox> lacks <{tag}>; expected xmin ymin xmax ymax")
        values.append(el.text.strip())
    name = obj.findtext("name")
    return BoxAnnotation(_box_from_values(values, where), name.strip() if name else None)


def read_box_file(path: str | Path) -> BoxAnnotation:
    """Read a per-image annotation file (``.txt``, ``.json`` or ``.xml``)."""
    where = str(path)
    try:
        with open(where, encoding="utf-8-sig") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as e:
        raise AnnotationError(f"{where}: cannot read ({e})") from None
    ext = os.path.splitext(where)[1].lower()
    if ext == ".txt":
        parts = text.split()
        if len(parts) == 4:  # the common "x1 y1 x2 y2" of integers, without the general parser
            try:
                x1, y1, x2, y2 = (int(p) for p in parts)
                return BoxAnnotation((x1, y1, x2, y2))
            except ValueError:
                pass
    if ext == ".json":
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as e:
            raise AnnotationError(f"{where}: not valid JSON ({e}); {_EXPECTED}") from None
        return parse_box_obj(obj, where)
    if ext == ".xml":
        return parse_voc_xml(text, where)
    return parse_box_text(text, where)


def row_image_stem(name: str) -> str:
    """The image stem a table row refers to: base name without an image extension."""
    base = re.split(r"[\\/]", str(name).strip())[-1]
    return base[: -len(Path(base).suffix)] if base.lower().endswith(IMAGE_EXTS) else base


def _rows_from_csv(text: str, where: str) -> list[tuple[str, str, object]]:
    rows = [r for r in csv.reader(io.StringIO(text)) if any(c.strip() for c in r)]
    if not rows:
        return []
    header = [c.strip().lower() for c in rows[0]]
    out = []
    if not any(_NUMBER.match(c) for c in header) and any(k in header for k in _NAME_KEYS):
        name_col = next(header.index(k) for k in _NAME_KEYS if k in header)
        for i, row in enumerate(rows[1:], start=2):
            rec = {h: c for j, (h, c) in enumerate(zip(header, row, strict=False)) if j != name_col}
            for key in _BOX_KEYS:
                if key in rec:
                    rec[key] = re.findall(r"[+-]?[\d.]+(?:[eE][+-]?\d+)?", rec[key])
            obj: object = rec
            name = row[name_col] if name_col < len(row) else ""
            out.append((name, f"{where} row {i}", obj))
        return out
    for i, row in enumerate(rows, start=1):
        out.append((row[0], f"{where} row {i}", ",".join(row[1:])))
    return out


def _rows_from_text(text: str, where: str) -> list[tuple[str, str, object]]:
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = re.match(r"^\s*(.*?\.(?:png|jpe?g))[\s,;]+(.*)$", line, re.IGNORECASE)
        if m:
            name, rest = m.group(1), m.group(2)
        else:
            name, _, rest = line.strip().replace(",", " ", 1).partition(" ")
        out.append((name, f"{where} line {i}", rest))
    return out


def _rows_from_json(obj, where: str) -> list[tuple[str, str, object]]:
    if isinstance(obj, dict):
        for key in ("annotations", "images", "items", "boxes"):
            if isinstance(obj.get(key), list | dict):
                return _rows_from_json(obj[key], where)
        return [(str(k), f"{where} [{k!r}]", v) for k, v in obj.items()]
    if isinstance(obj, list):
        out = []
        for i, item in enumerate(obj):
            if not isinstance(item, dict):
                raise AnnotationError(f"{where}: item {i} is not an object; expected {{'image': NAME, 'bbox': ...}}")
            lower = {str(k).lower(): v for k, v in item.items()}
            name = next((lower[k] for k in _NAME_KEYS if k in lower), None)
            if name is None:
                raise AnnotationError(f"{where}: item {i} names no image; expected one of keys {list(_NAME_KEYS)}")
            out.append((str(name), f"{where} item {i}", {k: v for k, v in lower.items() if k not in _NAME_KEYS}))
        return out
    raise AnnotationError(f"{where}: expected a JSON object keyed by image name or a list of records")


def read_annotation_table(path: Path) -> tuple[dict[str, BoxAnnotation], list[str]]:
    """Read a per-scene annotation table.

    Returns ``(boxes, errors)``: boxes keyed by image stem (see :func:`row_image_stem`), and
    one message per row that could not be parsed (naming the file and row). Raises
    :class:`AnnotationError` when the file as a whole cannot be read.
    """
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise AnnotationError(f"{where}: cannot read ({e})") from None
    ext = Path(path).suffix.lower()
    if ext == ".json":
        try:
            rows = _rows_from_json(json.loads(text), where)
        except json.JSONDecodeError as e:
            raise AnnotationError(f"{where}: not valid JSON ({e})") from None
    elif ext == ".csv":
        rows = _rows_from_csv(text, where)
    else:
        rows = _rows_from_text(text, where)
    boxes: dict[str, BoxAnnotation] = {}
    errors: list[str] = []
    for name, row_where, value in rows:
        key = row_image_stem(name)
        try:
            if not key:
                raise AnnotationError(f"{row_where}: no image name")
            ann = parse_box_text(value, row_where) if isinstance(value, str) else parse_box_obj(value, row_where)
        except AnnotationError as e:
            errors.append(str(e))
            continue
        if key in boxes:
            errors.append(f"{row_where}: second row for image {key!r}")
            continue
        boxes[key] = ann
    return boxes, errors

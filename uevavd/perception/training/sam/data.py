"""Ground-truth views for SAM training and evaluation, read through the dataset reader.

A :class:`GTViews` holds decoded views in memory: images (N, H, W, 3) uint8 RGB, seg
(N, H, W) uint16 instance ids, boxes (N, 4) int32 XYXY (x2, y2 exclusive, all zero =
fully occluded), and per view the id -> category table ("target" marks the target).
Views read from a dataset also carry their keys (``"<scene>/<target>/<view>"``) and how
they were drawn, so a checkpoint can record exactly which views it was trained on
(:func:`view_selection`) and an evaluation can leave them out (``load_views(exclude=)``).
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Mapping, Sequence, Set
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ....data.reader import read_dataset

BACKGROUND = ("none",)


@dataclass
class GTViews:
    images: np.ndarray
    seg: np.ndarray
    boxes: np.ndarray
    categories: list[Mapping[int, str]]
    splits: list[str | None] = field(default_factory=list)
    keys: list[str] = field(default_factory=list)  #: "<scene>/<target>/<view>" per view, when read from a dataset
    drawn: dict = field(default_factory=dict)  #: how load_views drew them: contexts, per_context, seed

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, idx: Sequence[int] | np.ndarray) -> GTViews:
        idx = np.asarray(idx, np.int64)
        return GTViews(self.images[idx], self.seg[idx], self.boxes[idx], [self.categories[i] for i in idx],
                       [self.splits[i] for i in idx] if self.splits else [],
                       [self.keys[i] for i in idx] if self.keys else [])

    def target_ids(self, i: int) -> np.ndarray:
        return np.array([k for k, v in self.categories[i].items() if v == "target"], np.int64)

    def target_mask(self, i: int) -> np.ndarray:
        """(H, W) bool ground-truth target pixels of view ``i``."""
        return np.isin(self.seg[i], self.target_ids(i))

    def object_ids(self, i: int) -> set[int]:
        """Instance ids of view ``i`` that are surrounding objects (not target, not "none")."""
        return {k for k, v in self.categories[i].items() if v != "target" and v not in BACKGROUND}

    def digest(self) -> str:
        """sha256 of the images, instance maps and boxes (what training saw)."""
        h = hashlib.sha256()
        for a in (self.images, self.seg, self.boxes):
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: cannot decode the image; expected an RGB PNG/JPEG")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _read_seg(path: Path) -> np.ndarray:
    seg = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if seg is None or seg.ndim != 2:
        raise ValueError(f"{path}: cannot decode the instance map; expected a single-channel uint16 PNG")
    return seg.astype(np.uint16)


def view_key(record) -> str:
    """``"<scene>/<target>/<view>"``: a view of a dataset, as training metadata names it."""
    return f"{record.scene}/{record.target}/{record.view}"


def view_selection(views: GTViews) -> dict:
    """The views' keys, grouped compactly for a checkpoint's metadata:
    ``{**views.drawn, "n": N, "views": {"<scene>/<target>": [view, ...]}}``; ``{}`` when
    the views were not read from a dataset (no keys)."""
    if not views.keys:
        return {}
    groups: dict[str, list[int]] = {}
    for k in views.keys:
        group, view = k.rsplit("/", 1)
        groups.setdefault(group, []).append(int(view))
    return {**views.drawn, "n": len(views.keys), "views": {g: sorted(v) for g, v in sorted(groups.items())}}


def selection_keys(selection: Mapping) -> set[str]:
    """The view keys of a :func:`view_selection` record (inverse of the grouping)."""
    return {f"{g}/{v}" for g, vs in (selection.get("views") or {}).items() for v in vs}


def load_views(manifest, *, contexts: Sequence[int], per_context: int, seed: int = 0,
               exclude: Set[str] = frozenset()) -> GTViews:
    """Up to ``per_context`` random views (with ground truth) of each of ``contexts`` in a
    :class:`uevavd.data.records.Manifest`, leaving out the views whose :func:`view_key` is
    in ``exclude`` (e.g. the views a model was trained on) before drawing. Views without
    an instance map are skipped; no such view at all is an error."""
    rng = np.random.default_rng(seed)
    by_scene: dict[str, list] = {}
    for r in manifest.select(contexts=list(contexts)):
        if r.seg is not None and (not exclude or view_key(r) not in exclude):
            by_scene.setdefault(r.scene, []).append(r)
    chosen = []
    for scene in sorted(by_scene):
        recs = by_scene[scene]
        take = rng.choice(len(recs), size=min(per_context, len(recs)), replace=False)
        chosen += [recs[i] for i in sorted(take)]
    if not chosen:
        raise ValueError(f"{manifest.root}: no views with ground-truth segmentation (seg/*.png) in contexts "
                         f"{list(contexts)}; expected a synthetic world (uevavd synth) or data with instance maps")
    cats = {s: manifest.categories(s) or {} for s in by_scene}
    images = np.stack([_read_rgb(r.image) for r in chosen])
    seg = np.stack([_read_seg(r.seg) for r in chosen])
    boxes = np.array([r.box for r in chosen], np.int32).reshape(-1, 4)
    return GTViews(images, seg, boxes, [cats[r.scene] for r in chosen], [r.split for r in chosen],
                   [view_key(r) for r in chosen],
                   {"contexts": sorted(int(c) for c in contexts), "per_context": int(per_context), "seed": int(seed)})


def read_manifest(root: str | Path):
    """The dataset under ``root`` (reader, unchecked: views that parse are used; problems
    are summarised on stderr)."""
    manifest = read_dataset(root, check=False)
    if manifest.problems:
        print(f"note: {len(manifest.problems)} problem(s) in {root} (first: {manifest.problems[0]}); "
              "using the views that parsed", file=sys.stderr)
    return manifest


def train_and_heldout_contexts(manifest) -> tuple[list[int], list[int]]:
    """(training context ids, held-out context ids): the train split, and the simple + hard
    test contexts when the data has them, else the last train context."""
    split = {r.context: r.split for r in manifest if r.context is not None}
    train_ids = sorted(c for c, s in split.items() if s == "train")
    test_ids = sorted(c for c, s in split.items() if s in ("simple", "hard"))
    if not train_ids:
        raise ValueError(f"{manifest.root}: no train-split contexts; expected a dataset with contexts 1-20, 31-50, ...")
    if not test_ids:
        if len(train_ids) < 2:
            raise ValueError(f"{manifest.root}: one train context and no test contexts; need two contexts to hold one out")
        train_ids, test_ids = train_ids[:-1], train_ids[-1:]
    return train_ids, test_ids


def split_heldout(root: str | Path, *, per_context: int, heldout_per_context: int, seed: int
                  ) -> tuple[GTViews, GTViews]:
    """(train views, held-out views) of the dataset under ``root``, from the contexts of
    :func:`train_and_heldout_contexts`; training views drawn with ``seed``, held-out ones
    with ``seed + 1``."""
    manifest = read_manifest(root)
    train_ids, test_ids = train_and_heldout_contexts(manifest)
    train = load_views(manifest, contexts=train_ids, per_context=per_context, seed=seed)
    held = load_views(manifest, contexts=test_ids, per_context=heldout_per_context, seed=seed + 1)
    return train, held


def views_from_arrays(rgb: np.ndarray, seg: np.ndarray, boxes: np.ndarray, categories: Mapping[int, str],
                      split: str | None = None) -> GTViews:
    """A :class:`GTViews` from in-memory arrays of one context (e.g. ``render_context``)."""
    n = len(rgb)
    return GTViews(np.asarray(rgb, np.uint8), np.asarray(seg, np.uint16), np.asarray(boxes, np.int32).reshape(n, 4),
                   [dict(categories)] * n, [split] * n)

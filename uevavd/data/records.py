"""The dataset manifest: one :class:`ViewRecord` per view, in a deterministic order.

Built by :func:`uevavd.data.reader.read_dataset`; everything downstream (perception,
the observation table) reads the dataset through a :class:`Manifest`.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .layout import CATEGORIES, SEG_DIR
from .naming import normalize_target
from .splits import TARGETS, resolve_split


@dataclass(frozen=True)
class ViewRecord:
    """One view of one target in one scene.

    ``box`` is ``(x1, y1, x2, y2)`` int XYXY crop pixels, x2/y2 exclusive, ``(0, 0, 0, 0)``
    when the target is fully occluded. ``xyz`` is the UAV position in metres (target at
    the origin); ``view`` its :mod:`uevavd.data.grid` index 0..604.
    """

    scene: str  # folder name as on disk ("001", "12", "00", "train_605")
    context: int | None  # 1..150 for context scenes, None for "00" / "train_605"
    split: str | None  # "train" / "simple" / "hard" for contexts, else None
    target: str  # canonical class name, one of splits.TARGETS
    view: int
    xyz: tuple[int, int, int]
    image: Path
    box: tuple[int, int, int, int]
    seg: Path | None  # instance-id PNG (uint16) where the data has one
    visible: float | None  # visible fraction where known

    @property
    def occluded(self) -> bool:
        """Fully occluded: the box is all zero."""
        return self.box == (0, 0, 0, 0)

    @property
    def target_index(self) -> int:
        """Class index of the target (position in ``splits.TARGETS``)."""
        return TARGETS.index(self.target)


class Manifest:
    """An immutable, ordered sequence of :class:`ViewRecord` with array views.

    ``root`` is the dataset root, ``image_size`` the common ``(H, W)`` of the images,
    ``scene_dirs`` maps scene name to its folder, ``problems`` holds what the reader
    could not use (empty after a checked read).
    """

    __slots__ = ("_root", "_records", "_image_size", "_scene_dirs", "_problems", "_cache")

    def __init__(
        self,
        root: str | Path,
        records: Iterable[ViewRecord],
        image_size: tuple[int, int],
        *,
        scene_dirs: dict[str, Path] | None = None,
        problems: Iterable = (),
    ):
        self._root = Path(root)
        self._records = tuple(records)
        self._image_size = (int(image_size[0]), int(image_size[1]))
        dirs = dict(scene_dirs or {})
        for r in self._records:
            dirs.setdefault(r.scene, r.image.parent)
        self._scene_dirs = {k: Path(v) for k, v in dirs.items()}
        self._problems = tuple(problems)
        self._cache: dict[str, np.ndarray] = {}

    # -- attributes -------------------------------------------------------------------
    @property
    def root(self) -> Path:
        return self._root

    @property
    def records(self) -> tuple[ViewRecord, ...]:
        return self._records

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) of every image."""
        return self._image_size

    @property
    def scene_dirs(self) -> dict[str, Path]:
        return dict(self._scene_dirs)

    @property
    def problems(self) -> tuple:
        return self._problems

    # -- sequence ---------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._records)

    def __iter__(self) -> Iterator[ViewRecord]:
        return iter(self._records)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return self._derive(self._records[i])
        return self._records[i]

    def __repr__(self) -> str:
        return (f"Manifest(root={str(self._root)!r}, records={len(self)}, scenes={len(self.scenes())}, "
                f"image_size={self._image_size})")

    def _derive(self, records: Iterable[ViewRecord]) -> Manifest:
        records = tuple(records)
        keep = {r.scene for r in records}
        return Manifest(self._root, records, self._image_size,
                        scene_dirs={k: v for k, v in self._scene_dirs.items() if k in keep})

    # -- queries ----------------------------------------------------------------------
    def scenes(self) -> list[str]:
        """Scene names in manifest order."""
        return list(dict.fromkeys(r.scene for r in self._records))

    def contexts(self) -> dict[int, str]:
        """Context id -> its target, sorted by id."""
        return {r.context: r.target for r in self._records if r.context is not None}

    def select(self, *, scenes=None, split=None, targets=None, contexts=None) -> Manifest:
        """The records matching every given filter, in the same order.

        ``scenes``: scene names as on disk; ``split``: "train", "simple", "hard" or an
        alias ("test", "hard_test"; selects context scenes only); ``targets``: names in
        any accepted spelling; ``contexts``: context ids. Unknown names raise ``ValueError``.
        """
        recs: Iterable[ViewRecord] = self._records
        if scenes is not None:
            wanted = {str(s) for s in ([scenes] if isinstance(scenes, str) else scenes)}
            unknown = wanted - set(self.scenes())
            if unknown:
                raise ValueError(f"unknown scene(s) {sorted(unknown)}: expected among {self.scenes()}")
            recs = [r for r in recs if r.scene in wanted]
        if split is not None:
            splits = set(resolve_split(split))
            recs = [r for r in recs if r.split in splits]
        if targets is not None:
            names = {normalize_target(t) for t in ([targets] if isinstance(targets, str) else targets)}
            recs = [r for r in recs if r.target in names]
        if contexts is not None:
            ids = {int(c) for c in ([contexts] if isinstance(contexts, int) else contexts)}
            recs = [r for r in recs if r.context in ids]
        return self._derive(recs)

    def categories(self, scene: str) -> dict[int, str] | None:
        """Instance id -> category name of a scene's segmentation, from
        ``seg/categories.json``; ``None`` where the scene has none."""
        if scene not in self._scene_dirs:
            raise ValueError(f"unknown scene {scene!r}: expected among {self.scenes()}")
        path = self._scene_dirs[scene] / SEG_DIR / CATEGORIES
        if not path.is_file():
            return None
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
            return {int(k): str(v) for k, v in raw.items()}
        except (ValueError, AttributeError) as e:
            raise ValueError(f"{path}: cannot read categories ({e}); expected "
                             '{"<instance id>": "<category>", ...}') from None

    def index(self, scene: str, target: str, view: int) -> int:
        """Position of the record (scene, target, view); ``KeyError`` if absent."""
        lookup = self._cache.get("_index")
        if lookup is None:
            lookup = {(r.scene, r.target, r.view): i for i, r in enumerate(self._records)}
            self._cache["_index"] = lookup  # type: ignore[assignment]
        key = (str(scene), normalize_target(target), int(view))
        if key not in lookup:
            raise KeyError(f"no record for scene {scene!r}, target {target!r}, view {view}")
        return lookup[key]  # type: ignore[index]

    # -- arrays (cached, read-only) -----------------------------------------------------
    def _array(self, name: str, build) -> np.ndarray:
        arr = self._cache.get(name)
        if arr is None:
            arr = build()
            arr.setflags(write=False)
            self._cache[name] = arr
        return arr

    def boxes(self) -> np.ndarray:
        """(N, 4) int32 XYXY pixels, x2/y2 exclusive; all zero = fully occluded."""
        return self._array("boxes", lambda: np.array([r.box for r in self._records], np.int32).reshape(-1, 4))

    def views(self) -> np.ndarray:
        """(N,) int64 view indices 0..604."""
        return self._array("views", lambda: np.array([r.view for r in self._records], np.int64))

    def xyz(self) -> np.ndarray:
        """(N, 3) int64 UAV positions in metres."""
        return self._array("xyz", lambda: np.array([r.xyz for r in self._records], np.int64).reshape(-1, 3))

    def targets(self) -> np.ndarray:
        """(N,) int64 class indices (positions in ``splits.TARGETS``)."""
        return self._array("targets", lambda: np.array([TARGETS.index(r.target) for r in self._records], np.int64))

    def context_ids(self) -> np.ndarray:
        """(N,) int64 context ids, 0 for the non-context scenes ("00", "train_605")."""
        return self._array("context_ids", lambda: np.array([r.context or 0 for r in self._records], np.int64))

    def occluded(self) -> np.ndarray:
        """(N,) bool: the box is all zero."""
        return self._array("occluded", lambda: ~self.boxes().any(axis=1))

    def visible(self) -> np.ndarray:
        """(N,) float32 visible fraction, NaN where unknown."""
        return self._array("visible", lambda: np.array(
            [np.nan if r.visible is None else r.visible for r in self._records], np.float32))

    def images(self) -> list[Path]:
        """Image paths in record order."""
        return [r.image for r in self._records]


#: Problems that name a file the reader could not use, without making the views it read
#: wrong: reported by ``uevavd validate``, logged (not raised) by :func:`read_dataset`.
UNUSED_FILE_KINDS: frozenset[str] = frozenset({"orphan_annotation", "unparseable_annotation_name", "unknown_file"})


@dataclass(frozen=True)
class Problem:
    """One problem found in a dataset: a ``kind`` (e.g. "missing_annotation"), the file
    or folder it concerns, and a message saying what was expected."""

    kind: str
    path: Path
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"

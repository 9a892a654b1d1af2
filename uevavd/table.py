"""The observation table: the hand-off between perception and reinforcement learning.

For one dataset and one perception config, arrays over (scene, view):

* ``features`` (S, 605, D) float16: encoder features of the (possibly decomposed) view
* ``probs`` (S, 605, K) float32: classifier probabilities on the *raw* view, K = 5 classes
* ``boxes`` (S, 605, 4) float32: target box XYXY normalised by (W, H, W, H) to [0, 1];
  all zero when the target is fully occluded
* ``visible`` (S, 605) float32: visible fraction of the target, NaN where unknown

plus per-scene ``scenes`` (names), ``contexts`` (ids), ``targets`` (class indices),
``splits``, and ``meta`` (config, key, versions). On disk a table is a folder
``<key>/`` of ``.npy`` files and ``meta.json``, written into a temporary folder and
renamed into place, so a reader never sees a half-written table. Arrays load
memory-mapped, so an environment step is an array lookup.

Integrity: values (finite, probabilities summing to 1, boxes in [0, 1]) are checked in
full once, when a table is built (:meth:`ObservationTable.from_arrays`) and written
(:meth:`ObservationTable.save`). ``save`` records each array file's size, modification
time (set one second back, so that any later write, however soon, gives another one) and
sha256 in ``meta.json``. :meth:`ObservationTable.load` re-checks the small arrays (probs,
boxes, visible) in full and the features only by ``stat``: a features file whose size or
time differs from the record is hashed and scanned before it is served, so loading an
untouched table never reads the features. :meth:`ObservationTable.verify` hashes and
scans everything.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_dir, short_writes_named
from .data.grid import N_VIEWS
from .data.splits import SPLITS, TARGETS, VALIDATION, block_of, first_per_block, resolve_split
from .hashing import arrays_sha256, file_sha256, json_digest
from .paths import tables_dir
from .version import __version__

SCHEMA_VERSION = 1
ARRAYS = ("features", "probs", "boxes", "visible")
META_FILE = "meta.json"


class TableError(ValueError):
    """An observation table is invalid, stale or of another schema; the message says why."""


#: Arrays small enough to check in full on every load (features are checked by stat + record).
SMALL_ARRAYS = ("probs", "boxes", "visible")
#: Value checks that save/from_arrays run in full, recorded in meta.json.
CHECKS = ("shapes", "finite features, probs and boxes", "probs sum to 1", "boxes in [0, 1]")
_BACKDATE_NS = 10**9


def _meta_digest(meta: dict) -> str:
    """sha256 of a table's metadata (without its own digest), as JSON with sorted keys."""
    return json_digest({k: v for k, v in meta.items() if k != "meta_sha256"})


@dataclass(frozen=True)
class ObservationTable:
    """Perception outputs over (scene, view). Build with :meth:`from_arrays` or :meth:`load`."""

    features: np.ndarray
    probs: np.ndarray
    boxes: np.ndarray
    visible: np.ndarray
    scenes: tuple[str, ...]
    contexts: np.ndarray  #: (S,) int64 context ids (0 for scenes that are not contexts)
    targets: np.ndarray  #: (S,) int64 class index into ``class_names``
    splits: tuple[str, ...]  #: (S,) "train" / "simple" / "hard"
    meta: Mapping[str, Any] = field(default_factory=dict)
    path: Path | None = None

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        features: np.ndarray,
        probs: np.ndarray,
        boxes: np.ndarray,
        *,
        scenes: Sequence[str],
        targets: Sequence[int] | Sequence[str],
        splits: Sequence[str],
        contexts: Sequence[int] | None = None,
        visible: np.ndarray | None = None,
        class_names: Sequence[str] = TARGETS,
        config: Mapping[str, Any] | None = None,
        key: str | None = None,
    ) -> ObservationTable:
        """Build a table from your own perception outputs (shapes as in the module doc).

        ``targets`` are class indices or names; ``key`` defaults to a hash of the arrays
        and config. Everything is validated (shapes, dtypes, NaN/inf, probabilities).
        """
        features = np.asarray(features, dtype=np.float16)
        probs = np.asarray(probs, dtype=np.float32)
        boxes = np.asarray(boxes, dtype=np.float32)
        n = features.shape[0] if features.ndim else 0
        visible = (
            np.full((n, N_VIEWS), np.nan, np.float32) if visible is None else np.asarray(visible, np.float32)
        )
        class_names = tuple(class_names)
        tgt = np.array(
            [class_names.index(t) if isinstance(t, str) else int(t) for t in targets], dtype=np.int64
        )
        ctx = np.zeros(n, np.int64) if contexts is None else np.asarray(contexts, dtype=np.int64)
        config = dict(config or {})
        meta = {
            "schema_version": SCHEMA_VERSION,
            "class_names": list(class_names),
            "config": config,
            "key": key or arrays_sha256(features, probs, boxes, visible, n=16)
            + json_digest(config, 8),
            "versions": _versions(),
        }
        table = cls(features, probs, boxes, visible, tuple(scenes), ctx, tgt, tuple(splits), meta)
        table.check()
        return table

    # -- validation -------------------------------------------------------------------------
    def check(self, where: str = "table", *, values: bool = True) -> None:
        """Raise :class:`TableError` naming the problem unless the table is consistent.

        ``values=False`` checks shapes and metadata only (no pass over the arrays)."""
        s = len(self.scenes)
        f, p, b, v = self.features, self.probs, self.boxes, self.visible
        if f.ndim != 3 or f.shape[:2] != (s, N_VIEWS):
            raise TableError(f"{where}: features have shape {f.shape}; expected ({s}, {N_VIEWS}, D)")
        k = len(self.class_names)
        if p.shape != (s, N_VIEWS, k):
            raise TableError(f"{where}: probs have shape {p.shape}; expected ({s}, {N_VIEWS}, {k})")
        if b.shape != (s, N_VIEWS, 4):
            raise TableError(f"{where}: boxes have shape {b.shape}; expected ({s}, {N_VIEWS}, 4)")
        if v.shape != (s, N_VIEWS):
            raise TableError(f"{where}: visible has shape {v.shape}; expected ({s}, {N_VIEWS})")
        for name, arr in (("targets", self.targets), ("contexts", self.contexts)):
            if arr.shape != (s,):
                raise TableError(f"{where}: {name} has shape {arr.shape}; expected ({s},)")
        if len(self.splits) != s:
            raise TableError(f"{where}: {len(self.splits)} splits for {s} scenes")
        bad = sorted(set(self.splits) - set(SPLITS))
        if bad:
            raise TableError(f"{where}: unknown split(s) {bad}; expected among {list(SPLITS)}")
        if s and (self.targets.min() < 0 or self.targets.max() >= k):
            raise TableError(f"{where}: target class index out of 0..{k - 1}")
        if values:
            self._check_values(where, ("features", "probs", "boxes"))

    def _check_values(self, where: str, names: Sequence[str]) -> None:
        """Full pass over the named arrays: finite; probabilities sum to 1; boxes in [0, 1]."""
        s = len(self.scenes)
        for name in names:
            if name == "visible":  # NaN means unknown there
                continue
            arr = getattr(self, name)
            finite = np.isfinite(arr).all(axis=tuple(range(1, arr.ndim)))
            if not finite.all():
                i = int(np.flatnonzero(~finite)[0])
                raise TableError(
                    f"{where}: {name} contain NaN or inf (first in scene {self.scenes[i]!r}); "
                    "rebuild the table (`uevavd prepare`) or fix the arrays passed to from_arrays"
                )
        if s and "probs" in names and not np.allclose(self.probs.sum(-1), 1.0, atol=1e-3):
            raise TableError(f"{where}: class probabilities do not sum to 1 over the last axis")
        if s and "boxes" in names and (self.boxes.min() < 0 or self.boxes.max() > 1):
            raise TableError(f"{where}: boxes must be normalised to [0, 1] (XYXY / (W, H, W, H))")

    def verify(self) -> ObservationTable:
        """Full check of a loaded table: every array file's sha256 against the record made
        when it was written, and every value (finite, probabilities, boxes). Reads all data;
        :meth:`load` does not. Returns the table; raises :class:`TableError`."""
        if self.path is None:
            self.check()
            return self
        files = dict(self.meta.get("integrity", {}).get("files", {}))
        for name in ARRAYS:
            f = self.path / f"{name}.npy"
            rec = files.get(f.name)
            if rec is None:
                raise TableError(f"{self.path}: no integrity record for {f.name} in {META_FILE} (written by an "
                                 "older uevavd); values are still checked, but a checksum cannot be")
            if file_sha256(f) != rec["sha256"]:
                raise TableError(f"{f}: sha256 differs from the one recorded when the table was written; "
                                 "the file was changed or damaged: rebuild the table")
        self.check(where=str(self.path))
        return self

    # -- accessors --------------------------------------------------------------------------
    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(self.meta.get("class_names", TARGETS))

    @property
    def key(self) -> str:
        return str(self.meta.get("key", ""))

    @property
    def feature_dim(self) -> int:
        return int(self.features.shape[2])

    @property
    def perception_identity(self) -> dict[str, Any]:
        """What made the table's numbers apart from the dataset: the identities of its
        segmenter, decomposition, encoder and classifier (with their weights hashes) and the
        schema, i.e. the table key's parts without the dataset fingerprint. A policy trained
        on one table may act on another table of the same identity (another dataset root,
        another split); ``{}`` for tables made with ``from_arrays``."""
        parts = (self.meta.get("config") or {}).get("key_parts") or {}
        return {k: v for k, v in sorted(parts.items()) if k != "dataset"}

    def __len__(self) -> int:
        return len(self.scenes)

    def scene_indices(self, split: str) -> np.ndarray:
        """(n,) int64 indices of the scenes in a split or alias ("train", "test", ...)."""
        wanted = set(resolve_split(split))
        return np.array([i for i, s in enumerate(self.splits) if s in wanted], dtype=np.int64)

    # -- selection --------------------------------------------------------------------------
    def select(self, split: str, contexts: Any = None, *, train_per_block: int = 0,
               holdout_block: int = 0) -> np.ndarray:
        """(n,) int64 scene indices of ``split``, optionally only the given context ids: the
        scenes an env, a trainer or an evaluation of that split serves.

        ``train_per_block`` (``EnvConfig.train_per_block``; 0 = all) keeps of the split's
        training contexts the first N of each block, by id; ``holdout_block``
        (``EnvConfig.holdout_block``; 0 = none) drops the training contexts of that target
        block (1..5) whole; test contexts are never dropped.
        ``split="validation"`` (:data:`~uevavd.data.splits.VALIDATION`) is the other training
        contexts: those a run with these settings never trains on.
        Raises :class:`TableError` when the selection is empty (a table without contexts of
        that split) or a block holds fewer than ``train_per_block`` training contexts, and
        ``ValueError`` naming context ids that are not in the split.
        """
        if split == VALIDATION:
            idx = self._validation(train_per_block, holdout_block)
        else:
            idx = self._trained(split, train_per_block, holdout_block)
        if contexts is not None:
            wanted = [int(c) for c in np.atleast_1d(np.asarray(contexts))]
            have = {int(self.contexts[i]): int(i) for i in idx}
            missing = [c for c in wanted if c not in have]
            if missing:
                raise ValueError(f"context(s) {missing} are not in split {split!r} of table {self.key!r}; "
                                 f"its contexts there are {sorted(have)}")
            idx = np.array([have[c] for c in wanted], dtype=np.int64)
        if idx.size == 0:
            raise TableError(f"table {self.key!r} has no scenes in split {split!r} (splits present: "
                             f"{sorted(set(self.splits))}); build the table over contexts of that split")
        return idx

    def _trained(self, split: str, train_per_block: int, holdout_block: int = 0) -> np.ndarray:
        """The scenes of ``split``, its training contexts less those of ``holdout_block`` (0:
        none) and cut to the first ``train_per_block`` of each block (0 = all)."""
        idx = self.scene_indices(split)
        is_train = np.asarray(self.splits)[idx] == "train"
        if holdout_block:
            held = np.array([block_of(int(c)) + 1 == holdout_block for c in self.contexts[idx]], bool)
            if split == "train" and is_train.any() and (is_train <= held).all():  # every training context held out
                raise TableError(f"env.holdout_block = {holdout_block} holds out every training context of table "
                                 f"{self.key!r} (all lie in target block {holdout_block}): choose another block, or "
                                 "0 for none")
            idx, is_train = idx[~(is_train & held)], is_train[~(is_train & held)]
        if not train_per_block:
            return idx
        try:
            keep = set(first_per_block(self.contexts[idx[is_train]], train_per_block))
        except ValueError as exc:
            raise TableError(f"env.train_per_block = {train_per_block}: {exc} (table {self.key!r}); build "
                             "the table over a world with more training contexts, or lower it") from None
        return idx[~is_train | np.isin(self.contexts[idx], sorted(keep))]

    def _validation(self, train_per_block: int, holdout_block: int = 0) -> np.ndarray:
        """The training scenes a run with these settings leaves out: those past the first
        ``train_per_block`` of each block, and every one of ``holdout_block``."""
        if not (train_per_block or holdout_block):
            raise TableError("split 'validation' is the training contexts a run leaves out of its training: set "
                             "env.train_per_block (e.g. 16 of the 20 per block) or env.holdout_block (a target "
                             "block, 1..5) to hold some out")
        idx = self.scene_indices("train")
        idx = idx[~np.isin(idx, self._trained("train", train_per_block, holdout_block))]
        if idx.size == 0:
            raise TableError(f"env.train_per_block = {train_per_block} and env.holdout_block = {holdout_block} "
                             f"leave no training context of table {self.key!r} out: nothing to validate on")
        return idx

    def true_class_probs(self) -> np.ndarray:
        """(S, 605) float32: the recognizer's probability for each scene's true class, per
        view. Whether a view counts as recognised is the env's rule,
        :meth:`uevavd.env.config.EnvConfig.recognized` (above ``thre``)."""
        return np.take_along_axis(self.probs, self.targets[:, None, None], axis=2)[..., 0]

    def argmax_correct(self) -> np.ndarray:
        """(S, 605) bool: argmax of the probabilities is the true class (accuracy)."""
        return self.probs.argmax(-1) == self.targets[:, None]

    def describe(self) -> str:
        """One line: the key, the scenes per split, the feature width and the perception config."""
        counts = {s: sum(1 for x in self.splits if x == s) for s in SPLITS}
        return (
            f"ObservationTable {self.key}: {len(self)} scenes {counts}, features "
            f"{self.features.shape[2]}-d {self.features.dtype}, classes {list(self.class_names)}"
        )

    # -- disk -------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write to folder ``path`` atomically (temp folder + rename). Returns the path."""
        path = Path(path)
        self.check(where=str(path))  # the one full pass over the values; load trusts the record
        with atomic_dir(path) as tmp, short_writes_named(path.parent):
            files = {}
            for name in ARRAYS:
                f = tmp / f"{name}.npy"
                with open(f, "wb") as fh:
                    np.save(fh, np.ascontiguousarray(getattr(self, name)))
                    fh.flush()
                    os.fsync(fh.fileno())
                # Back-date the file: any later write sets the time to "now", never to this.
                st = f.stat()
                os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns - _BACKDATE_NS))
                st = f.stat()
                files[f.name] = {"bytes": st.st_size, "mtime_ns": st.st_mtime_ns, "ctime_ns": st.st_ctime_ns,
                                 "sha256": file_sha256(f)}
            meta = dict(self.meta)
            meta.update(
                scenes=list(self.scenes),
                contexts=self.contexts.tolist(),
                targets=self.targets.tolist(),
                splits=list(self.splits),
                shapes={n: list(getattr(self, n).shape) for n in ARRAYS},
                integrity={"checked": list(CHECKS), "files": files},
            )
            meta["meta_sha256"] = _meta_digest(meta)
            with open(tmp / META_FILE, "w", encoding="utf-8") as fh:
                json.dump(meta, fh, indent=1, sort_keys=True)
                fh.flush()
                os.fsync(fh.fileno())
        return path

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], *, expect_key: str | None = None, mmap: bool = True
    ) -> ObservationTable:
        """Load a table folder (memory-mapped). Refuses another schema, another key, or NaN.

        Cheap: the small arrays are checked in full, the features by their file's size and
        modification time against the record written by :meth:`save` (hashed and scanned
        only when those differ, or when the table has no record). :meth:`verify` checks all."""
        path = Path(path)
        meta = _read_meta(path, expect_key)
        arrays = {}
        for name in ARRAYS:
            f = path / f"{name}.npy"
            if not f.is_file():
                raise TableError(f"{path}: missing {f.name}; the table is incomplete, rebuild it")
            try:
                arrays[name] = np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
            except (ValueError, EOFError, OSError) as exc:  # truncated, empty or not .npy
                raise TableError(f"{f}: unreadable array ({type(exc).__name__}: {exc or 'empty file'}); rebuild the "
                                 "table (`uevavd prepare` rebuilds it)") from None
            if list(arrays[name].shape) != meta.get("shapes", {}).get(name, list(arrays[name].shape)):
                raise TableError(f"{f}: shape {arrays[name].shape} disagrees with {META_FILE}; rebuild it")
        table = cls(
            scenes=tuple(meta.pop("scenes")),
            contexts=np.asarray(meta.pop("contexts"), np.int64),
            targets=np.asarray(meta.pop("targets"), np.int64),
            splits=tuple(meta.pop("splits")),
            meta=meta,
            path=path,
            **arrays,
        )
        table.check(where=str(path), values=False)
        table._check_values(str(path), SMALL_ARRAYS)
        table._check_files()
        return table

    def _check_files(self) -> None:
        """Each array file of a loaded table against the record :meth:`save` wrote with it."""
        records = self.meta.get("integrity", {}).get("files", {})
        for name in ARRAYS:
            f = self.path / f"{name}.npy"
            rec = records.get(f.name)
            if name in SMALL_ARRAYS:  # a few MB: their digest, on every load (values in range can be wrong)
                if rec is not None and file_sha256(f) != rec["sha256"]:
                    raise TableError(f"{f}: changed since the table was written (sha256 differs from {META_FILE}); "
                                     "rebuild the table, or write changed arrays with from_arrays(...).save()")
                continue
            if rec is not None:
                st = f.stat()
                if st.st_size != rec["bytes"]:
                    raise TableError(f"{f}: {st.st_size} bytes but {rec['bytes']} when the table was written; "
                                     "the file was truncated or replaced: rebuild the table")
                # untouched since save, which checked its values: its mtime, and its ctime, which no
                # one can set back (a write with the mtime restored changes it); a copied table is
                # hashed once per load
                if st.st_mtime_ns == rec["mtime_ns"] and st.st_ctime_ns == rec.get("ctime_ns", st.st_ctime_ns):
                    continue
            # No record (an older table) or changed since written: scan it, then compare its hash.
            self._check_values(str(self.path), (name,))
            if rec is not None and file_sha256(f) != rec["sha256"]:
                raise TableError(f"{f}: changed since the table was written (sha256 differs from {META_FILE}); "
                                 "rebuild the table, or write changed arrays with from_arrays(...).save()")


def _read_meta(path: Path, expect_key: str | None) -> dict[str, Any]:
    """A table folder's ``meta.json``, checked: its schema, its own digest, the per-scene keys
    and (where given) the expected table key; its digest removed."""
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise TableError(f"{path} is not an observation table (no {META_FILE}); build one with `uevavd prepare`")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except ValueError as exc:  # not JSON, or not UTF-8
        raise TableError(f"{meta_path}: unreadable metadata ({exc}); rebuild the table") from None
    if not isinstance(meta, dict):
        raise TableError(f"{meta_path}: expected a JSON object; rebuild the table")
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise TableError(f"{path}: table schema version {version} but this uevavd reads version {SCHEMA_VERSION}; "
                         "rebuild it with `uevavd prepare`")
    digest = meta.pop("meta_sha256", None)
    if digest is None or digest != _meta_digest(meta):  # every table of this schema is written with one
        raise TableError(f"{meta_path} was changed after the table was written (its scenes, targets, splits or "
                         "config no longer match their checksum, or the checksum was removed): rebuild the "
                         "table with `uevavd prepare`")
    missing = [k for k in ("scenes", "contexts", "targets", "splits") if k not in meta]
    if missing:
        raise TableError(f"{meta_path}: no {', '.join(missing)}; rebuild the table with `uevavd prepare`")
    if expect_key is not None and meta.get("key") != expect_key:
        raise TableError(f"{path}: table key {meta.get('key')} does not match the expected {expect_key} "
                         "(it was built from other inputs or another config); rebuild it")
    return meta

def load_table(table: ObservationTable | str | os.PathLike[str]) -> ObservationTable:
    """An :class:`ObservationTable`, or one loaded (and checked, NaN refused) from a folder, or
    by its key from ``$UEVAVD_CACHE/tables`` where no such folder exists (a portable name:
    Minari datasets' environment specs hold the key, not a machine's path)."""
    if isinstance(table, ObservationTable):
        return table
    if isinstance(table, str | os.PathLike):
        path = Path(table)
        if not path.exists() and len(path.parts) == 1:  # a key: the cache's copy, or how to make one
            if not (tables_dir() / path).is_dir():
                raise TableError(f"table {path} is neither a folder nor in the table cache {tables_dir()}: rebuild it "
                                 "with `uevavd prepare` (the same data and method give the same key) or copy it there")
            path = tables_dir() / path
        return ObservationTable.load(path)
    raise TypeError(f"table={table!r}: expected an ObservationTable or the path of a table folder")


def select_scenes(table: ObservationTable, split: str, contexts: Any = None, *, train_per_block: int = 0,
                  holdout_block: int = 0) -> np.ndarray:
    """``table.select(...)`` (:meth:`ObservationTable.select`), for ``uevavd.env.select_scenes``."""
    return table.select(split, contexts, train_per_block=train_per_block, holdout_block=holdout_block)


def _versions() -> dict[str, str]:
    out = {"uevavd": __version__, "numpy": np.__version__}
    try:  # torch is optional for tables built from arrays
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover
        pass
    return out

"""Inputs of the Fig. 8 strips: the trajectories to draw and the crops along them.

``trajectories.json`` is a list of greedy episodes ({"method", "seed", "setting",
"scene", "context", "split", "start_view", "views", "actions", "recognized",
"correct", "return"}). The crops are found through the dataset reader
(:func:`uevavd.data.reader.read_dataset`) and, failing that, by the canonical file name
(:func:`uevavd.data.layout.view_stem`) under ``data_root/<scene>/``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ..data.grid import N_VIEWS, view_coords
from ..data.layout import IMAGE_EXT, view_stem
from ..data.reader import read_dataset
from .report_data import order_methods

_REQUIRED = ("method", "views")


def load_trajectories(path: Path) -> tuple[list[dict], str]:
    """The trajectories to draw and a note for the report.

    Keeps the default setting (or, without one, the first setting), prefers the hard
    split, and one episode per method (the lowest seed), in report order. Returns
    ``([], reason)`` when the file is missing or empty. Raises ``ValueError`` naming the
    file for malformed content.
    """
    path = Path(path)
    if not path.is_file():
        return [], f"No `{path.name}` in the ablation directory: the strips were not drawn."
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as e:
        raise ValueError(f"{path}: not valid JSON ({e}); expected a list of episodes") from None
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list of episodes, got {type(data).__name__}")
    for i, t in enumerate(data):
        if not isinstance(t, dict) or any(k not in t for k in _REQUIRED):
            raise ValueError(f"{path}: episode {i} lacks {list(_REQUIRED)}; expected dicts with "
                             "method, seed, setting, scene, context, split, start_view, views, actions, ...")
        views = t["views"]
        if not views or any(not isinstance(v, int) or not 0 <= v < N_VIEWS for v in views):
            raise ValueError(f"{path}: episode {i} ({t['method']}) has views {views!r}; expected a non-empty "
                             f"list of view indices 0..{N_VIEWS - 1}")
    if not data:
        return [], f"`{path.name}` holds no episodes: the strips were not drawn."
    settings = [t.get("setting", "default") for t in data]
    setting = "default" if "default" in settings else settings[0]
    chosen = [t for t in data if t.get("setting", "default") == setting]
    if any(t.get("split") == "hard" for t in chosen):
        chosen = [t for t in chosen if t.get("split") == "hard"]
    best: dict[str, dict] = {}
    for t in chosen:
        m = t["method"]
        if m not in best or int(t.get("seed", 0)) < int(best[m].get("seed", 0)):
            best[m] = t
    out = [best[m] for m in order_methods(best)]
    starts = {(t.get("scene"), t.get("start_view")) for t in out}
    note = ""
    if len(starts) > 1:
        note = f"Note: the episodes do not share one start (scene, start view): {sorted(map(str, starts))}."
    return out, note


class CropLookup:
    """``lookup(traj, view) -> (H, W, 3) uint8 RGB or None``; counts what it cannot find
    (``missing``) and says where it looked (``source``)."""

    def __init__(self, data_root: str | Path | None, scenes: set[str]):
        self.missing = 0
        self.root = Path(data_root) if data_root else None
        self._index: dict[tuple[str, int], Path] = {}
        self._by_context: dict[tuple[int, int], Path] = {}
        if self.root is None:
            self.source = "nowhere (ablation.json names no data_root)"
        elif not self.root.is_dir():
            self.source = f"nowhere (data_root `{self.root}` does not exist)"
        else:
            self.source = f"`{self.root}` by canonical file name"
            try:
                manifest = read_dataset(self.root, check=False)
                for rec in manifest:
                    if rec.scene in scenes or str(rec.context) in scenes:
                        self._index[(rec.scene, rec.view)] = rec.image
                        if rec.context is not None:
                            self._by_context[(rec.context, rec.view)] = rec.image
                if self._index:
                    self.source = f"`{self.root}` through the dataset reader"
            except (ImportError, ValueError, OSError):
                pass  # the canonical names below still work

    def _find(self, traj: dict, view: int) -> Path | None:
        scene = str(traj.get("scene", ""))
        hit = self._index.get((scene, view))
        if hit is None and traj.get("context") is not None:
            hit = self._by_context.get((int(traj["context"]), view))
        if hit is not None or self.root is None:
            return hit
        x, y, z = view_coords(view)
        folder = self.root / scene
        if folder.is_dir():
            for p in sorted(folder.glob(view_stem(x, y, z, "*", scene) + IMAGE_EXT)):
                return p
        return None

    def __call__(self, traj: dict, view: int) -> np.ndarray | None:
        path = self._find(traj, view)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR) if path is not None else None
        if img is None:
            self.missing += 1
            return None
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def strip_images(trajectories: list[dict], data_root: str | Path | None) -> CropLookup:
    """A :class:`CropLookup` over the scenes of ``trajectories``."""
    scenes = {str(t.get("scene")) for t in trajectories} | {str(t.get("context")) for t in trajectories}
    return CropLookup(data_root, scenes)

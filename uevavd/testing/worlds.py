"""A tiny UEVAVD-layout world drawn in numpy (16 px crops, a few seconds to write).

Each class is a rectangle of its own shape and colour on a noisy background; context
views carry an occluding gray band whose height grows with the view index, with exact
instance maps (1 = target, 2 = building band, 3 = ground patch, 0 = none) and visible
fractions in ``scene.json``. ``train_605`` holds the unoccluded crops of the five classes.
Tests of the whole pipeline (reader -> classifier -> table -> training -> ablation) run on it:

    from uevavd.testing.worlds import write_tiny_world
    root = write_tiny_world(tmp_path, contexts=(1, 26, 31, 56), train605=True)
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from ..data.grid import N_VIEWS, view_coords
from ..data.layout import view_stem
from ..data.splits import TARGETS

SIZE = 16
#: per class: (half height, half width, RGB)
SHAPES = [(2, 6, (200, 60, 60)), (5, 5, (60, 200, 60)), (6, 2, (60, 60, 200)), (3, 3, (200, 200, 60)),
          (4, 7, (200, 60, 200))]


def draw_view(cls: int, view: int, occlude: bool, rng) -> tuple[np.ndarray, np.ndarray, tuple, float]:
    """``(rgb (S, S, 3) uint8, instance map (S, S) uint16, box, visible fraction)``."""
    img = rng.integers(0, 80, (SIZE, SIZE, 3), dtype=np.uint8)
    seg = np.zeros((SIZE, SIZE), np.uint16)
    seg[SIZE - 4 :, : SIZE // 2] = 3
    hh, hw, rgb = SHAPES[cls]
    c = SIZE // 2
    target = np.zeros((SIZE, SIZE), bool)
    target[c - hh : c + hh, c - hw : c + hw] = True
    img[target] = rgb
    seg[target] = 1
    band = (view % 9) * 2 if occlude else 0  # rows covered from the top
    if band:
        img[:band] = 128
        seg[:band] = 2
    vis_mask = target.copy()
    vis_mask[:band] = False
    visible = float(vis_mask.sum() / target.sum())
    ys, xs = np.nonzero(vis_mask)
    box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1) if len(xs) else (0, 0, 0, 0)
    return img, seg, box, visible


def write_tiny_world(root: str | os.PathLike[str], contexts=(1, 31), train605: bool = True, seed: int = 0) -> Path:
    """A tiny UEVAVD-layout world in ``root`` (16 px views of ``contexts``, and ``train_605``
    when asked); returns ``root`` as a Path."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    scenes = [(f"{c:03d}", [TARGETS[(c - 1) // 30]], True) for c in contexts]
    if train605:
        scenes.append(("train_605", list(TARGETS), False))
    for scene, targets, occlude in scenes:
        d = root / scene
        (d / "seg").mkdir(parents=True, exist_ok=True)
        visible = {}
        for target in targets:
            cls = TARGETS.index(target)
            for v in range(N_VIEWS):
                stem = view_stem(*view_coords(v), target, scene)
                img, seg, box, vis = draw_view(cls, v, occlude, rng)
                cv2.imwrite(str(d / f"{stem}.png"), img[..., ::-1])
                (d / f"{stem}.txt").write_text(" ".join(map(str, box)) + "\n")
                if occlude:
                    cv2.imwrite(str(d / "seg" / f"{stem}.png"), seg)
                visible[stem] = vis
        if occlude:
            (d / "seg" / "categories.json").write_text(
                json.dumps({"0": "none", "1": "target", "2": "building", "3": "ground"}))
        (d / "scene.json").write_text(json.dumps({"visible": visible}))
    return root


__all__ = ["SHAPES", "SIZE", "draw_view", "write_tiny_world"]


def tiny_preset(*, overrides: str = "", ablation: str = "", episodes: int = 200) -> str:
    """A preset TOML for :func:`write_tiny_world`: ``episodes`` per run (evaluated every 100)
    and a 2-epoch recognizer. ``overrides`` adds lines to its ``[overrides]`` section,
    ``ablation`` gives it an ``[ablation]`` section."""
    text = """name = "tiny"
description = "a few hundred episodes per run on the 16 px test world"

[overrides]
"perception.encoder.name" = "resnet18"
"perception.encoder.weights" = "classifier"
"train.episodes" = """ + str(int(episodes)) + """
"train.epoch_episodes" = 100
"train.n_envs" = 16
"train.learning_starts" = 50
"train.eval_splits" = ["train", "hard"]
"train.eval_contexts" = 1
""" + overrides + """
[classifier]
epochs = 2
max_views = 40
batch_size = 32
"""
    return text + (f"\n[ablation]\n{ablation}" if ablation else "")

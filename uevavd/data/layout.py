"""The canonical UEVAVD on-disk layout, as the synthetic writer produces it.

The real release names images "UAV coordinates + target name + scene id" and keeps box
annotations beside them, in a format it does not document; the reader
(:mod:`uevavd.data.reader`) accepts reasonable variants of everything here. This module
fixes the *canonical* spelling that our writer uses::

    ROOT/
      uevavd.json                       dataset card: format, version, generator settings
      manifest.json                     sha256 + size of every file (written last)
      001/ .. 150/                      one folder per context (zero-padded context id)
        x-50_y+40_z080_sedan_001.png    RGB crop, H x W x 3, centred on the target
        x-50_y+40_z080_sedan_001.txt    "x1 y1 x2 y2" target box, XYXY crop pixels
                                        (x2, y2 exclusive); "0 0 0 0" = fully occluded
        seg/x-50_y+40_z080_sedan_001.png  instance ids, uint16 PNG, same H x W
        seg/categories.json             {"<instance id>": "<category>", ...}
        scene.json                      per-scene metadata (target, split, terrain,
                                        visible fraction per view stem, ...)
      00/                               unoccluded views of all five targets
      train_605/                        unoccluded crops of the five targets, 605 views
"""

from __future__ import annotations

DATASET_CARD = "uevavd.json"
MANIFEST = "manifest.json"
SCENE_META = "scene.json"
SEG_DIR = "seg"
CATEGORIES = "categories.json"
IMAGE_EXT = ".png"
BOX_EXT = ".txt"

#: Instance-segmentation categories. Instance id 0 is reserved for "none" (no geometry).
CATEGORIES_ORDER: tuple[str, ...] = (
    "none",
    "target",
    "building",
    "tree",
    "road",
    "pavement",
    "ground",
    "vehicle",
)


def view_stem(x: float, y: float, z: float, target: str, scene: str) -> str:
    """Canonical file stem, e.g. ``view_stem(-50, 40, 80, "sedan", "001")`` ->
    ``"x-50_y+40_z080_sedan_001"``. Coordinates are metres, signed, zero-padded."""
    return f"x{int(x):+03d}_y{int(y):+03d}_z{int(z):03d}_{target}_{scene}"

"""``AODEnv(render_mode="rgb_array")`` frames: the current view beside a top-down map of the path.

Left: the image the UAV sees now, read from the table's dataset (``meta["config"]["data_root"]``)
when the table records one and the file is there, else a gray panel saying why. Right: the
11 x 11 horizontal grid seen from above with the target at the centre, the path so far
(each visited view's altitude in metres) and the current view ringed.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..data.grid import NX, NY, grid_indices, view_coords
from ..data.reader import DatasetError, read_dataset
from ..perception.images import read_rgb

#: Side of each of the two square panels, in pixels.
PANEL = 256


def render_frame(table: Any, scene: int, path: list[int], t: int) -> np.ndarray:
    """(PANEL, 2 * PANEL, 3) uint8 RGB frame of table scene ``scene`` after the views ``path``."""
    view = path[-1]
    left = _view_panel(table, scene, view)
    right = _map_panel(path)
    x, y, z = (int(c) for c in view_coords(view))
    cv2.putText(right, f"t={t}  ({x}, {y}, {z}) m", (6, PANEL - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (20, 20, 20), 1, cv2.LINE_AA)
    return np.concatenate([left, right], axis=1)


def _view_panel(table: Any, scene: int, view: int) -> np.ndarray:
    image, why = _view_image(table, scene, view)
    if image is None:
        panel = np.full((PANEL, PANEL, 3), 128, np.uint8)
        for i, line in enumerate(_wrap(f"no image: {why}", 30)):
            cv2.putText(panel, line, (8, 24 + 18 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1,
                        cv2.LINE_AA)
        return panel
    return cv2.resize(image, (PANEL, PANEL), interpolation=cv2.INTER_NEAREST)


def _view_image(table: Any, scene: int, view: int) -> tuple[np.ndarray | None, str]:
    config = (getattr(table, "meta", None) or {}).get("config") or {}
    root = config.get("data_root") if isinstance(config, dict) else None
    if not root:
        return None, "the table records no dataset folder"
    manifest = _manifest(str(root))
    if manifest is None:
        return None, f"{root} is not readable"
    name = str(table.scenes[scene])
    target = table.class_names[int(table.targets[scene])]
    try:
        record = manifest.records[manifest.index(name, target, int(view))]

        return read_rgb(record.image), ""
    except (KeyError, ValueError, OSError) as exc:
        return None, str(exc)


@lru_cache(maxsize=4)
def _manifest(root: str):
    if not Path(root).is_dir():
        return None
    try:
        return read_dataset(root, check=False)
    except (DatasetError, OSError):
        return None


def _map_panel(path: list[int]) -> np.ndarray:
    panel = np.full((PANEL, PANEL, 3), 245, np.uint8)
    cell = (PANEL - 32) // max(NX, NY)
    x0 = (PANEL - cell * NX) // 2

    def centre(v: int) -> tuple[int, int]:
        ix, iy, _ = grid_indices(v)
        return x0 + int(ix) * cell + cell // 2, 8 + (NY - 1 - int(iy)) * cell + cell // 2  # +y up

    for i in range(NX + 1):
        cv2.line(panel, (x0 + i * cell, 8), (x0 + i * cell, 8 + NY * cell), (215, 215, 215), 1)
    for j in range(NY + 1):
        cv2.line(panel, (x0, 8 + j * cell), (x0 + NX * cell, 8 + j * cell), (215, 215, 215), 1)
    cx, cy = x0 + (NX // 2) * cell + cell // 2, 8 + (NY // 2) * cell + cell // 2
    cv2.drawMarker(panel, (cx, cy), (200, 30, 30), cv2.MARKER_TILTED_CROSS, cell // 2, 2)  # the target
    points = [centre(v) for v in path]
    for a, b in zip(points, points[1:], strict=False):
        cv2.line(panel, a, b, (40, 90, 200), 2, cv2.LINE_AA)
    for v, p in zip(path, points, strict=True):
        cv2.circle(panel, p, 4, (40, 90, 200), -1, cv2.LINE_AA)
        cv2.putText(panel, str(int(view_coords(v)[2])), (p[0] + 5, p[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33,
                    (40, 40, 40), 1, cv2.LINE_AA)
    cv2.circle(panel, points[-1], 8, (20, 160, 60), 2, cv2.LINE_AA)
    return panel


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for w in words:
        if len(line) + len(w) + 1 > width and line:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return [*lines, line][:10]

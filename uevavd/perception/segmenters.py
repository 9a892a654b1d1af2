"""Built-in segmenters: ``none`` and ``gt`` (ground-truth instance maps).

``gt`` reads the dataset's instance maps (``seg/*.png``, uint16 ids) with their
id -> category table: category ``"target"`` is the target, id 0 (``"none"``) is
uncovered, every other instance id is one segment.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from .base import Segmentation
from .decompose import decompose_instances

GT_VERSION = 1


class NoSegmenter:
    """No target mask and no segments: the pre-decomposition, if asked for, turns the
    whole view into one gray segment, so methods with ``decompose = true`` need a real
    segmenter."""

    needs_ground_truth = False

    def segment(self, images, boxes, *, instance_maps=None, categories=None) -> list[Segmentation]:
        n, h, w = np.asarray(images).shape[:3]
        return [Segmentation(np.zeros((h, w), bool), []) for _ in range(n)]

    def identity(self) -> str:
        return "segmenter:none"


class GroundTruthSegmenter:
    """Segments from the dataset's ground-truth instance maps."""

    needs_ground_truth = True

    def segment(
        self,
        images: np.ndarray,
        boxes: np.ndarray,
        *,
        instance_maps: np.ndarray | None = None,
        categories: Sequence[Mapping[int, str]] | None = None,
    ) -> list[Segmentation]:
        if instance_maps is None or categories is None:
            raise ValueError(
                "segmenter 'gt' needs the dataset's ground-truth instance maps (seg/*.png and "
                "seg/categories.json); this dataset has none: use segmenter 'sam' or 'none'"
            )
        maps = np.asarray(instance_maps)
        if maps.shape[0] != len(images) or maps.shape[1:] != np.asarray(images).shape[1:3]:
            raise ValueError(f"instance maps {maps.shape} do not match images {np.asarray(images).shape}")
        out = []
        for m, cats in zip(maps, categories, strict=True):
            target_ids = [i for i, c in cats.items() if c == "target"]
            target = np.isin(m, target_ids)
            ids = np.unique(m)
            segs = [m == i for i in ids if i != 0 and i not in target_ids]
            out.append(Segmentation(target, segs))
        return out

    def decompose_views(self, images: np.ndarray, instance_maps: np.ndarray,
                        categories: Sequence[Mapping[int, str]], seeds: Sequence[int]) -> np.ndarray:
        """Fast path of segment + :func:`~uevavd.perception.decompose.decompose` (identical
        output): (N, H, W, 3) uint8 pre-decomposed views, one table lookup per view."""
        out = np.empty_like(images)
        for i, (img, m, cats, seed) in enumerate(zip(images, instance_maps, categories, seeds, strict=True)):
            out[i] = decompose_instances(img, m, [k for k, c in cats.items() if c == "target"], seed=seed)
        return out

    def identity(self) -> str:
        return f"segmenter:gt:v{GT_VERSION}"


def build_none() -> NoSegmenter:
    """No segmentation."""
    return NoSegmenter()


def build_gt() -> GroundTruthSegmenter:
    """Ground-truth segmentation from the dataset's seg/ PNGs."""
    return GroundTruthSegmenter()

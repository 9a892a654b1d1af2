"""Protocols of the perception components (one per kind).

Images everywhere are RGB uint8 arrays, (N, H, W, 3), channels last, in the crop frame
of the dataset (target at the centre). Boxes are (N, 4) integer XYXY crop pixels with
x2, y2 exclusive; an all-zero box means the target is fully occluded.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass
class Segmentation:
    """The segments of one view.

    * ``target`` (H, W) bool: the target's pixels (all False when none is found).
    * ``segments`` list of (H, W) bool: the surrounding objects; none of them contains a
      target pixel. They may leave pixels uncovered (the pre-decomposition fills those as
      one more segment) and should not overlap (where they do, a later one wins).
    """

    target: np.ndarray
    segments: list[np.ndarray] = field(default_factory=list)


@runtime_checkable
class Segmenter(Protocol):
    """Splits a view into the target and its surrounding objects."""

    #: True when :meth:`segment` needs the dataset's ground-truth instance maps.
    needs_ground_truth: bool

    def segment(
        self,
        images: np.ndarray,
        boxes: np.ndarray,
        *,
        instance_maps: np.ndarray | None = None,
        categories: Sequence[Mapping[int, str]] | None = None,
    ) -> list[Segmentation]:
        """Segment N views.

        images (N, H, W, 3) uint8 RGB; boxes (N, 4) int XYXY pixels (all zero = occluded);
        instance_maps (N, H, W) uint16 ground-truth instance ids and, per view, the id ->
        category table (category "target" marks the target), for segmenters that need them.
        Returns one :class:`Segmentation` per view.
        """
        ...

    def identity(self) -> str:
        """A string that changes whenever the output could change (weights hash, settings);
        it goes into the observation table's key."""
        ...


@runtime_checkable
class Encoder(Protocol):
    """Images -> feature vectors."""

    feature_dim: int

    def encode(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) uint8 RGB -> (N, feature_dim) float32. Deterministic."""
        ...

    def identity(self) -> str:
        """Architecture + weights hash + preprocessing, for the observation table's key."""
        ...


@runtime_checkable
class Classifier(Protocol):
    """Images -> class probabilities over ``classes``."""

    classes: tuple[str, ...]

    def predict_proba(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) uint8 RGB -> (N, len(classes)) float32, rows sum to 1."""
        ...

    def identity(self) -> str:
        """Architecture + weights hash + preprocessing, for the observation table's key."""
        ...

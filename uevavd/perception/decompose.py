"""Scene pre-decomposition (docs/perception.md, "Segmenters and pre-decomposition"): keep the target, flatten the rest.

Target pixels stay as they are; every other segment is filled with one gray value drawn
uniformly from [0, 1] (RGB ``(round(255 g),) * 3``); pixels no segment covers are filled
as one more segment. Deterministic for a given seed; :func:`view_seed` derives a per-view
seed from ``(gray_seed, scene, view)`` so that tables are reproducible.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np


def view_seed(gray_seed: int, scene: str, view: int, target: str = "") -> int:
    """A 63-bit seed for one view, stable across runs and platforms."""
    blob = f"{int(gray_seed)}:{scene}:{target}:{int(view)}".encode()
    return int.from_bytes(hashlib.sha256(blob).digest()[:8], "little") >> 1


def label_image(target_mask: np.ndarray, segments: Sequence[np.ndarray]) -> np.ndarray:
    """(H, W) int32 labels: 0 = target, 1..S = segments (later ones win where they
    overlap), S + 1 = uncovered. Target pixels are never relabelled."""
    h, w = target_mask.shape
    labels = np.full((h, w), len(segments) + 1, np.int32)
    for i, seg in enumerate(segments, start=1):
        labels[seg] = i
    labels[target_mask] = 0
    return labels


def decompose(image: np.ndarray, target_mask: np.ndarray, segments: Sequence[np.ndarray], *, seed: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W, 3) uint8 RGB pre-decomposed view.

    ``target_mask`` (H, W) bool; ``segments`` list of (H, W) bool. Segment i (in order) gets
    gray ``g_i ~ U[0, 1]`` from ``numpy.random.default_rng(seed)``, the uncovered pixels
    the next draw.
    """
    image = np.asarray(image)
    target_mask = np.asarray(target_mask, dtype=bool)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"decompose: expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    if target_mask.shape != image.shape[:2]:
        raise ValueError(f"decompose: target mask {target_mask.shape} does not match image {image.shape[:2]}")
    for i, s in enumerate(segments):
        if np.shape(s) != image.shape[:2]:
            raise ValueError(f"decompose: segment {i} has shape {np.shape(s)}; expected {image.shape[:2]}")
    labels = label_image(target_mask, [np.asarray(s, dtype=bool) for s in segments])
    grays = np.random.default_rng(seed).random(len(segments) + 1)
    lut = np.empty((len(segments) + 2, 3), np.uint8)
    lut[1:] = np.round(255.0 * grays)[:, None].astype(np.uint8)
    out = lut[labels]
    out[target_mask] = image[target_mask]
    return out


def decompose_instances(image: np.ndarray, instance_map: np.ndarray, target_ids, *, seed: int) -> np.ndarray:
    """Same result as :func:`decompose` over the ground-truth segmentation (target = the
    ``target_ids`` instances; segments = every other non-zero id in increasing order;
    id 0 uncovered), by one table lookup: ``instance_map`` (H, W) uint16 -> (H, W, 3) uint8."""
    flat = instance_map.ravel()
    present = np.bincount(flat) > 0
    is_target = np.zeros(len(present), bool)
    tids = [int(t) for t in target_ids if 0 <= int(t) < len(present)]
    is_target[tids] = True
    is_seg = present & ~is_target
    is_seg[0] = False
    n_segs = int(is_seg.sum())
    grays = np.round(255.0 * np.random.default_rng(seed).random(n_segs + 1)).astype(np.uint8)
    lut = np.zeros(len(present), np.uint8)
    lut[is_seg] = grays[:n_segs]
    lut[0] = grays[n_segs]
    # two lookups and OpenCV's merge and masked copy: half the time of numpy's boolean
    # indexing, and they release the GIL, so decoding threads decompose views in parallel
    gray = lut.take(instance_map)
    out = cv2.merge([gray, gray, gray])
    return cv2.copyTo(np.ascontiguousarray(image), is_target.take(instance_map).view(np.uint8), out)


def check_decomposition(perception: Any, where: str) -> None:
    """Refuse a decomposition a method's perception section (``PerceptionSection``) asks for but
    cannot be made: no segmenter, or the ``none`` segmenter (every
    view one flat gray); ``where`` names the method. Checked before any work by ``uevavd ablate``."""
    if not perception.decompose:
        return
    if perception.segmenter is None:
        raise ValueError(f"{where}: perception.decompose = true needs a perception.segmenter")
    if perception.segmenter.name == "none":
        raise ValueError(
            f"{where}: perception.decompose = true with segmenter 'none' would turn "
            "every view into one flat gray (no target mask); use segmenter 'gt' or 'sam', or set "
            "perception.decompose = false")

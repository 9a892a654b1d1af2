"""Prompt geometry and mask post-processing for the SAM segmenter (pure numpy / OpenCV).

Frames: images and masks are (H, W); points are (N, 2) float32 (x, y) pixel coordinates
of pixel centres; boxes are int XYXY pixels with x2, y2 exclusive.
"""

from __future__ import annotations

import cv2
import numpy as np


def clip_box(box, height: int, width: int, *, index: int | None = None) -> np.ndarray | None:
    """The box clipped to the image, as (4,) int64 XYXY; ``None`` for an all-zero box (fully
    occluded target) or one that lies completely outside the image (nothing to prompt).
    A non-zero box with x2 <= x1 or y2 <= y1 is an error naming the view."""
    b = np.asarray(box, dtype=np.int64).reshape(4)
    where = f"view {index}: " if index is not None else ""
    if not b.any():
        return None
    if b[2] <= b[0] or b[3] <= b[1]:
        raise ValueError(f"{where}box {b.tolist()} is inverted or empty: expected XYXY pixels with x2 > x1 and "
                         "y2 > y1, or 0 0 0 0 for a fully occluded target")
    c = np.array([max(b[0], 0), max(b[1], 0), min(b[2], width), min(b[3], height)], np.int64)
    if c[2] <= c[0] or c[3] <= c[1]:
        return None
    return c


def centre_box(height: int, width: int, frac: float = 0.25) -> np.ndarray:
    """A box of ``frac`` of the image side around the centre (the crop frame keeps the
    target there): where the ring goes when the target is fully occluded."""
    bw, bh = max(2, round(width * frac)), max(2, round(height * frac))
    x1, y1 = (width - bw) // 2, (height - bh) // 2
    return np.array([x1, y1, x1 + bw, y1 + bh], np.int64)


def box_mask(box: np.ndarray, height: int, width: int) -> np.ndarray:
    m = np.zeros((height, width), bool)
    m[box[1]:box[3], box[0]:box[2]] = True
    return m


def ring_points(region: np.ndarray, n: int, margin: float) -> np.ndarray:
    """N points on a ring at ``margin`` pixels outside ``region``'s contour.

    region (H, W) bool, not empty (the target mask, or its box when the mask is empty).
    Rays leave the region's centroid at N evenly spaced angles; each point is the first
    pixel along its ray whose distance to the region is >= margin. Where a ray leaves the
    image first, the point is the farthest in-image pixel of that ray outside the region;
    rays with no such pixel are dropped. Returns (M, 2) float32 (x, y), M <= N, every point
    outside ``region`` and inside the image.
    """
    h, w = region.shape
    if n <= 0 or not region.any():
        return np.zeros((0, 2), np.float32)
    # Distance of each pixel to the nearest region pixel (0 inside the region).
    dist = cv2.distanceTransform((~region).astype(np.uint8), cv2.DIST_L2, 5)
    ys, xs = np.nonzero(region)
    cy, cx = ys.mean(), xs.mean()
    angles = 2 * np.pi * np.arange(n) / n
    rmax = int(np.hypot(h, w)) + 1
    r = np.arange(rmax, dtype=np.float32)
    px = np.rint(cx + np.cos(angles)[:, None] * r[None]).astype(np.int64)  # (n, rmax)
    py = np.rint(cy + np.sin(angles)[:, None] * r[None]).astype(np.int64)
    inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    d = np.where(inside, dist[py.clip(0, h - 1), px.clip(0, w - 1)], -1.0)
    out = []
    for i in range(n):
        reach = np.nonzero(d[i] >= max(margin, 1.0))[0]
        if reach.size:
            j = reach[0]
        else:  # the image edge comes first: the farthest in-image pixel outside the region
            ok = np.nonzero(d[i] > 0)[0]
            if not ok.size:
                continue
            j = ok[-1]
        out.append((px[i, j], py[i, j]))
    if not out:
        return np.zeros((0, 2), np.float32)
    pts = np.unique(np.asarray(out, np.int64), axis=0)  # rays may meet at one pixel
    return pts.astype(np.float32)


def mask_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of (A, H, W) and (B, H, W) bool masks -> (A, B) float64."""
    fa = a.reshape(len(a), -1).astype(np.float32)
    fb = b.reshape(len(b), -1).astype(np.float32)
    inter = fa @ fb.T
    union = fa.sum(1)[:, None] + fb.sum(1)[None] - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def merge_duplicates(masks: list[np.ndarray], iou_threshold: float) -> list[np.ndarray]:
    """Merge masks that overlap with IoU >= ``iou_threshold`` (one object prompted by
    several ring points) into their union. Greedy over masks by decreasing area: each
    mask joins the first kept mask it matches, else it is kept. Returns (H, W) bool masks."""
    if not masks:
        return []
    order = sorted(range(len(masks)), key=lambda i: -int(masks[i].sum()))
    kept: list[np.ndarray] = []
    for i in order:
        m = masks[i]
        if kept:
            ious = mask_iou(m[None], np.stack(kept))[0]
            j = int(np.argmax(ious))
            if ious[j] >= iou_threshold:
                kept[j] = kept[j] | m
                continue
        kept.append(m.copy())
    return kept


def make_disjoint(masks: list[np.ndarray], min_area: int) -> list[np.ndarray]:
    """Masks in order of decreasing area, each pixel given to the smallest mask covering it
    (a small object prompted inside a large region keeps its pixels); masks left with fewer
    than ``min_area`` pixels are dropped."""
    if not masks:
        return []
    order = sorted(masks, key=lambda m: -int(m.sum()))
    label = np.full(order[0].shape, -1, np.int32)
    for i, m in enumerate(order):
        label[m] = i  # later (smaller) masks win
    out = [label == i for i in range(len(order))]
    return [m for m in out if int(m.sum()) >= max(min_area, 1)]

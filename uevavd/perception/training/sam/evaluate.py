"""Mask quality of the SAM segmenter against ground truth (mIoU).

* Target mIoU: mean over views whose ground-truth target is visible of IoU(predicted
  target mask, ground-truth target mask).
* Surrounding mIoU: for every ground-truth surrounding instance that a ring point falls
  on, the IoU of the best-matching predicted surrounding segment (0 when none overlaps);
  mean over all such (view, instance) pairs.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ...sam.prompts import mask_iou
from .data import GTViews


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def evaluate(segmenter, views: GTViews, *, batch: int = 32, progress: bool = False) -> dict:
    """mIoU of ``segmenter`` (a :class:`~.segmenter.SamSegmenter`) on ``views``.

    Returns {"target_miou", "surround_miou", "n_target", "n_surround", "per_split": {split:
    {same keys}}}; a mean over nothing is NaN."""
    acc: dict[str, dict[str, list[float]]] = defaultdict(lambda: {"t": [], "s": []})
    it = range(0, len(views), batch)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="evaluating", unit="batch", leave=False)
    for i in it:
        out = segmenter.segment_detailed(views.images[i:i + batch], views.boxes[i:i + batch])
        for k, v in enumerate(out):
            j = i + k
            split = views.splits[j] if views.splits else None
            gt_t = views.target_mask(j)
            if gt_t.any():
                acc[split or "all"]["t"].append(_iou(v.target, gt_t))
            seg = views.seg[j]
            objects = views.object_ids(j)
            pts = np.rint(v.points).astype(np.int64)
            touched = {int(seg[y, x]) for x, y in pts} & objects
            if not touched:
                continue
            gt = np.stack([seg == t for t in sorted(touched)])
            if v.segments:
                best = mask_iou(gt, np.stack(v.segments)).max(1)
            else:
                best = np.zeros(len(gt))
            acc[split or "all"]["s"].extend(best.tolist())

    def summary(t: list[float], s: list[float]) -> dict:
        return {"target_miou": float(np.mean(t)) if t else float("nan"),
                "surround_miou": float(np.mean(s)) if s else float("nan"),
                "n_target": len(t), "n_surround": len(s)}

    all_t = [x for a in acc.values() for x in a["t"]]
    all_s = [x for a in acc.values() for x in a["s"]]
    return {**summary(all_t, all_s), "per_split": {k: summary(a["t"], a["s"]) for k, a in sorted(acc.items())}}

"""Segment Anything as a ``segmenter`` plugin (``sam``): the models, prompts and segmenter
(inference). Fine-tuning and the small SAM trained from scratch on the synthetic world are
in :mod:`uevavd.perception.training.sam`.

    from uevavd.perception.sam import build_sam_segmenter
    seg = build_sam_segmenter(checkpoint="sam_vit_b_01ec64.pth", ring_points=16)
    out = seg.segment(images, boxes)        # (N, H, W, 3) uint8, (N, 4) int XYXY
"""

from __future__ import annotations

import os

from .model import CheckpointError, SmallConfig, default_small_path, load_sam
from .segmenter import SamSegmenter, SamView

__all__ = ["CheckpointError", "SamSegmenter", "SamView", "SmallConfig", "build_sam_segmenter", "load_sam"]


def build_sam_segmenter(
    *,
    checkpoint: str | None = None,
    model_type: str = "auto",
    device: str = "auto",
    ring_points: int = 16,
    ring_margin: float = 0.1,
    ring_margin_min: float = 2.0,
    iou_merge: float = 0.7,
    min_area: float = 0.001,
    pred_iou_min: float = 0.0,
    multimask: bool = True,
    batch_size: int = 8,
    precision: str = "fp32",
) -> SamSegmenter:
    """The ``sam`` segmenter.

    * ``checkpoint``: a local SAM file: an official ``.pth`` (vit_b / vit_l / vit_h), a
      MobileSAM ``.pt`` (vit_t, needs the ``mobile_sam`` package), or a ``.safetensors``
      written by ``uevavd train-sam-small`` / ``uevavd finetune-sam``. ``None``: the small
      model at ``$UEVAVD_CACHE/sam/sam_small.safetensors``.
    * ``model_type``: "auto" (read from the file) or the type you expect; a mismatch is an error.
    * ``device``: "auto" (CUDA when available), "cpu", "cuda", "cuda:1", ...
    * ``ring_points``: N, the number of point prompts on the ring (one surrounding object each).
    * ``ring_margin``: the ring's distance outside the target's contour, as a fraction of
      the target's longer side, at least ``ring_margin_min`` pixels.
    * ``iou_merge``: ring masks overlapping with IoU >= this are merged (one object, several points).
    * ``min_area``: masks smaller than this fraction of the view are dropped.
    * ``pred_iou_min``: ring masks whose predicted IoU is below this are dropped.
    * ``multimask``: ask SAM for three masks per point and keep the best-scored one.
    * ``batch_size``: images per image-encoder batch; ``precision``: "fp32" or "bf16" (autocast).
    """
    from .model import load_sam as _load

    if checkpoint is None:
        path = default_small_path()
        if not path.is_file():
            raise CheckpointError(
                f"no SAM checkpoint given and no small SAM at {path}; run `uevavd train-sam-small DATA` "
                "(DATA: a synthetic world, e.g. from `uevavd synth`) or set [perception.segmenter] "
                "checkpoint = \"/path/to/sam_vit_b_01ec64.pth\"")
    else:
        path = os.path.expanduser(checkpoint)
    loaded = _load(path, model_type)
    return SamSegmenter(
        loaded, device=device, ring_points=ring_points, ring_margin=ring_margin, ring_margin_min=ring_margin_min,
        iou_merge=iou_merge, min_area=min_area, pred_iou_min=pred_iou_min, multimask=multimask,
        batch_size=batch_size, precision=precision,
    )

"""Segment Anything as a ``segmenter`` plugin (``sam``): the models, prompts and segmenter
(inference). Fine-tuning and the small SAM trained from scratch on the synthetic world are
in :mod:`uevavd.perception.training.sam`.

    from uevavd.perception.sam import build_sam_segmenter
    seg = build_sam_segmenter(checkpoint="sam_vit_b_01ec64.pth", ring_points=16)
    out = seg.segment(images, boxes)        # (N, H, W, 3) uint8, (N, 4) int XYXY
"""

from __future__ import annotations

import inspect
import os
from typing import Any

from .model import CheckpointError, SmallConfig, default_small_path, load_sam
from .segmenter import SamSegmenter, SamView

__all__ = ["CheckpointError", "SamSegmenter", "SamView", "SmallConfig", "build_sam_segmenter", "load_sam"]


def build_sam_segmenter(*, checkpoint: str | None = None, model_type: str = "auto", **options: Any) -> SamSegmenter:
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

    The options after ``model_type`` are :class:`SamSegmenter`'s, with its defaults and types
    (this function's signature is built from its constructor's, below).
    """
    from .model import load_sam as _load

    inspect.signature(build_sam_segmenter).bind(**options)  # a misspelt option: TypeError before loading
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
    return SamSegmenter(loaded, **options)


# The options after ``model_type`` are SamSegmenter's: the builder's signature, which the
# config's validation reads (an unknown key or a wrong type is refused before a model loads),
# is built from its constructor's, so their defaults and types exist once.
_params = [p for p in inspect.signature(build_sam_segmenter).parameters.values() if p.kind is p.KEYWORD_ONLY]
_params += [p for p in inspect.signature(SamSegmenter).parameters.values() if p.name != "loaded"]
build_sam_segmenter.__signature__ = inspect.Signature(_params, return_annotation=SamSegmenter)  # type: ignore[attr-defined]
build_sam_segmenter.__annotations__ = {p.name: p.annotation for p in _params}
del _params

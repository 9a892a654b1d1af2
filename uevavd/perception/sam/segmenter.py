"""The ``sam`` segmenter: target from its box, surrounding objects from a ring of points.

Per batch of views the image encoder runs once over all images (one embedding per image);
per image, ``SamPredictor.predict_torch`` decodes the box prompt (target) and then all
ring-point prompts in one batch (one point per prompt, a surrounding object each).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from segment_anything import SamPredictor

from ...runtime import resolve_device
from ..base import Segmentation
from .model import LoadedSam
from .prompts import box_mask, centre_box, clip_box, make_disjoint, merge_duplicates, ring_points


@dataclass
class SamView:
    """Everything the segmenter decided for one view (for evaluation and pictures).

    target (H, W) bool; segments list of (H, W) bool, disjoint, no target pixel;
    points (M, 2) float32 (x, y) ring prompts; box (4,) int64 XYXY clipped prompt box or
    None (fully occluded / outside); raw list of (H, W) bool, one mask per ring point
    before merging (target pixels removed).
    """

    target: np.ndarray
    segments: list[np.ndarray]
    points: np.ndarray
    box: np.ndarray | None
    raw: list[np.ndarray]


def images_to_input(images: np.ndarray, predictor: SamPredictor) -> torch.Tensor:
    """(N, H, W, 3) uint8 RGB -> (N, 3, h, w) float32 resized so the long side is the
    encoder's input size (ResizeLongestSide), not yet normalised or padded."""
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images: expected (N, H, W, 3) uint8 RGB, got {images.shape} {images.dtype}")
    x = torch.from_numpy(np.ascontiguousarray(images)).to(predictor.device).permute(0, 3, 1, 2).float()
    # ResizeLongestSide.apply_image_torch of segment-anything 1.0 reads the size from
    # shape[0], shape[1] (batch, channels) instead of (H, W); use its size rule directly.
    t = predictor.transform
    size = t.get_preprocess_shape(images.shape[1], images.shape[2], t.target_length)
    return F.interpolate(x, size, mode="bilinear", align_corners=False, antialias=True)


class SamSegmenter:
    """:class:`uevavd.perception.base.Segmenter` over a SAM model (see module docstring)."""

    needs_ground_truth = False

    def __init__(
        self,
        loaded: LoadedSam,
        *,
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
    ):
        if ring_points < 0 or ring_margin < 0 or not 0 < iou_merge <= 1 or batch_size < 1:
            raise ValueError(f"sam segmenter: need ring_points >= 0, ring_margin >= 0, 0 < iou_merge <= 1, "
                             f"batch_size >= 1; got {ring_points}, {ring_margin}, {iou_merge}, {batch_size}")
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"sam segmenter: precision {precision!r}; expected 'fp32' or 'bf16'")
        self.loaded = loaded
        self.device = resolve_device(device)
        self.model = loaded.model.to(self.device).eval()
        self.predictor = SamPredictor(self.model)
        self.ring_points = int(ring_points)
        self.ring_margin = float(ring_margin)
        self.ring_margin_min = float(ring_margin_min)
        self.iou_merge = float(iou_merge)
        self.min_area = float(min_area)
        self.pred_iou_min = float(pred_iou_min)
        self.multimask = bool(multimask)
        self.batch_size = int(batch_size)
        self.precision = precision

    # -- protocol -------------------------------------------------------------------------
    def identity(self) -> str:
        return (f"sam:{self.loaded.model_type}:{self.loaded.sha256[:16]}:n{self.ring_points}:m{self.ring_margin}"
                f"/{self.ring_margin_min}:iou{self.iou_merge}:a{self.min_area}:q{self.pred_iou_min}"
                f":mm{int(self.multimask)}:{self.precision}")

    def segment(
        self,
        images: np.ndarray,
        boxes: np.ndarray,
        *,
        instance_maps: np.ndarray | None = None,
        categories: Sequence[Mapping[int, str]] | None = None,
    ) -> list[Segmentation]:
        """images (N, H, W, 3) uint8 RGB; boxes (N, 4) int XYXY pixels (all zero = fully
        occluded). Ground truth is not used. Returns one Segmentation per view."""
        return [Segmentation(target=v.target, segments=v.segments) for v in self.segment_detailed(images, boxes)]

    # -- work -----------------------------------------------------------------------------
    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return nullcontext()

    @torch.no_grad()
    def embed(self, images: np.ndarray) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, C, h, w) float32 image embeddings, computed in batches
        of ``batch_size``."""
        out = []
        for i in range(0, len(images), self.batch_size):
            x = images_to_input(images[i:i + self.batch_size], self.predictor)
            with self._autocast():
                out.append(self.model.image_encoder(self.model.preprocess(x)).float())
        return torch.cat(out) if out else torch.zeros(0)

    def _set_embedding(self, feats: torch.Tensor, hw: tuple[int, int]) -> None:
        # SamPredictor.set_torch_image embeds one image at a time; we embed a batch and give
        # the predictor each image's embedding in the same state set_torch_image leaves.
        p = self.predictor
        p.reset_image()
        p.original_size = hw
        p.input_size = p.transform.get_preprocess_shape(hw[0], hw[1], p.transform.target_length)
        p.features = feats
        p.is_image_set = True

    @torch.no_grad()
    def segment_detailed(self, images: np.ndarray, boxes: np.ndarray) -> list[SamView]:
        """Like :meth:`segment`, with the prompts and raw masks (:class:`SamView`)."""
        images = np.asarray(images)
        boxes = np.asarray(boxes)
        if boxes.shape != (len(images), 4):
            raise ValueError(f"boxes: expected ({len(images)}, 4) int XYXY pixels, got {boxes.shape}")
        h, w = images.shape[1:3]
        clipped = [clip_box(b, h, w, index=i) for i, b in enumerate(boxes)]
        views: list[SamView] = []
        for i in range(0, len(images), self.batch_size):
            feats = self.embed(images[i:i + self.batch_size])
            for j in range(len(feats)):
                self._set_embedding(feats[j:j + 1], (h, w))
                views.append(self._decode_view(clipped[i + j], h, w))
        self.predictor.reset_image()
        return views

    def _decode_view(self, box: np.ndarray | None, h: int, w: int) -> SamView:
        p = self.predictor
        target = np.zeros((h, w), bool)
        with self._autocast():
            if box is not None:
                bt = p.transform.apply_boxes_torch(torch.as_tensor(box[None], dtype=torch.float32, device=p.device),
                                                   (h, w))
                m, _, _ = p.predict_torch(None, None, boxes=bt, multimask_output=False)
                target = m[0, 0].cpu().numpy()
            # The ring goes around the target mask; around its box when SAM found nothing
            # there; around the crop centre when the target is fully occluded.
            region = target if target.any() else box_mask(box if box is not None else centre_box(h, w), h, w)
            ys, xs = np.nonzero(region)
            size = max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
            margin = max(self.ring_margin_min, self.ring_margin * size)
            pts = ring_points(region, self.ring_points, margin)
            raw: list[np.ndarray] = []
            if len(pts):
                ct = p.transform.apply_coords_torch(torch.as_tensor(pts[:, None], device=p.device), (h, w))
                lt = torch.ones(ct.shape[:2], dtype=torch.int64, device=p.device)
                masks, scores, _ = p.predict_torch(ct, lt, multimask_output=self.multimask)
                best = scores.float().argmax(1)
                sel = masks[torch.arange(len(masks), device=masks.device), best].cpu().numpy()
                keep = scores.float().max(1).values.cpu().numpy() >= self.pred_iou_min
                raw = [m & ~target for m, k in zip(sel, keep, strict=True) if k]
        min_area = max(1, int(round(self.min_area * h * w)))
        merged = merge_duplicates([m for m in raw if m.sum() >= min_area], self.iou_merge)
        segments = make_disjoint(merged, min_area)
        return SamView(target=target, segments=segments, points=pts, box=box, raw=raw)


"""What fine-tuning and small-SAM training share: prompt sampling from ground truth, the
Dice + BCE loss through SAM's own prompt encoder and mask decoder, and a resumable loop.

Prompts are sampled the way the segmenter prompts at inference: a jittered box around the
ground-truth target (target mask), and points on a ring outside the target (the object
under each point is its mask).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from segment_anything import SamPredictor

from ....atomic import atomic_write
from ...sam.prompts import box_mask, centre_box, ring_points
from .data import GTViews


@dataclass
class TrainArgs:
    """Settings of a training run (all go into the checkpoint's metadata)."""

    steps: int = 1500  #: optimizer steps
    batch_size: int = 8  #: views per step
    lr: float = 3e-4  #: AdamW peak learning rate (linear warm-up, cosine decay to 10 %)
    weight_decay: float = 0.01
    warmup: int = 50  #: warm-up steps
    points_per_view: int = 4  #: ring-point prompts per view per step
    jitter: float = 0.1  #: box jitter, std as a fraction of the box side (max 20 px)
    seed: int = 0
    save_every: int = 100  #: steps between resumable snapshots


@dataclass
class ViewPrompts:
    """Prompts of one view in its pixel frame: box (4,) float32 XYXY or None; box_target
    (H, W) bool; points (K, 2) float32 (x, y); point_targets (K, H, W) bool."""

    box: np.ndarray | None
    box_target: np.ndarray | None
    points: np.ndarray
    point_targets: np.ndarray


def sample_prompts(views: GTViews, i: int, rng: np.random.Generator, *, n_points: int, jitter: float) -> ViewPrompts:
    seg = views.seg[i]
    h, w = seg.shape
    target = views.target_mask(i)
    box = gt = None
    if target.any():
        ys, xs = np.nonzero(target)
        b = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)
        side = np.array([b[2] - b[0], b[3] - b[1]] * 2, np.float32)
        noise = np.clip(rng.normal(0, jitter, 4) * side, -20, 20)
        box = np.clip(b + noise, 0, [w, h, w, h]).astype(np.float32)
        if box[2] - box[0] < 1 or box[3] - box[1] < 1:
            box = b
        gt = target
    region = target if target.any() else box_mask(centre_box(h, w), h, w)
    size = max(np.ptp(np.nonzero(region)[0]), np.ptp(np.nonzero(region)[1])) + 1
    margin = max(2.0, rng.uniform(0.05, 0.3) * size)
    ring = ring_points(region, 16, margin)
    objects = views.object_ids(i)
    pts, masks = [], []
    for k in rng.permutation(len(ring)):
        if len(pts) >= n_points:
            break
        x, y = (int(round(c)) for c in ring[k])
        oid = int(seg[y, x])
        if oid in objects:
            pts.append(ring[k])
            masks.append(seg == oid)
    pts_a = np.asarray(pts, np.float32).reshape(-1, 2)
    masks_a = np.stack(masks) if masks else np.zeros((0, h, w), bool)
    return ViewPrompts(box, gt, pts_a, masks_a)


def dice_bce(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-mask Dice + BCE. logits (..., H, W) float; target same shape, {0, 1} -> (...,)"""
    p = torch.sigmoid(logits).flatten(-2)
    t = target.flatten(-2)
    dice = 1 - (2 * (p * t).sum(-1) + 1) / (p.sum(-1) + t.sum(-1) + 1)
    bce = F.binary_cross_entropy_with_logits(logits.flatten(-2), t, reduction="none").mean(-1)
    return dice + bce


def _iou_of(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    pred = (logits > 0).flatten(-2).float()
    t = target.flatten(-2)
    inter = (pred * t).sum(-1)
    union = pred.sum(-1) + t.sum(-1) - inter
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


def _decode(model, predictor: SamPredictor, feats, points, boxes, multimask, hw):
    sparse, dense = model.prompt_encoder(points=points, boxes=boxes, masks=None)
    low, iou_pred = model.mask_decoder(image_embeddings=feats, image_pe=model.prompt_encoder.get_dense_pe(),
                                       sparse_prompt_embeddings=sparse, dense_prompt_embeddings=dense,
                                       multimask_output=multimask)
    input_size = predictor.transform.get_preprocess_shape(hw[0], hw[1], predictor.transform.target_length)
    return model.postprocess_masks(low, input_size, hw), iou_pred


def view_loss(model, predictor: SamPredictor, feats: torch.Tensor, pr: ViewPrompts) -> torch.Tensor | None:
    """Loss of one view's prompts through SAM's prompt encoder and mask decoder (with
    gradients: ``SamPredictor.predict_torch`` runs without them). feats (1, C, h, w)."""
    hw = tuple(pr.point_targets.shape[1:]) if pr.box_target is None else pr.box_target.shape
    dev = feats.device
    parts = []
    if pr.box is not None:
        bt = predictor.transform.apply_boxes_torch(torch.as_tensor(pr.box[None], device=dev), hw)
        masks, iou_pred = _decode(model, predictor, feats, None, bt, False, hw)
        tgt = torch.as_tensor(pr.box_target, dtype=torch.float32, device=dev)[None, None]
        parts.append(dice_bce(masks, tgt).mean() + F.mse_loss(iou_pred, _iou_of(masks, tgt).detach()))
    if len(pr.points):
        ct = predictor.transform.apply_coords_torch(torch.as_tensor(pr.points[:, None], device=dev), hw)
        lt = torch.ones(ct.shape[:2], dtype=torch.int64, device=dev)
        masks, iou_pred = _decode(model, predictor, feats, (ct, lt), None, True, hw)
        tgt = torch.as_tensor(pr.point_targets, dtype=torch.float32, device=dev)[:, None]
        per = dice_bce(masks, tgt.expand_as(masks))  # (K, 3): the best of SAM's three masks counts
        parts.append(per.min(1).values.mean() + F.mse_loss(iou_pred, _iou_of(masks, tgt).detach()))
    if not parts:
        return None
    return torch.stack(parts).mean()


def loss_summary(losses: list[float]) -> dict[str, float]:
    """Mean loss over the first and the last tenth of the steps (at least one step each)."""
    w = max(1, len(losses) // 10)
    if not losses:
        return {}
    return {"loss_first": float(np.nanmean(losses[:w])), "loss_last": float(np.nanmean(losses[-w:]))}


def lr_at(step: int, args: TrainArgs) -> float:
    if step < args.warmup:
        return args.lr * (step + 1) / args.warmup
    t = (step - args.warmup) / max(1, args.steps - args.warmup)
    return args.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(1.0, t))))


def _atomic_torch_save(obj, path: Path) -> None:
    atomic_write(path, lambda fh: torch.save(obj, fh))


def train_loop(
    model,
    trainable: torch.nn.Module,
    features: Callable[[np.ndarray], torch.Tensor],
    views: GTViews,
    args: TrainArgs,
    *,
    resume_path: Path,
    settings: dict,
    desc: str,
    fresh: bool = False,
) -> list[float]:
    """AdamW over ``trainable``'s parameters for ``args.steps`` steps; each step draws
    ``args.batch_size`` views (seeded by (seed, step), so a resumed run draws the same),
    ``features(idx)`` gives their (B, C, h, w) embeddings. Snapshots every ``save_every``
    steps to ``resume_path`` (resumed when its settings match). Returns the loss per step."""
    from tqdm import tqdm

    predictor = SamPredictor(model)
    opt = torch.optim.AdamW([p for p in trainable.parameters() if p.requires_grad], lr=args.lr,
                            weight_decay=args.weight_decay)
    key = json.dumps({**settings, "args": asdict(args)}, sort_keys=True, default=str)
    start, losses = 0, []
    if resume_path.is_file() and not fresh:
        snap = torch.load(resume_path, map_location="cpu", weights_only=True)
        if snap.get("key") != key:
            raise ValueError(f"{resume_path} is an interrupted run with other settings; rerun with the same "
                             "settings to resume, or pass --fresh to start over")
        trainable.load_state_dict(snap["model"])
        opt.load_state_dict(snap["optim"])
        start, losses = int(snap["step"]), list(snap["losses"])
    resume_path.parent.mkdir(parents=True, exist_ok=True)
    model.train()
    bar = tqdm(range(start, args.steps), desc=desc, unit="step", initial=start, total=args.steps)
    for step in bar:
        rng = np.random.default_rng([args.seed, step])
        idx = rng.choice(len(views), size=min(args.batch_size, len(views)), replace=False)
        for g in opt.param_groups:
            g["lr"] = lr_at(step, args)
        feats = features(idx)
        terms = []
        for k, i in enumerate(idx):
            pr = sample_prompts(views, int(i), rng, n_points=args.points_per_view, jitter=args.jitter)
            loss = view_loss(model, predictor, feats[k:k + 1], pr)
            if loss is not None:
                terms.append(loss)
        if not terms:
            losses.append(float("nan"))
            continue
        loss = torch.stack(terms).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trainable.parameters(), 1.0)
        opt.step()
        losses.append(float(loss.detach()))
        bar.set_postfix(loss=f"{np.nanmean(losses[-20:]):.3f}")
        if (step + 1) % args.save_every == 0 and step + 1 < args.steps:
            _atomic_torch_save({"key": key, "step": step + 1, "model": trainable.state_dict(),
                                "optim": opt.state_dict(), "losses": losses}, resume_path)
    model.eval()
    return losses

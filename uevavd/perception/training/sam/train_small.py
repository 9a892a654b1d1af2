"""Train the small SAM from scratch on a world's ground truth (``uevavd train-sam-small``).

Every part of the model (image encoder, prompt encoder, mask decoder) trains, on target
masks from jittered boxes and surrounding-object masks from ring points, Dice + BCE,
AdamW. The held-out mIoU (simple + hard contexts, else the last train context) goes into
a JSON report beside the checkpoint.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from segment_anything import SamPredictor

from ....atomic import atomic_write_json
from ....hashing import file_sha256
from ...sam.model import LoadedSam, SmallConfig, build_model, default_small_path, save_full
from ...sam.segmenter import SamSegmenter, images_to_input
from .data import GTViews, view_selection
from .evaluate import evaluate
from .loop import TrainArgs, loss_summary, train_loop


def train_small(
    train: GTViews,
    heldout: GTViews | None,
    *,
    out: str | os.PathLike[str] | None = None,
    config: SmallConfig = SmallConfig(),
    args: TrainArgs = TrainArgs(),
    fresh: bool = False,
    progress_eval: bool = True,
) -> dict:
    """Train a small SAM on ``train`` views, evaluate on ``heldout``, write the checkpoint
    (safetensors + metadata) to ``out`` (default: the ``sam`` plugin's default path) and
    ``<out>.report.json``. Returns the report."""
    out_path = Path(out).expanduser() if out else default_small_path()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    model = build_model("small", config)
    predictor = SamPredictor(model)
    # Resize once (ResizeLongestSide) and keep as uint8: the encoder input of every view.
    with torch.no_grad():
        inputs = torch.cat([images_to_input(train.images[i:i + 256], predictor).round().clamp(0, 255).to(torch.uint8)
                            for i in range(0, len(train), 256)])

    def features(idx: np.ndarray) -> torch.Tensor:
        return model.image_encoder(model.preprocess(inputs[torch.as_tensor(idx)].float()))

    data_hash = train.digest()
    settings = {"kind": "train-sam-small", "config": config.to_dict(), "data": data_hash}
    t0 = time.perf_counter()
    losses = train_loop(model, model, features, train, args, resume_path=out_path.with_name(out_path.name + ".resume"),
                        settings=settings, desc="train-sam-small", fresh=fresh)
    seconds = time.perf_counter() - t0
    meta = {"data_hash": data_hash, "image_size": list(train.images.shape[1:3]), "train": asdict(args),
            "n_train_views": len(train), "train_seconds_this_run": round(seconds, 1),
            "torch_threads": torch.get_num_threads()}
    # Which views trained the model (keys, contexts, per-context count, seed), so the mask-
    # quality report can leave them out of its train row; kept out of the printed report.
    save_full(out_path, model, "small", config, **meta, train_views=view_selection(train))
    report = {"checkpoint": str(out_path), "sha256": file_sha256(out_path), **meta,
              **loss_summary(losses)}
    if heldout is not None and len(heldout):
        seg = SamSegmenter(LoadedSam(model, "small", out_path, report["sha256"], meta), device="cpu")
        report["heldout"] = evaluate(seg, heldout, progress=progress_eval)
        report["n_heldout_views"] = len(heldout)
    resume = out_path.with_name(out_path.name + ".resume")
    if resume.exists():
        resume.unlink()
    atomic_write_json(out_path.with_name(out_path.name + ".report.json"), report)
    return report

"""Fine-tune a SAM's mask decoder on ground truth (``uevavd finetune-sam``).

The image encoder and the prompt encoder stay frozen, so every training view's image
embedding is computed once and cached on disk (keyed by the checkpoint's and the data's
hashes). The decoder trains on jittered box prompts of ground-truth target masks (and
ring points on surrounding objects, ``points_per_view``; 0 = target masks only) with
Dice + BCE and AdamW. Held-out mIoU is measured before and after; the changed weights
(the mask decoder) are saved with metadata naming the base checkpoint, loadable by the
``sam`` plugin.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ....atomic import atomic_write, atomic_write_json
from ....hashing import file_sha256
from ....paths import cache_dir
from ...sam.model import LoadedSam, load_sam, save_decoder
from ...sam.segmenter import SamSegmenter
from .data import GTViews, view_selection
from .evaluate import evaluate
from .loop import TrainArgs, loss_summary, train_loop


def cached_embeddings(seg: SamSegmenter, views: GTViews, base_sha: str, *, cache: Path | None = None,
                      chunk: int = 16) -> torch.Tensor:
    """(N, C, h, w) float16 image embeddings of ``views`` on CPU, computed once and cached at
    ``cache`` (default ``$UEVAVD_CACHE/sam/embeddings/<model>_<data>.pt``). Resumable: the
    chunks computed so far are kept in ``<cache>.partial/``."""
    path = cache or cache_dir() / "sam" / "embeddings" / f"{base_sha[:16]}_{views.digest()[:16]}.pt"
    if path.is_file():
        return torch.load(path, map_location="cpu", weights_only=True)
    part = path.with_name(path.name + ".partial")
    part.mkdir(parents=True, exist_ok=True)
    pieces = []
    for i in tqdm(range(0, len(views), chunk), desc="embedding", unit="chunk"):
        f = part / f"{i:07d}.pt"
        if f.is_file():
            pieces.append(torch.load(f, map_location="cpu", weights_only=True))
            continue
        e = seg.embed(views.images[i:i + chunk]).to("cpu", torch.float16)
        torch.save(e, f)
        pieces.append(e)
    emb = torch.cat(pieces)

    atomic_write(path, lambda fh: torch.save(emb, fh))
    for f in part.iterdir():
        f.unlink()
    part.rmdir()
    return emb


def finetune_model(
    checkpoint: str | os.PathLike[str],
    train: GTViews,
    heldout: GTViews | None,
    *,
    out: str | os.PathLike[str],
    model_type: str = "auto",
    device: str = "auto",
    args: TrainArgs = TrainArgs(lr=1e-4, steps=500, points_per_view=0),
    fresh: bool = False,
    embedding_cache: Path | None = None,
) -> tuple[dict, SamSegmenter]:
    """Fine-tune the mask decoder of ``checkpoint``; write ``out`` (decoder weights +
    metadata naming the base and the training views) and ``<out>.report.json`` (held-out
    mIoU before and after). Returns ``(report, segmenter over the fine-tuned model in
    memory)``; the segmenter has the default prompting settings."""
    out_path = Path(out).expanduser()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    base = load_sam(checkpoint, model_type)
    seg = SamSegmenter(base, device=device)
    model = seg.model
    report: dict = {"base_checkpoint": str(base.path), "base_sha256": base.sha256, "model_type": base.model_type}
    if heldout is not None and len(heldout):
        report["heldout_before"] = evaluate(seg, heldout, progress=True)
    emb = cached_embeddings(seg, train, base.sha256, cache=embedding_cache)
    for p in model.image_encoder.parameters():
        p.requires_grad_(False)
    for p in model.prompt_encoder.parameters():
        p.requires_grad_(False)

    def features(idx: np.ndarray) -> torch.Tensor:
        return emb[torch.as_tensor(idx)].to(seg.device, torch.float32)

    data_hash = train.digest()
    settings = {"kind": "finetune-sam", "base": base.sha256, "data": data_hash}
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    losses = train_loop(model, model.mask_decoder, features, train, args,
                        resume_path=out_path.with_name(out_path.name + ".resume"), settings=settings,
                        desc="finetune-sam", fresh=fresh)
    meta = {"data_hash": data_hash, "image_size": list(train.images.shape[1:3]), "train": asdict(args),
            "n_train_views": len(train), "train_seconds_this_run": round(time.perf_counter() - t0, 1)}
    save_decoder(out_path, model, base, **meta, train_views=view_selection(train))
    report.update(meta, checkpoint=str(out_path), sha256=file_sha256(out_path),
                  **loss_summary(losses))
    tuned = SamSegmenter(LoadedSam(model, base.model_type, out_path, report["sha256"], meta), device=device)
    if heldout is not None and len(heldout):
        report["heldout_after"] = evaluate(tuned, heldout, progress=True)
    resume = out_path.with_name(out_path.name + ".resume")
    if resume.exists():
        resume.unlink()
    atomic_write_json(out_path.with_name(out_path.name + ".report.json"), report)
    return report, tuned

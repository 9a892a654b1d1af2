"""Mask-quality figures for ``docs/sam.md``: mIoU per split and a picture of prompts and masks.

Views the model was trained on are left out of every split (the checkpoint's metadata
names them), so the train row measures unseen views of the training contexts.

    python -m uevavd.perception.sam.report WORLD --checkpoint FILE --json out.json --png docs/img/sam_views.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from ....atomic import atomic_write_json
from ...decompose import decompose
from ...sam import build_sam_segmenter
from ...sam.model import read_meta
from .data import load_views, read_manifest, selection_keys, train_and_heldout_contexts, view_key
from .evaluate import evaluate


def training_views(loaded, manifest) -> tuple[set[str] | None, str]:
    """(keys of the views of ``manifest`` the model was trained on, how that is known).

    From the checkpoint's metadata (``train_views``, written by ``train-sam-small`` and
    ``finetune-sam``); for a fine-tuned decoder, the base checkpoint's too. A checkpoint of
    ours written before that field existed: the selection is redrawn from its seed and
    count and accepted only when the redrawn views hash to the recorded ``data_hash``.
    ``None`` when our training metadata exists but the views cannot be recovered; an empty
    set when the file records no training here (an official checkpoint)."""
    metas = [loaded.meta]
    if loaded.meta.get("kind") == "decoder" and loaded.meta.get("base_checkpoint"):
        metas.append(read_meta(loaded.meta["base_checkpoint"]))
    keys: set[str] = set()
    how = []
    for meta in metas:
        if meta.get("train_views", {}).get("views"):
            keys |= selection_keys(meta["train_views"])
            how.append("recorded")
        elif meta.get("data_hash") and meta.get("n_train_views") and "seed" in meta.get("train", {}):
            ids = train_and_heldout_contexts(manifest)[0]
            per = int(meta["n_train_views"]) // len(ids)
            v = load_views(manifest, contexts=ids, per_context=per, seed=int(meta["train"]["seed"]))
            if v.digest() != meta["data_hash"]:
                return None, (f"the checkpoint records no training views and redrawing {per} per context with "
                              f"seed {meta['train']['seed']} does not reproduce its data hash")
            keys |= set(v.keys)
            how.append(f"redrawn ({per} per context, seed {meta['train']['seed']}), data hash verified")
    return keys, "; ".join(how) or "the checkpoint records no training on this data"


def miou_per_split(seg, root: str | Path, *, per_context: int = 60, seed: int = 123,
                   exclude: set[str] | None = None) -> dict:
    """{split: evaluate(...)} over ``per_context`` random views of each context of each split
    present under ``root``, drawn with ``seed`` from the views not in ``exclude`` (the
    keys of the views the model was trained on, see :func:`training_views`)."""
    m = read_manifest(root)
    split = {r.context: r.split for r in m if r.context is not None}
    exclude = exclude or set()
    out = {}
    for name in ("train", "simple", "hard"):
        ids = sorted(c for c, s in split.items() if s == name)
        if ids:
            v = load_views(m, contexts=ids, per_context=per_context, seed=seed, exclude=exclude)
            r = evaluate(seg, v, progress=True)
            out[name] = {k: r[k] for k in ("target_miou", "surround_miou", "n_target", "n_surround")}
            out[name]["contexts"] = ids
            out[name]["training_views_left_out"] = sum(
                1 for rec in m if rec.context in ids and view_key(rec) in exclude)
    return out


def _palette(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(40, 255, (max(n, 1), 3)).astype(np.uint8)


def _overlay(img: np.ndarray, masks: list[np.ndarray], colours: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    out = img.astype(np.float32)
    for m, c in zip(masks, colours, strict=False):
        out[m] = (1 - alpha) * out[m] + alpha * c
    return out.astype(np.uint8)


def picture(seg, views, idx, *, scale: int = 4) -> np.ndarray:
    """One row per view: image | ground truth | SAM prompts + masks | pre-decomposed view.
    Returns (rows*H*scale, 4*W*scale, 3) uint8 RGB."""
    res = seg.segment_detailed(views.images[idx], views.boxes[idx])
    rows = []
    for k, (i, r) in enumerate(zip(idx, res, strict=True)):
        img = views.images[i]
        h, w = img.shape[:2]
        ids = np.unique(views.seg[i])
        gt_masks = [views.seg[i] == t for t in ids]
        pal = _palette(len(ids), seed=k)
        tcol = np.array([255, 30, 30], np.uint8)
        gt_cols = np.stack([tcol if t in views.target_ids(i) else pal[j] for j, t in enumerate(ids)])
        gt = _overlay(img, gt_masks, gt_cols, 0.7)
        sam = _overlay(img, [*r.segments, r.target], np.vstack([_palette(len(r.segments), seed=k + 7)[:len(r.segments)],
                                                               tcol[None]]), 0.6)
        dec = decompose(img, r.target, r.segments, seed=k)
        panels = [cv2.resize(p, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST) for p in (img, gt, sam, dec)]
        big = panels[2]
        if r.box is not None:
            x1, y1, x2, y2 = (int(v) * scale for v in r.box)
            cv2.rectangle(big, (x1, y1), (x2 - 1, y2 - 1), (255, 230, 0), 1)
        for x, y in r.points:
            c = (int((x + 0.5) * scale), int((y + 0.5) * scale))
            cv2.circle(big, c, max(2, scale // 2), (255, 255, 255), -1)
            cv2.circle(big, c, max(2, scale // 2), (0, 0, 0), 1)
        sep = np.full((h * scale, 3, 3), 255, np.uint8)
        rows.append(np.hstack([panels[0], sep, panels[1], sep, big, sep, panels[3]]))
        rows.append(np.full((3, rows[-1].shape[1], 3), 255, np.uint8))
    return np.vstack(rows[:-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="mIoU per split and a prompts/masks picture for a SAM checkpoint")
    ap.add_argument("data", help="a synthetic world root with train / simple / hard contexts")
    ap.add_argument("--checkpoint", default=None, help="SAM checkpoint (default: the small model in the cache)")
    ap.add_argument("--per-context", type=int, default=60)
    ap.add_argument("--json", default=None, help="write the mIoU table here")
    ap.add_argument("--png", default=None, help="write the picture here")
    ap.add_argument("--views", type=int, default=4, help="views in the picture")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    import torch


    torch.set_num_threads(a.threads)
    seg = build_sam_segmenter(checkpoint=a.checkpoint, device="cpu")
    trained_on, how = training_views(seg.loaded, read_manifest(a.data))
    if trained_on is None:
        print(f"warning: {how}; the train row may include training views (optimistic)", file=sys.stderr)
    table = {"checkpoint": str(seg.loaded.path), "identity": seg.identity(),
             "training_views": {"n": None if trained_on is None else len(trained_on), "how": how},
             "splits": miou_per_split(seg, a.data, per_context=a.per_context, exclude=trained_on)}
    print(json.dumps(table, indent=2))
    if a.json:
        atomic_write_json(a.json, table)
    if a.png:
        m = read_manifest(a.data)
        ids = sorted({r.context for r in m if r.context is not None and r.split in ("simple", "hard")})
        v = load_views(m, contexts=ids or sorted({r.context for r in m if r.context}), per_context=40, seed=7)
        vis = [i for i in range(len(v)) if v.target_mask(i).sum() > 30]
        occl = [i for i in range(len(v)) if not v.boxes[i].any()]
        pick = vis[:: max(1, len(vis) // max(1, a.views - 1))][: a.views - 1] + occl[:1]
        img = picture(seg, v, np.array(pick))
        Path(a.png).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(a.png, cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        print(f"wrote {a.png}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

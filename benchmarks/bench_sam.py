"""Speed of the ``sam`` segmenter: image embeddings per second and decomposed views per second.

    python benchmarks/bench_sam.py                       # small SAM on CPU (threads: --threads)
    python benchmarks/bench_sam.py --model vit_b --device cuda --batch 32 --precision bf16

Weights are random unless --checkpoint is given (speed does not depend on them). Views
are synthetic-world crops when --data names a world, else textured random images. Baselines
measured in the same run: one image per encoder call (what ``SamPredictor.set_image`` does)
for embeddings, and the ``gt`` segmenter + decomposition for decomposed views.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def _images(n: int, size: int, data: str | None) -> tuple[np.ndarray, np.ndarray]:
    if data:
        from uevavd.perception.training.sam.data import load_views, read_manifest

        m = read_manifest(data)
        ctx = sorted({r.context for r in m if r.context is not None})
        v = load_views(m, contexts=ctx, per_context=max(1, n // len(ctx) + 1), seed=0)
        return v.images[:n], v.boxes[:n]
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 255, (n, size, size, 3), dtype=np.uint8)
    c, r = size // 2, max(2, size // 8)
    boxes = np.tile(np.array([c - r, c - r, c + r, c + r], np.int64), (n, 1))
    return imgs, boxes


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize()


def _rate(fn, n: int, dev: torch.device, *, min_s: float = 2.0) -> float:
    fn()  # warm-up
    _sync(dev)
    done, t0 = 0, time.perf_counter()
    while True:
        fn()
        done += n
        _sync(dev)
        if time.perf_counter() - t0 >= min_s:
            return done / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="small", help="small / vit_b / vit_l / vit_h (random weights)")
    ap.add_argument("--checkpoint", default=None, help="use this checkpoint instead of random weights")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (more can be slower on a busy machine)")
    ap.add_argument("--batch", type=int, default=16, help="images per encoder call")
    ap.add_argument("--precision", default="fp32", choices=["fp32", "bf16"])
    ap.add_argument("--size", type=int, default=64, help="crop size of the random images")
    ap.add_argument("--n", type=int, default=64, help="views per timed round")
    ap.add_argument("--ring-points", type=int, default=16)
    ap.add_argument("--data", default=None, help="a synthetic world root to take views from")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)

    from uevavd.perception.decompose import decompose
    from uevavd.perception.sam.model import LoadedSam, build_model, load_sam
    from uevavd.perception.sam.segmenter import SamSegmenter

    if a.checkpoint:
        loaded = load_sam(a.checkpoint)
    else:
        torch.manual_seed(0)
        loaded = LoadedSam(build_model(a.model), a.model, None, "random", {})  # type: ignore[arg-type]
    seg = SamSegmenter(loaded, device=a.device, batch_size=a.batch, precision=a.precision,
                       ring_points=a.ring_points)
    dev = seg.device
    images, boxes = _images(a.n, a.size, a.data)
    n = len(images)
    print(f"model {loaded.model_type}, device {dev} ({torch.cuda.get_device_name(dev) if dev.type == 'cuda' else f'{a.threads} threads'}), "
          f"{a.precision}, images {images.shape[1]}x{images.shape[2]}, encoder input {seg.model.image_encoder.img_size}")

    with torch.inference_mode():
        one = _rate(lambda: [seg.embed(images[i:i + 1]) for i in range(min(n, 8))], min(n, 8), dev)
        batched = _rate(lambda: seg.embed(images), n, dev)
    print(f"embeddings/s  one image per call: {one:8.1f}   batch {a.batch}: {batched:8.1f}   ratio {batched / one:5.2f}x")

    def sam_views():
        out = seg.segment(images, boxes)
        for i, s in enumerate(out):
            decompose(images[i], s.target, s.segments, seed=i)

    views = _rate(sam_views, n, dev)
    # Baseline: ground-truth segments (a box-shaped target, four quadrants around it).
    h, w = images.shape[1:3]
    maps = np.zeros((n, h, w), np.uint16)
    maps[:, : h // 2, : w // 2], maps[:, : h // 2, w // 2:], maps[:, h // 2:, : w // 2] = 2, 3, 4
    for i, b in enumerate(boxes):
        maps[i, b[1]:b[3], b[0]:b[2]] = 1
    cats = [{1: "target", 2: "building", 3: "tree", 4: "road", 0: "ground"}] * n
    from uevavd.perception.segmenters import build_gt

    gt = build_gt()

    def gt_views():
        out = gt.segment(images, boxes, instance_maps=maps, categories=cats)
        for i, s in enumerate(out):
            decompose(images[i], s.target, s.segments, seed=i)

    base = _rate(gt_views, n, dev)
    print(f"decomposed views/s  sam ({a.ring_points} ring points): {views:8.1f}   gt segmenter: {base:8.1f}   "
          f"ratio {views / base:5.3f}x")


if __name__ == "__main__":
    main()

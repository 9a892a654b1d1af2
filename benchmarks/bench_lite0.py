"""EfficientNet-Lite0 inference as ``prepare`` runs it, against the same model without the
padding fold, in one process (the demo's table stage).

``fold_lite0`` folds the batch norms into the convolutions and, for every convolution whose
TF-"same" padding is symmetric, pads inside ``conv2d`` instead of through a ``ZeroPad2d``
copy (ReLU6 in place). This times both on the same images, in the batch size ``prepare``
uses, alternating, and checks that their outputs are bit-identical.

    python benchmarks/bench_lite0.py [--size 64] [--images 2048] [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from uevavd.perception import efficientnet
from uevavd.perception.efficientnet import build_efficientnet_lite0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--images", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    # smooth images (an upsampled 8 x 8 noise field), like rendered views more than white noise
    small = rng.integers(0, 256, (args.images, 8, 8, 3), dtype=np.uint8)
    images = np.ascontiguousarray(small.repeat(args.size // 8, axis=1).repeat(args.size // 8, axis=2))
    fast = build_efficientnet_lite0(weights="imagenet", device="cpu")
    real = efficientnet._pad_in_conv
    efficientnet._pad_in_conv = lambda model: None  # the baseline: batch norms folded, padding copied
    try:
        base = build_efficientnet_lite0(weights="imagenet", device="cpu")
    finally:
        efficientnet._pad_in_conv = real
    times: dict[str, list[float]] = {"baseline (ZeroPad2d copies)": [], "fold_lite0 (padding in conv2d)": []}
    outputs = {}
    for _ in range(args.repeats):
        for name, enc in zip(times, (base, fast), strict=True):
            t0 = time.perf_counter()
            outputs[name] = enc.encode(images)
            times[name].append(time.perf_counter() - t0)
    a, b = outputs.values()
    print(f"EfficientNet-Lite0 features of {args.images} images at {args.size} px, {args.threads} threads, "
          f"best of {args.repeats}:")
    best = {k: min(v) for k, v in times.items()}
    for name, t in best.items():
        print(f"  {name:<32} {t:6.2f} s  {args.images / t:7.0f} images/s")
    print(f"  speed-up {best['baseline (ZeroPad2d copies)'] / best['fold_lite0 (padding in conv2d)']:.2f}x; "
          f"outputs bit-identical: {bool(np.array_equal(a, b))}")


if __name__ == "__main__":
    main()

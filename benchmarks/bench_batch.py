"""Images per batch of the perception forward on a CPU: the automatic size against batches of 256.

A table runs three network forwards per view (the encoder for MAP's table, again on IBE-MAP's
decomposed views, the recognizer). This script times the quick preset's encoder
(EfficientNet-Lite0, ImageNet) and the paper's ResNet50 (random weights: the time does not
depend on them) over random views, in batches of 256 (the former default) and of the automatic
size (:data:`uevavd.perception.nets.CPU_BATCH_PIXELS` pixels), in one process, and checks that
every view's output is the same bit for bit whatever its batch.

    python benchmarks/bench_batch.py [--threads 2] [--views 1024]

Prints ms per view and the ratio per network and size, and the machine-speed reference
(``../shared/tools/refwork.py``) where it exists.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import torchvision
from machine_speed import refwork

from uevavd.perception.efficientnet import build_efficientnet_lite0
from uevavd.perception.nets import BatchRunner


def ms_per_view(runner: BatchRunner, images: np.ndarray, batch: int | None, repeats: int) -> tuple[float, np.ndarray]:
    runner.batch_size = batch
    runner(images)  # warm: the folding, the allocator's and oneDNN's first-call work at this batch
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = runner(images)
        best = min(best, time.perf_counter() - t0)
    return 1e3 * best / len(images), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2, the demo's)")
    ap.add_argument("--views", type=int, default=1024, help="views of 64 px timed per network (256 px: an eighth)")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes, the best kept")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    resnet50 = torchvision.models.resnet50()
    resnet50.fc = torch.nn.Identity()
    nets = (("efficientnet_lite0 (quick)", build_efficientnet_lite0(weights="imagenet", device="cpu").runner),
            ("resnet50 (paper)", BatchRunner(resnet50, device="cpu")))
    print(refwork())
    print(f"torch {torch.__version__}, {args.threads} thread(s)\n")
    print("| network | px | batch | ms per view, batches of 256 | ms per view, automatic | ratio | same outputs |")
    print("|---|---|---|---|---|---|---|")
    for name, runner in nets:
        for px in (64, 256):
            n = args.views if px == 64 else max(16, args.views // 8)
            images = rng.integers(0, 256, (n, px, px, 3), dtype=np.uint8)
            old, ref = ms_per_view(runner, images, 256, args.repeats)
            new, out = ms_per_view(runner, images, None, args.repeats)
            runner.batch_size = None
            print(f"| {name} | {px} | {runner.batch_of(images)} | {old:.2f} | {new:.2f} | {old / new:.2f}x | "
                  f"{np.array_equal(out, ref)} |")
    print("\n" + refwork())


if __name__ == "__main__":
    main()

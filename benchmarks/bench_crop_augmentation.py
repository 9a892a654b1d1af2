"""What augmenting the crops before encoding (DrQ / RAD) would cost, against the augmentation of
the table's features that the library ships (``train.feature_dropout``).

    python benchmarks/bench_crop_augmentation.py [--device cpu] [--threads 2] [--repeats 5] [--run RUN_DIR]

One update of ``ibe_map_aug`` at the paper64 preset's sizes (Lite0's 1280-d features, g_t 160,
s_t 128, head 128, a 64-episode batch on a stand-in table, episode lengths as a trained
policy's: bench_update.py's replay) reads the features of the views its episodes saw from the
table, each feature dropped with p = 0.3. DrQ and RAD would instead shift each of those views'
crops by up to 4 px (replicate padding) and jitter its brightness, contrast and saturation by
up to 40 %, then run the encoder on them again: the table cannot hold an augmented view, so
every update encodes its batch's views. This times both on the same batches, interleaved (the
median of ``--repeats`` rounds of ``--updates`` updates): the update, the crops' augmentation
and the encoder (the library's EfficientNet-Lite0 at 64 px, as ``prepare`` runs it), each
update's crops padded to a multiple of ``--bucket`` so the encoder sees a few batch shapes (on
CUDA every new shape is slow the first time). Work per image does not depend on content: the
crops are smooth random images.

With ``--run`` (a finished run of ``ibe_map_aug``, e.g. one of the paper64 ablation's), the
run's own update count and training time project what its training would take with the crops
augmented instead.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from bench_update import stand_in_replay

PAD = 4  # DrQ's shift
JITTER = 0.4  # RAD's colour jitter strength


def augment_crops(crops: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> the same, each shifted by up to PAD px (replicate padding) and its
    brightness, contrast and saturation scaled by a factor drawn from [1 - JITTER, 1 + JITTER]."""
    n, h, w, _ = crops.shape
    x = F.pad(crops.permute(0, 3, 1, 2).float(), (PAD,) * 4, mode="replicate")
    dy, dx = (torch.randint(0, 2 * PAD + 1, (n,), generator=g) for _ in range(2))
    rows = (dy[:, None] + torch.arange(h))[:, None, :, None]
    cols = (dx[:, None] + torch.arange(w))[:, None, None, :]
    x = x[torch.arange(n)[:, None, None, None], torch.arange(3)[None, :, None, None], rows, cols]
    b, c, s = (1 + JITTER * (2 * torch.rand(n, 1, 1, 1, generator=g) - 1) for _ in range(3))
    x = x * b
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * c + mean
    gray = x.mean(dim=1, keepdim=True)
    x = (x - gray) * s + gray
    return x.clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5, help="rounds, each timing both paths on the same batches")
    ap.add_argument("--updates", type=int, default=20, help="updates per timed round")
    ap.add_argument("--size", type=int, default=64, help="crop size in pixels (the paper's is 256)")
    ap.add_argument("--bucket", type=int, default=32,
                    help="pad each update's crops to a multiple of this (repeating the last), so the encoder sees a "
                         "few shapes, as an implementation would (1: no padding)")
    ap.add_argument("--run", type=Path, default=None, help="a finished ibe_map_aug run to project")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()
    from uevavd.config import load_method
    from uevavd.env.batched import EnvTensors
    from uevavd.env.config import EnvConfig
    from uevavd.perception.efficientnet import build_efficientnet_lite0
    from uevavd.policy.learner import FeatureDropout, FeatureLookup, Learner, needed_observations
    from uevavd.policy.network import build_network
    from uevavd.presets import load_preset
    from uevavd.testing.policy import toy_table

    dev = torch.device(args.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    spec = load_method("ibe_map_aug", overrides=load_preset("paper64")["overrides"])
    table = toy_table(n_train=100, n_hard=25, feature_dim=1280)
    cfg = EnvConfig()
    tensors = EnvTensors(table, "train", cfg, device=dev, features_dtype=torch.float16)
    lookup = FeatureLookup(tensors)
    torch.manual_seed(0)
    net = build_network(spec.state, spec.head, table.feature_dim, n_ranges=cfg.max_range).to(dev)
    train = spec.train_config(seed=0)
    learner = Learner(net, lr=train.lr, gamma=cfg.gamma, grad_clip=train.grad_clip,
                      augment=FeatureDropout(train.feature_dropout, seed=0, device=dev))
    replay = stand_in_replay(tensors, cfg.t_max, device=str(dev))
    encoder = build_efficientnet_lite0(weights="imagenet", device=str(dev))
    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, (4096, 8, 8, 3), dtype=np.uint8)  # smooth images, like rendered views
    crops = torch.from_numpy(small.repeat(args.size // 8, axis=1).repeat(args.size // 8, axis=2))
    g = torch.Generator().manual_seed(0)

    times: dict[str, list[float]] = {"update": [], "augment": [], "encode": []}
    n_crops: list[int] = []
    for rnd in range(args.repeats + 1):  # the first round warms up
        batches = [replay.sample(64, 0.4) for _ in range(args.updates)]
        seen = [int(needed_observations(b).sum()) for b in batches]
        sync()
        t0 = time.perf_counter()
        for b in batches:
            learner.update(b, lookup)
        sync()
        t1 = time.perf_counter()
        padded = [-(-n // args.bucket) * args.bucket for n in seen]
        augmented = [augment_crops(crops[torch.randint(0, len(crops), (n,), generator=g)], g) for n in padded]
        t2 = time.perf_counter()
        for a in augmented:
            encoder.encode(a.numpy())
        sync()
        t3 = time.perf_counter()
        if rnd:
            for k, t in zip(times, (t1 - t0, t2 - t1, t3 - t2), strict=True):
                times[k].append(1000 * t / args.updates)
            n_crops += seen
    ms = {k: statistics.median(v) for k, v in times.items()}
    crop_ms = ms["augment"] + ms["encode"]
    print(f"device {dev}, torch threads {torch.get_num_threads()}; ibe_map_aug at paper64 sizes, 64-episode batches, "
          f"{args.size} px crops; median of {args.repeats} rounds x {args.updates} updates")
    print(f"  views read per update: {statistics.mean(n_crops):.0f} (range {min(n_crops)}-{max(n_crops)}), "
          f"encoded padded to a multiple of {args.bucket}")
    print(f"  update with feature dropout (the library's)   {ms['update']:8.1f} ms")
    print(f"  crops: augment {ms['augment']:.1f} ms + encode {ms['encode']:.1f} ms  {crop_ms:8.1f} ms  "
          f"({1000 * statistics.mean(n_crops) / ms['encode']:.0f} views/s through the encoder)")
    print(f"  update with the crops augmented instead         {ms['update'] + crop_ms:8.1f} ms   "
          f"x{(ms['update'] + crop_ms) / ms['update']:.1f} the update")
    for contexts, size in ((150, args.size), (150, 256)):
        print(f"  crops held in memory for {contexts} contexts x 605 views at {size} px: "
              f"{contexts * 605 * size * size * 3 / 2**30:.1f} GiB (uint8)")
    if args.run is not None:
        last = json.loads((args.run / "done.json").read_text())
        extra = last["updates"] * crop_ms / 1000
        print(f"  {args.run}: {last['updates']:,} updates in {last['wall_s']:.0f} s of training; with the crops "
              f"augmented: +{extra:.0f} s, x{(last['wall_s'] + extra) / last['wall_s']:.1f} the run")


if __name__ == "__main__":
    main()

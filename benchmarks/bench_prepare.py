"""How close does ``uevavd prepare`` come to the bare forward of its models?

For each (encoder, image size) configuration, in the same run:

* bare forward: the encoder and the classifier (ResNet18) on images already decoded in
  memory, in the batch size ``prepare`` uses (this is the compute ``prepare`` cannot avoid);
* bare encoder alone, for reference;
* ``prepare_table`` from scratch on a dataset of PNGs: decoding in worker threads,
  (optionally) pre-decomposition from the ground-truth segmentation, both forwards, the
  per-scene shards and the final table write.

The ratio pipeline time / bare forward time is the overhead of loading and writing
(goal: <= 1.25). ``setup`` (reading the dataset, building the models, the key; a fixed cost
per run, timed separately with ``plan_table``) is also reported, and the ratio without it;
``decode`` is the loading threads alone on the same files (images/s; with ``--decompose`` also
the instance maps and the pre-decomposition), the pipeline's other ceiling. Weights are random (speed does not depend on them). Without ``--data``
a stand-in dataset (smooth random images in the UEVAVD layout, ``--scenes`` contexts of
605 views) is written to a temporary folder; pass ``--data`` to time a real world.

Run: ``python benchmarks/bench_prepare.py [--threads 2] [--scenes 2] [--device cpu]
[--config resnet18:128 --config resnet50:256] [--decompose]``.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from uevavd.data.grid import N_VIEWS, view_coords
from uevavd.data.layout import view_stem
from uevavd.data.splits import TARGETS
from uevavd.perception.classifier import load_classifier, write_classifier_file
from uevavd.perception.efficientnet import build_efficientnet_lite0
from uevavd.perception.encoders import build_resnet18, build_resnet50
from uevavd.perception.images import Decoder
from uevavd.perception.prepare import _load_scene as load_scene
from uevavd.perception.prepare import plan_table, prepare_table
from uevavd.perception.weights import make_resnet

METHOD = """
name = "bench"
[perception]
segmenter = {{ name = "gt" }}
encoder = {{ name = "{arch}", weights = "random", device = "{device}", batch_size = {batch} }}
classifier = {{ name = "resnet18", device = "{device}", batch_size = {batch} }}
decompose = {decompose}
"""


def write_standin(root: Path, n_scenes: int, size: int) -> None:
    """Contexts 1, 31, 61, ... (one per block) with smooth images, boxes, instance maps."""
    rng = np.random.default_rng(0)
    for i in range(n_scenes):
        cid = 1 + 30 * (i % 5) + i // 5
        scene, target = f"{cid:03d}", TARGETS[(cid - 1) // 30]
        d = root / scene
        (d / "seg").mkdir(parents=True, exist_ok=True)
        base = cv2.resize(rng.integers(0, 255, (size // 8, size // 8, 3), dtype=np.uint8), (size, size))
        seg = np.zeros((size, size), np.uint16)
        seg[: size // 3] = 2
        seg[size // 3 :, : size // 2] = 3
        c = size // 2
        seg[c - size // 10 : c + size // 10, c - size // 6 : c + size // 6] = 1
        for v in range(N_VIEWS):
            stem = view_stem(*view_coords(v), target, scene)
            img = np.roll(base, v % size, axis=1)
            cv2.imwrite(str(d / f"{stem}.png"), img)
            cv2.imwrite(str(d / "seg" / f"{stem}.png"), seg)
            (d / f"{stem}.txt").write_text(f"{c - size // 6} {c - size // 10} {c + size // 6} {c + size // 10}\n")
        (d / "seg" / "categories.json").write_text(json.dumps({"0": "none", "1": "target", "2": "building",
                                                               "3": "tree"}))


def bare_forward(arch: str, images: np.ndarray, device: str, batch: int, clf_path: Path, repeats: int = 2):
    """Images/s of encoder + classifier, and of the encoder alone (best of ``repeats``)."""
    builders = {"resnet18": build_resnet18, "resnet50": build_resnet50,
                "efficientnet_lite0": build_efficientnet_lite0}
    enc = builders[arch](weights="random", device=device, batch_size=batch)
    clf = load_classifier(clf_path, device=device, batch_size=batch)
    enc.encode(images[:batch])
    clf.predict_proba(images[:batch])  # warm-up
    both, alone = [], []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        enc.encode(images)
        sync(device)
        t1 = time.perf_counter()
        clf.predict_proba(images)
        sync(device)
        t2 = time.perf_counter()
        alone.append(t1 - t)
        both.append(t2 - t)
    return len(images) / min(both), len(images) / min(alone)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--workers", type=int, default=2, help="prepare's decoding threads")
    ap.add_argument("--scenes", type=int, default=2, help="stand-in context scenes (605 views each)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=1, help="bare-forward repeats (best is kept)")
    ap.add_argument("--config", action="append", default=None, metavar="ARCH:SIZE",
                    help="encoder and image size (repeatable; default resnet18:128 and resnet50:256; "
                         "efficientnet_lite0:64 is the quick preset's)")
    ap.add_argument("--decompose", action="store_true", help="also pre-decompose (gt segmenter)")
    ap.add_argument("--profile", default=None, metavar="FILE",
                    help="append cProfile's top functions of each prepare run to FILE")
    ap.add_argument("--data", default=None, help="time this dataset instead of a stand-in (its own size)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    configs = [c.split(":") for c in (args.config or ["resnet18:128", "resnet50:256"])]
    work = Path(tempfile.mkdtemp(prefix="uevavd-bench-prepare-"))
    try:
        clf_path = write_classifier_file(work / "clf.safetensors", make_resnet("resnet18", num_classes=5).state_dict(),
                                         {"arch": "resnet18", "classes": list(TARGETS), "mean": [0.485, 0.456, 0.406],
                                          "std": [0.229, 0.224, 0.225]})
        print(f"torch {torch.__version__}, {args.threads} threads, device {args.device}, decode workers "
              f"{args.workers}, decompose {args.decompose}")
        print(f"{'config':<16}{'views':>7}{'bare enc+clf':>14}{'bare enc':>11}{'prepare':>10}{'ratio':>7}"
              f"{'setup':>8}{'prepare-setup':>15}{'ratio':>7}{'decode':>11}")
        for arch, size in configs:
            size = int(size)
            if args.data:
                root = Path(args.data)
            else:
                root = work / f"data{size}"
                if not root.exists():
                    write_standin(root, args.scenes, size)
            from uevavd.data.reader import read_dataset

            manifest = read_dataset(root)
            recs = [r for r in manifest.records if r.context is not None]
            with Decoder(args.workers) as dec:
                dec.images([r.image for r in recs[: 2 * args.workers]])  # threads started
                t = time.perf_counter()
                images = dec.images([r.image for r in recs])
                decode = len(recs) / (time.perf_counter() - t)
            both, alone = bare_forward(arch, images, args.device, args.batch, clf_path, args.repeats)
            del images
            method = work / f"{arch}.toml"
            method.write_text(METHOD.format(arch=arch, device=args.device, batch=args.batch,
                                            decompose=str(args.decompose).lower()))
            out = work / f"tables-{arch}-{size}"
            t = time.perf_counter()
            tp = plan_table(root, method, classifier_path=clf_path)  # setup alone: read data, build models, key
            setup = time.perf_counter() - t
            if args.decompose:  # the loader's ceiling: decode images and instance maps, pre-decompose
                with Decoder(args.workers) as dec:
                    t = time.perf_counter()
                    for scene, scene_recs in tp.scenes:
                        load_scene(dec, tp.manifest, scene, scene_recs, tp.segmenter, tp.gray_seed)
                    decode = len(recs) / (time.perf_counter() - t)
            del tp
            prof = cProfile.Profile() if args.profile else None
            t = time.perf_counter()
            if prof:
                prof.enable()
            prepare_table(root, method, classifier_path=clf_path, out_dir=out, workers=args.workers,
                          progress=False)
            sync(args.device)
            total = time.perf_counter() - t
            if prof:
                prof.disable()
                with open(args.profile, "a") as fh:
                    fh.write(f"# prepare_table, {arch} at {size} px, {len(recs)} views\n")
                    pstats.Stats(prof, stream=fh).sort_stats("cumulative").print_stats(40)
            pipe, steady = len(recs) / total, len(recs) / max(total - setup, 1e-9)
            shutil.rmtree(out, ignore_errors=True)
            label = f"{arch}@{manifest.image_size[0]}px"
            print(f"{label:<16}{len(recs):>7}{both:>12.1f}/s{alone:>9.1f}/s{pipe:>8.1f}/s{both / pipe:>7.2f}"
                  f"{setup:>7.1f}s{steady:>13.1f}/s{both / steady:>7.2f}{decode:>9.1f}/s")
            sys.stdout.flush()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

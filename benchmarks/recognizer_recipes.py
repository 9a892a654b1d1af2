"""Choose the quick preset's recognizer recipe on training data only.

Each recipe ``ARCH:INIT:EPOCHS:LR`` trains a recognizer on the world's ``train_605`` crops
(``uevavd.perception.training.classifier.train_classifier``, the settings of the quick preset otherwise),
then is judged by its accuracy on the *clear* views (visible >= 0.9) of the world's training
contexts: views of the training contexts are never used to train the recognizer, so this is
held-out data, and no test split is read. Also printed: held-out ``train_605`` accuracy and
the training time.

    python benchmarks/recognizer_recipes.py --world WORLD \\
        resnet18:random:4:3e-3 efficientnet_lite0:imagenet:4:1e-3 efficientnet_lite0:imagenet:4:3e-3

WORLD: a written synthetic world (``uevavd synth --preset quick --out WORLD``, or the demo's
cached one under ``$UEVAVD_CACHE/worlds``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("/tmp/uevavd-recipes"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("recipes", nargs="+", metavar="ARCH:INIT:EPOCHS:LR")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.data.reader import read_dataset
    from uevavd.data.splits import TARGETS
    from uevavd.perception.classifier import load_classifier
    from uevavd.perception.images import Decoder
    from uevavd.perception.training.classifier import ClassifierRecipe, train_classifier
    from uevavd.presets import load_preset
    from uevavd.runtime import tune_malloc

    tune_malloc()
    quick = load_preset("quick")
    manifest = read_dataset(args.world)
    recs = [r for r in manifest.records if r.split == "train" and r.visible is not None and r.visible >= 0.9]
    with Decoder(2) as dec:
        images = dec.images([r.image for r in recs])
    labels = np.array([TARGETS.index(r.target) for r in recs])
    contexts = np.array([r.context for r in recs])
    print(f"{len(recs)} clear views of {len(set(contexts.tolist()))} training contexts")
    rows = []
    for recipe in args.recipes:
        arch, init, epochs, lr = recipe.split(":")
        settings = ClassifierRecipe.from_preset(quick, arch=arch, init=init, epochs=int(epochs), lr=float(lr),
                                                seed=args.seed)
        path = args.out / f"{arch}-{init}-{epochs}-{lr}-seed{args.seed}.safetensors"
        t0 = time.perf_counter()
        train_classifier(args.world, path, settings=settings, workers=2, progress=False, threads=args.threads)
        seconds = time.perf_counter() - t0
        clf = load_classifier(path, device="cpu")
        correct = clf.predict_proba(images).argmax(1) == labels
        per_ctx = [correct[contexts == c].mean() for c in sorted(set(contexts.tolist()))]
        val = clf.meta["train"]["val_accuracy"]
        rows.append((recipe, val, correct.mean(), min(per_ctx), seconds))
        print(f"{recipe}: held-out train_605 {val:.3f}, clear views of training contexts {correct.mean():.3f} "
              f"(lowest context {min(per_ctx):.3f}), {seconds:.0f} s", flush=True)
    print("\n| recipe (arch:init:epochs:lr) | held-out train_605 | clear views, training contexts | lowest context "
          "| training + report (s) |\n|---|---|---|---|---|")
    for recipe, val, acc, low, sec in rows:
        print(f"| {recipe} | {val:.3f} | {acc:.3f} | {low:.3f} | {sec:.0f} |")


if __name__ == "__main__":
    main()

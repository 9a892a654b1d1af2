"""CLI commands of the perception layer: ``train-classifier`` and ``prepare``."""

from __future__ import annotations

import argparse
import logging


def _logging() -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")


def add_train_classifier(p: argparse.ArgumentParser):
    from .training.classifier import ClassifierRecipe

    d = ClassifierRecipe()
    p.add_argument("data", help="dataset root (UEVAVD layout) holding the train_605 scene")
    p.add_argument("--out", default=None,
                   help="output .safetensors (default: <cache>/classifiers/<data hash>.safetensors, "
                        "where `uevavd prepare` looks)")
    p.add_argument("--arch", default=d.arch, choices=["resnet18", "efficientnet_lite0"],
                   help="recognizer network (the paper's is resnet18)")
    p.add_argument("--init", default=d.init, choices=["imagenet", "random"],
                   help="initial weights: ImageNet (resnet18: torch's cache or --imagenet, else random with a "
                        "warning; efficientnet_lite0: its installed package) or random")
    p.add_argument("--epochs", type=int, default=d.epochs)
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--val-fraction", type=float, default=d.val_fraction,
                   help="share of the 605 viewpoints held out for validation")
    p.add_argument("--imagenet", default=None,
                   help="ImageNet ResNet18 weights file to start from (default: torch's cache, else random)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--max-views", type=int, default=None,
                   help="train on a seeded sample of this many viewpoints (default: all 605)")
    p.add_argument("--workers", type=int, default=2, help="image decoding threads")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--device", default="auto", help="where the network trains: auto (CUDA when present), cpu, cuda")

    def run(args) -> int:
        from .nets import resolve_device
        from .training.classifier import ClassifierRecipe, train_classifier

        _logging()
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        resolve_device(args.device)  # a bad or absent device is refused before any work
        s = ClassifierRecipe(arch=args.arch, init=args.init, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                          val_fraction=args.val_fraction, seed=args.seed, max_views=args.max_views)
        path = train_classifier(args.data, args.out, settings=s, imagenet=args.imagenet, workers=args.workers,
                                device=args.device)
        print(path)
        print(f"report: {path.with_suffix('.md')}")
        return 0

    return run


def add_prepare(p: argparse.ArgumentParser):
    p.add_argument("data", help="dataset root (UEVAVD layout)")
    p.add_argument("--method", required=True, help="registered method name or a method TOML path")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a method key, e.g. --set perception.encoder.weights=random (repeatable)")
    p.add_argument("--classifier", default=None, help="classifier .safetensors (default: the dataset's default)")
    p.add_argument("--out", default=None, help="tables folder (default: <cache>/tables)")
    p.add_argument("--workers", type=int, default=2, help="image decoding threads")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local: this process; ray: scenes sharded over Ray tasks (a local Ray instance, "
                        "or the cluster at RAY_ADDRESS; workers must share --out)")
    p.add_argument("--shards", type=int, default=None,
                   help="Ray tasks to split the scenes into (default: the cluster's CPUs)")

    def run(args) -> int:
        from ..config import parse_override

        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        from .prepare import prepare_table

        _logging()
        overrides = dict(parse_override(s) for s in args.overrides)
        if args.backend == "ray":
            from .prepare_ray import prepare_table_ray

            path = prepare_table_ray(args.data, args.method, classifier_path=args.classifier,
                                     overrides=overrides or None, out_dir=args.out, shards=args.shards)
        else:
            path = prepare_table(args.data, args.method, classifier_path=args.classifier,
                                 overrides=overrides or None, out_dir=args.out, workers=args.workers)
        print(path)
        return 0

    return run

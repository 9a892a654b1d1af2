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
    return out


def run_info(args: argparse.Namespace) -> int:
    data = info_dict()
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for key in ("uevavd", "python", "platform", "torch", "device", "cpu_threads"):
        if key in data:
            print(f"{key:>12}: {data[key]}")
    print("  components:")
    for kind, names in data["components"].items():
        print(f"{kind:>12}: {', '.join(names) or '-'}")
    print("       paths:")
    for key, value in data["paths"].items():
        print(f"{key:>12}: {value}")
    print(f"{'presets':>12}: {', '.join(data['presets'])}")
    return 0

"""``uevavd plugins``: the installed plugins and what each registered, by kind (never imports torch)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any


def add_plugins(parser: argparse.ArgumentParser):
    parser.add_argument("--all", action="store_true", help="also list blocked and failed plugins, with errors")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return run_plugins


def plugin_rows(include_all: bool) -> list[dict[str, Any]]:
    from .manager import manager

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

    from .manager import PluginWarning

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

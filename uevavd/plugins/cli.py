"""``uevavd plugins``: the installed plugins and what each registered, by kind (never imports torch)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any


def add_plugins(parser: argparse.ArgumentParser):
    parser.add_argument("--all", action="store_true", help="also list blocked and failed plugins, with errors")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--check", metavar="MODULE",
                        help="check the plugin whose hooks MODULE holds (its import name, e.g. my_plugin): every "
                             "component built and run through its kind's rules, every method trained a few hundred "
                             "toy episodes and evaluated (uevavd.testing.check_plugin); exit 1 listing what is wrong")
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

    if args.check:
        return _check(args.check)

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


def _check(module: str) -> int:
    import importlib
    import importlib.util

    from .manager import manager

    # an installed plugin's name (`uevavd plugins` lists it), or its distribution's (the pip name),
    # stands for the module its entry point names
    source = next((p.source for p in manager.plugins if p.name == module and not p.builtin), None)
    if source is None:
        points = _entry_points(module, distribution=True)
        source = points[0] if len(points) == 1 else module
    try:
        found = importlib.util.find_spec(source.partition(":")[0]) is not None
    except ImportError:
        found = False
    if not found:
        print(f"uevavd plugins --check: no module named {module!r} is importable and no installed plugin has that "
              "name: give the import name of the module that holds the plugin's hooks (the value of its uevavd "
              "entry point)", file=sys.stderr)
        return 2
    from ..plugins.registry import import_target
    from ..testing.plugins import check_plugin

    try:
        target = import_target(source) if ":" in source else importlib.import_module(source)
    except Exception as exc:  # the plugin's own code failed: the module and the error, one line
        print(f"uevavd plugins --check: importing {source!r} failed: {type(exc).__name__}: {exc}; fix the plugin "
              "module (UEVAVD_DEBUG=1 shows the traceback)", file=sys.stderr)
        if os.environ.get("UEVAVD_DEBUG"):
            raise
        return 2
    try:
        report = check_plugin(target)
    except AssertionError as exc:
        inside = _entry_points(source.partition(":")[0], distribution=False)
        if "registered nothing" in str(exc) and inside:  # a package whose hooks live in a module of it
            print(f"uevavd plugins --check: {module!r} holds no uevavd hooks itself; its package's uevavd entry "
                  f"point{'s name' if len(inside) > 1 else ' names'} {', '.join(map(repr, inside))}: run `uevavd "
                  f"plugins --check {inside[0]}`", file=sys.stderr)
            return 2
        print(exc, file=sys.stderr)
        return 1
    print(report)
    return 0


def _entry_points(name: str, *, distribution: bool) -> list[str]:
    """The values of the installed ``uevavd`` entry points that ``name`` stands for: those of the
    distribution named so (``distribution``; its pip name, any spelling of - _ .), or those
    naming a module inside package ``name``."""
    import re
    from importlib import metadata

    from . import ENTRY_POINT_GROUP

    def norm(text: str) -> str:
        return re.sub(r"[-_.]+", "-", text).lower()

    out = []
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        dist = getattr(ep, "dist", None)
        if distribution and dist is not None and norm(dist.name) == norm(name):
            out.append(ep.value)
        elif not distribution and ep.value.partition(":")[0].startswith(name + "."):
            out.append(ep.value)
    return sorted(set(out))

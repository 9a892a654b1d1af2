"""The package's structure in figures, for this checkout and a baseline commit
read in the same run: the import-graph walk of tests/test_architecture.py applied to both.

Prints, per checkout: modules and those over 400 lines; imports of the package's own
modules inside functions (all, and outside the lazy command-line / API / ``__init__``
loading); import cycles at module level and in the whole graph once the written lazy edges
and mutual pairs (``MUTUAL``) are left out; private names imported from another module; the length of the trainer's
``_train``; and the calls of ``load_method`` in ``experiments/`` (each a place that resolves
a method spec). Nothing is imported from either checkout: both are read as syntax trees.

Run: ``python benchmarks/architecture_figures.py [--baseline 7865887]`` (7865887: the commit
before the structure's review).
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAZY_LOADERS = ("__init__.py", "cli.py")  # the written lazy edges (docs/architecture.md)
LAZY_MODULES = ("api.py", "info.py")


def _walker():
    """tests/test_architecture.py, whose walk the suite holds the package to."""
    spec = importlib.util.spec_from_file_location("test_architecture", REPO / "tests" / "test_architecture.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def figures(root: Path) -> dict[str, int]:
    """The figures of the package folder ``root`` (a checkout's ``uevavd/``)."""
    a = _walker()
    mods = a._modules(root)
    out = dict.fromkeys(("modules", "over 400 lines", "function-level own imports", "  outside the lazy loading",
                         "module-level import cycles", "whole-graph cycles outside the written edges",
                         "private names imported across modules", "trainer _train lines",
                         "load_method calls in experiments/"), 0)
    top, whole = {}, {}
    for name, (path, tree) in mods.items():
        rel = str(path.relative_to(root))
        out["modules"] += 1
        out["over 400 lines"] += len(path.read_text(encoding="utf-8").splitlines()) > 400
        top[name] = {t for n in tree.body if a._own_import(n) for t in a._target(mods, name, path, n)} - {name}
        runtime = a._runtime_imports(tree)
        inner = [n for fn in ast.walk(tree) if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef)
                 for n in ast.walk(fn) if a._own_import(n)]
        out["function-level own imports"] += len({id(n) for n in inner})
        if path.name not in LAZY_LOADERS and rel not in LAZY_MODULES:
            out["  outside the lazy loading"] += len({id(n) for n in inner})
        lazy = path.name in LAZY_LOADERS
        whole[name] = set() if lazy else {t for n in runtime for t in a._target(mods, name, path, n)
                                          if (rel, n.module) not in a.MUTUAL} - {name}
        out["private names imported across modules"] += sum(
            al.name.startswith("_") and not al.name.startswith("__") for n in ast.walk(tree) if a._own_import(n)
            for al in n.names)
        for node in ast.walk(tree):
            if rel == "policy/trainer.py" and isinstance(node, ast.FunctionDef) and node.name == "_train":
                out["trainer _train lines"] = node.end_lineno - node.lineno + 1
            if (rel.startswith("experiments/") and isinstance(node, ast.Call)
                    and getattr(node.func, "id", getattr(node.func, "attr", None)) == "load_method"):
                out["load_method calls in experiments/"] += 1
    out["module-level import cycles"] = len(a._cycles(top))
    out["whole-graph cycles outside the written edges"] = len(a._cycles(whole))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default="7865887", help="the commit to compare with (default: %(default)s)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            archive = subprocess.run(["git", "-C", str(REPO), "archive", args.baseline, "uevavd"],
                                     check=True, capture_output=True).stdout
        except subprocess.CalledProcessError as exc:
            print(f"--baseline {args.baseline}: {exc.stderr.decode().strip()}", file=sys.stderr)
            return 2
        (Path(tmp) / "base.tar").write_bytes(archive)
        with tarfile.open(Path(tmp) / "base.tar") as tar:
            tar.extractall(tmp, filter="data")
        base, now = figures(Path(tmp) / "uevavd"), figures(REPO / "uevavd")
    width = max(map(len, now))
    print(f"{'figure':<{width}}  {args.baseline:>9}  {'this':>6}")
    for key in now:
        print(f"{key:<{width}}  {base[key]:>9}  {now[key]:>6}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

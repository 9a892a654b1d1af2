"""Built-in methods: every TOML file in ``model_zoo/methods/``."""

from __future__ import annotations

from pathlib import Path

from . import hookimpl

METHODS_DIR = Path(__file__).resolve().parent.parent / "model_zoo" / "methods"


@hookimpl
def register_methods(registry):
    for path in sorted(METHODS_DIR.glob("*.toml")):
        if path.stem.startswith("_"):
            continue  # partial configs meant only for inheritance
        first = ""
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.startswith("description"):
                first = line.split("=", 1)[1].strip().strip('"')
                break
        registry.add(path.stem, str(path), summary=first)

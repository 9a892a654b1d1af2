"""Where uevavd keeps its caches (observation tables, trained weights, worlds).

``UEVAVD_CACHE`` overrides the root; the default is ``$XDG_CACHE_HOME/uevavd`` or
``~/.cache/uevavd``. Never a path relative to the working directory.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    root = os.environ.get("UEVAVD_CACHE")
    if root:
        return Path(root).expanduser().resolve()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return (base / "uevavd").resolve()


def tables_dir() -> Path:
    """Observation tables, one folder per key."""
    return cache_dir() / "tables"


def torch_hub_dir() -> Path:
    """torch's own cache of downloaded weights (``$TORCH_HOME/hub/checkpoints``)."""
    torch_home = os.environ.get("TORCH_HOME")
    if torch_home:
        base = Path(torch_home).expanduser()
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        base = (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "torch"
    return (base / "hub" / "checkpoints").resolve()

"""uevavd: UAV active object detection (AOD) research on the UEVAVD dataset.

The package is layered (each layer imports only the ones before it)::

    data -> perception -> env -> state -> policy -> experiments

Importing ``uevavd`` is cheap: nothing heavy (torch, plugins) loads until used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["__version__", "load_method", "MethodSpec", "registry"]

if TYPE_CHECKING:  # pragma: no cover
    from .config import MethodSpec, load_method
    from .plugins.manager import registry


def __getattr__(name: str) -> Any:
    # Lazy attributes keep `import uevavd` (and `uevavd plugins`) fast and torch-free.
    if name in ("load_method", "MethodSpec"):
        from . import config

        return getattr(config, name)
    if name == "registry":
        from .plugins.manager import registry

        return registry
    raise AttributeError(f"module 'uevavd' has no attribute {name!r}")

"""uevavd: UAV active object detection (AOD) research on the UEVAVD dataset.

The package is layered (each layer imports only the ones before it)::

    data -> perception -> table -> env -> state -> policy -> experiments

(see docs/architecture.md)

Importing ``uevavd`` is cheap: nothing heavy (torch, plugins) loads until used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .version import __version__

#: The researcher's API (:mod:`uevavd.api`), importable from the top level.
API = ("train_classifier", "build_table", "train", "load_run", "Run", "load_policy_file", "evaluate_pretrained",
       "policy_network", "save_network", "ablate", "Ablation")
__all__ = ["__version__", "load_method", "load_preset", "MethodSpec", "registry", "train_classifier", "build_table",
           "train", "load_run", "Run", "load_policy_file", "evaluate_pretrained", "policy_network", "save_network",
           "ablate", "Ablation"]

if TYPE_CHECKING:  # pragma: no cover
    from .api import (
        Ablation,
        Run,
        ablate,
        build_table,
        evaluate_pretrained,
        load_policy_file,
        load_run,
        policy_network,
        save_network,
        train,
        train_classifier,
    )
    from .config import MethodSpec, load_method
    from .plugins.manager import registry
    from .presets import load_preset


def __getattr__(name: str) -> Any:
    # Lazy attributes keep `import uevavd` (and `uevavd plugins`) fast and torch-free.
    if name in ("load_method", "MethodSpec"):
        from . import config

        return getattr(config, name)
    if name == "registry":
        from .plugins.manager import registry

        return registry
    if name == "load_preset":
        from .presets import load_preset

        return load_preset
    if name in API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'uevavd' has no attribute {name!r}")


def __dir__() -> list[str]:
    # the lazily loaded API too, so tab completion and help() list it (PEP 562)
    return sorted({*globals(), *__all__})

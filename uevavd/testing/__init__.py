"""Contract checks that plugin authors run in their own CI, like gymnasium's ``check_env``.

    from uevavd.testing import check_encoder, check_plugin
    check_encoder(my_pkg.build_vit(weights="random"))
    check_plugin(my_pkg)   # every component and method of a plugin package, trained on a toy table

Each check raises ``AssertionError`` with a message saying what is wrong.
"""

from __future__ import annotations

from typing import Any

_CHECKS = {
    "check_registry_entry": "uevavd.testing.plugins",
    "check_plugin_module": "uevavd.testing.plugins",
    "check_plugin": "uevavd.testing.plugins",
    "check_baseline": "uevavd.testing.plugins",
    "check_segmenter": "uevavd.testing.perception",
    "check_encoder": "uevavd.testing.perception",
    "check_classifier": "uevavd.testing.perception",
    "check_state_estimator": "uevavd.testing.policy",
    "check_head": "uevavd.testing.policy",
}

__all__ = sorted(_CHECKS)


def __getattr__(name: str) -> Any:
    if name in _CHECKS:
        import importlib

        return getattr(importlib.import_module(_CHECKS[name]), name)
    raise AttributeError(f"module 'uevavd.testing' has no attribute {name!r}")

"""The plugin system: pluggy hooks, one per component kind, each receiving a registry.

A plugin module (built-in or third-party, through the ``uevavd`` entry-point group)
implements hooks from :mod:`uevavd.plugins.hookspecs`::

    from uevavd.plugins import hookimpl

    @hookimpl
    def register_encoders(registry):
        registry.add("my_vit", "my_pkg.encoders:build_vit", summary="A ViT-S/16 encoder")

Builders named by "module:attr" strings are imported only when built.
"""

from __future__ import annotations

import pluggy

PROJECT = "uevavd"
ENTRY_POINT_GROUP = "uevavd"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)
"""The decorator a plugin puts on its implementations of :mod:`uevavd.plugins.hookspecs`."""

__all__ = ["PROJECT", "ENTRY_POINT_GROUP", "hookspec", "hookimpl"]

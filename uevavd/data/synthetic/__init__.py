"""The synthetic UEVAVD world: procedural scenes, a ray-casting renderer and a writer to
the UEVAVD on-disk layout (see ``docs/synthetic_world.md``)."""

from __future__ import annotations

from .render import ContextViews, View, render_context, render_view, render_views
from .world import BLOCK_TARGETS, Scene, build_context, build_unoccluded, target_of

__all__ = [
    "BLOCK_TARGETS",
    "ContextViews",
    "Scene",
    "View",
    "build_context",
    "build_unoccluded",
    "render_context",
    "render_view",
    "render_views",
    "target_of",
    "write_world",
]


def __getattr__(name: str):
    if name == "write_world":
        from .writer import write_world

        return write_world
    raise AttributeError(name)

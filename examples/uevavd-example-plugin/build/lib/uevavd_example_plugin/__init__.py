"""An example uevavd plugin: one module, hooks that register components by "module:attr".

Nothing heavy is imported here: uevavd imports the builders only when they are built.
"""

from uevavd.plugins import hookimpl


@hookimpl
def register_encoders(registry):
    registry.add(
        "color_hist",
        "uevavd_example_plugin.components:build_color_hist",
        summary="Per-channel colour histograms (a cheap, deterministic baseline encoder)",
    )


@hookimpl
def register_segmenters(registry):
    registry.add(
        "box",
        "uevavd_example_plugin.components:build_box_segmenter",
        summary="Target = its box; surroundings = the four bands around it",
    )


@hookimpl
def register_methods(registry):
    registry.add(
        "memo_map_hist",
        "uevavd_example_plugin:methods/memo_map_hist.toml",
        summary="Memo-MAP with the colour-histogram encoder",
    )

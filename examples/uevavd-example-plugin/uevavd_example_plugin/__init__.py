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
def register_state_estimators(registry):
    registry.add(
        "lstm",
        "uevavd_example_plugin.policies:build_lstm",
        summary="LSTM over the episode's observations (memory = [h, c])",
    )


@hookimpl
def register_baselines(registry):
    registry.add(
        "confident_stop",
        "uevavd_example_plugin.policies:build_confident_stop",
        summary="stop where the recognizer is confident, else one random allowed action",
        tags=("seeded",),
        label="Confident stop",
    )


@hookimpl
def register_methods(registry):
    registry.add(
        "memo_map_hist",
        "uevavd_example_plugin:methods/memo_map_hist.toml",
        summary="Memo-MAP with the colour-histogram encoder",
    )
    registry.add(
        "memo_map_lstm",
        "uevavd_example_plugin:methods/memo_map_lstm.toml",
        summary="Memo-MAP with the LSTM state estimator",
        label="Memo-MAP (LSTM)",
    )

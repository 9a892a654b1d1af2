"""Built-in state estimators."""

from __future__ import annotations

from ..plugins import hookimpl


@hookimpl
def register_state_estimators(registry):
    registry.add("single_view", "uevavd.state.single_view:build_single_view",
                 summary="MAP: MLP on the current g_t only")
    registry.add("gru", "uevavd.state.gru:build_gru",
                 summary="Memo-MAP / IBE-MAP: GRU over the episode's g_1..g_t")

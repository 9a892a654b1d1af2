"""Built-in baselines: what every evaluation shows beside a learned policy."""

from __future__ import annotations

from ..plugins import hookimpl


@hookimpl
def register_baselines(registry):
    registry.add("random", "uevavd.env.baselines:build_random", tags=("seeded",),
                 summary="uniform over the distinct allowed actions (one run per RL seed)")
    registry.add("passive", "uevavd.env.baselines:build_passive", summary="stop at once: classify the first view")
    registry.add("box_gate", "uevavd.env.baselines:build_box_gate",
                 summary="scripted, observation only: stop where the target's box is non-empty, else one fixed "
                         "move chosen on the training contexts")
    registry.add("pose_seek", "uevavd.env.baselines:build_pose_seek",
                 summary="scripted, observation and pose: stop where the target's box is non-empty, else fly "
                         "toward the column above the target (moves chosen on the training contexts)")
    registry.add("departure_ceiling", "uevavd.env.baselines:build_departure_ceiling",
                 summary="privileged: pose_seek, departed from once where the context's exact values gain (the "
                         "ceiling of a method anchored to the rule)")
    registry.add("departure_ceiling2", "uevavd.env.baselines:build_departure_ceiling2",
                 summary="privileged: pose_seek, departed from at most twice with the context's exact values")
    registry.add("visibility_oracle", "uevavd.env.baselines:build_visibility_oracle",
                 summary="knows every view's visible fraction, flies the cheapest path to the most visible "
                         "reachable view (tables with visible fractions)")
    registry.add("oracle", "uevavd.env.baselines:build_oracle",
                 summary="knows the class: the optimal return (an upper bound, not a reachable target)")

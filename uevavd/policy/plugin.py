"""Built-in Q-value heads."""

from __future__ import annotations

from ..plugins import hookimpl


@hookimpl
def register_heads(registry):
    registry.add("dueling_branch", "uevavd.policy.heads:build_branching_dueling",
                 summary="Two-channel dueling head (type 7, range 4), shared value stream")
    registry.add("dueling_joint", "uevavd.policy.heads:build_joint_dueling",
                 summary="Joint 28-way dueling head over (type, range)")
    registry.add("ensemble_branch", "uevavd.policy.heads:build_ensemble_branching",
                 summary="Ensemble of two-channel dueling heads acting on mean - kappa * std")

"""Contract checks for ``state`` and ``head`` plugins, and a small learnable toy table.

    from uevavd.testing import check_state_estimator, check_head
    check_state_estimator(my_pkg.build_lstm(feature_dim=16))
    check_head(my_pkg.build_my_head(state_dim=32))
"""

from __future__ import annotations

from typing import Any

from ..policy.contract import ComponentError, check_estimator_rules, check_head_rules
from ..toy import toy_table  # noqa: F401  (the tests' and plugin authors' import)


def check_state_estimator(est: Any, *, batch: int = 3, steps: int = 4) -> None:
    """Shapes, causality (s_t never reads o_{>t}), the memory at an episode start (zeros),
    and step() agreeing with forward(): the rules `uevavd train` checks before a run
    (:func:`uevavd.policy.contract.check_estimator_rules`), as an ``AssertionError``."""
    try:
        check_estimator_rules(est, batch=batch, steps=steps, what=f"state estimator {type(est).__name__}")
    except ComponentError as exc:
        raise AssertionError(str(exc)) from None


def check_head(head: Any, *, state_dim: int | None = None, n_types: int = 7, n_ranges: int = 4) -> None:
    """forward/greedy/taken/bootstrap/weights shapes, masks respected, gradients flow: the
    rules `uevavd train` checks (:func:`uevavd.policy.contract.check_head_rules`)."""
    try:
        check_head_rules(head, state_dim=int(state_dim or head.state_dim), n_types=n_types, n_ranges=n_ranges,
                         what=f"head {type(head).__name__}")
    except ComponentError as exc:
        raise AssertionError(str(exc)) from None


#: Method overrides that make a run tiny (networks of 16-24 units, 16 environments, epochs of
#: 100 episodes, one evaluated context): for tests on :func:`toy_table` (feature_dim 8).
SMALL_RUN = {
    "state.input_dim": 24, "state.box_dim": 8, "state.state_dim": 16,
    "head.hidden": 16, "train.n_envs": 16, "train.batch_size": 8, "train.buffer_episodes": 400,
    "train.learning_starts": 40, "train.updates_per_step": 1.0, "train.target_update": 5,
    "train.epoch_episodes": 100, "train.eval_contexts": 1, "train.threads": 1,
}


def small_run(method: str) -> dict[str, Any]:
    """:data:`SMALL_RUN` for ``method``; the GRU methods' hidden size too."""
    return {**SMALL_RUN, **({"state.hidden": 16} if method != "map" else {})}

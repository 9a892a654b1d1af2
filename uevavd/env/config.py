"""Constants of the AOD episode and reward (docs/environment.md, "Episode and reward"), one frozen dataclass.

A method's ``[env]`` TOML section is checked against the fields of :class:`EnvConfig`;
unknown keys are an error listing these names.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..data.grid import N_TYPES, N_VIEWS, NX, NY
from ..data.splits import N_BLOCKS, TRAIN_PER_BLOCK


def _where(cond: Any, a: Any, b: Any) -> Any:
    """``a if cond else b`` for a bool, ``np.where`` for an array, ``torch.where`` for a
    tensor (float64: where neither branch is a tensor, ``a`` becomes a float64 tensor, since
    two Python scalars would give a float32 result; a scalar beside a tensor keeps its dtype)."""
    if isinstance(cond, bool | np.bool_):
        return a if cond else b
    if isinstance(cond, np.ndarray):
        return np.where(cond, a, b)
    import torch  # only callers that hold tensors get here, and they have torch loaded

    if not isinstance(a, torch.Tensor) and not isinstance(b, torch.Tensor):
        a = torch.tensor(a, dtype=torch.float64, device=cond.device)
    return torch.where(cond, a, b)


#: What a run recorded before an env setting existed ran with: read into its recorded ``env``
#: section on resume (:func:`uevavd.policy.rundir.with_legacy_settings`).
LEGACY_ENV = {"train_per_block": 0, "holdout_block": 0, "pose": False}
#: The longest move that can stay on the grid (across its wider side), and a cap on the
#: decisions of an episode (the paper's 5; buffers are allocated for t_max + 1 observations).
MAX_RANGE = max(NX, NY) - 1
MAX_T_MAX = 100


class EnvConfigError(ValueError):
    """An environment constant is out of its range; the message names it and the range."""


@dataclass(frozen=True)
class EnvConfig:
    """Episode and reward constants of the AOD CMDP (defaults are the paper's).

    Reward (Eq. 2, 3): at the episode's end ``+xi1 - sigma*r`` if recognised, else
    ``-xi1 - sigma*r``; at every other step ``-xi2 - sigma*r``; ``sigma = 0`` for stop and
    ``C`` for a move, ``r`` the *requested* range in grid steps (range index + 1).
    """

    t_max: int = 5
    """T_max: most decisions per episode. A move at decision T_max-1 ends the episode."""
    max_range: int = 4
    """A: range indices 0..A-1 request 1..A grid steps of 10 m (action space (7, A))."""
    gamma: float = 0.9
    """Discount of the reported return sum_t gamma^t R_t (and the oracle's DP)."""
    xi1: float = 0.5
    """Terminal reward magnitude: +xi1 if the final view is recognised, -xi1 if not."""
    xi2: float = 0.1
    """Per-step penalty of a non-terminal move."""
    C: float = 0.02
    """Movement cost per requested grid step (sigma for a move; 0 for stop)."""
    thre: float = 0.2
    """Recognised means the classifier's probability for the true class is > thre."""
    start: str = "uniform"
    """Start view: "uniform" over the 605 views, or a view index as a string ("302")."""
    train_per_block: int = 0
    """Training contexts per target block that the "train" split holds: the first N of each
    block's training contexts in the table, by context id (0 = all of them). The number of
    training contexts is an experiment axis of its own (``uevavd ablate --sweep
    env.train_per_block=4,10,20``); a run trains, and is evaluated on "train", on those
    contexts only, and the test splits are untouched. A block holding fewer is an error."""
    holdout_block: int = 0
    """A target block (1..5: contexts 1-30, 31-60, ...) whose training contexts a run leaves out
    of its "train" split whole (0 = none): they join the "validation" split, a held-out set
    that is itself a distribution shift (an unseen target in unseen contexts), for choosing a
    setting on training data only. The test splits are untouched."""
    pose: bool = False
    """Add a ``pose`` entry to every observation: the viewpoint's (x, y, z) relative to the
    target, in metres, float32, in the grid's frame (target at the origin; x right, y forward, z
    up; x, y in -50..50, z in 60..100). The paper's task gives the target's position at the start
    ("the target's initial position is given beforehand"), so the drone's pose relative to it is
    information an agent may use; off by default, so the paper's observation (image and box) and
    every published method's inputs stay as they were."""

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> EnvConfigError:
            return EnvConfigError(f"EnvConfig.{name}={getattr(self, name)!r}: expected {expected}")

        for name, most in (("t_max", MAX_T_MAX), ("max_range", MAX_RANGE)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= most:
                raise bad(name, f"an integer in 1..{most}")
        if not isinstance(self.pose, bool | np.bool_):
            raise bad("pose", "true or false (add the viewpoint's pose to the observation)")
        v = self.train_per_block
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= TRAIN_PER_BLOCK:
            raise bad("train_per_block", f"an integer in 0..{TRAIN_PER_BLOCK} (training contexts per target "
                      "block; 0 = all the table holds)")
        v = self.holdout_block
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= N_BLOCKS:
            raise bad("holdout_block", f"an integer in 0..{N_BLOCKS} (a target block whose training contexts are "
                      "held out; 0 = none)")
        for name in ("gamma", "xi1", "xi2", "C", "thre"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise bad(name, "a finite number")
        if not 0.0 <= self.gamma <= 1.0:
            raise bad("gamma", "a discount in [0, 1]")
        for name in ("xi1", "xi2", "C"):
            if getattr(self, name) < 0:
                raise bad(name, "a number >= 0 (the sign is part of the reward's definition)")
        if not 0.0 <= self.thre < 1.0:
            raise bad("thre", "a probability threshold in [0, 1)")
        _ = self.start_view  # validates start

    # -- the reward (Eq. 2, 3): the one place it is written ------------------------------------
    # The Gymnasium env (Python scalars), the batched env and evaluation (torch tensors), the
    # class-knowing oracle's DP and the visibility oracle's path costs (numpy arrays) all call
    # these, so a new reward term is written here and nowhere else.
    def move_cost(self, range_index: Any) -> Any:
        """sigma * r of a move: ``C`` times the requested grid steps (range index + 1)."""
        return self.C * (range_index + 1)

    def terminal_reward(self, recognized: Any) -> Any:
        """``+xi1`` where the final view is recognised, ``-xi1`` where not."""
        return _where(recognized, self.xi1, -self.xi1)

    def recognized(self, true_class_probs: Any) -> Any:
        """The paper's recognition rule: a view is recognised where the recognizer's
        probability for the true class is above ``thre`` (elementwise; e.g. on
        ``table.true_class_probs()``, (S, 605) -> bool)."""
        return true_class_probs > self.thre

    def reward(self, final: Any, recognized: Any, cost: Any) -> Any:
        """R_t: ``terminal_reward(recognized) - cost`` where the decision ends the episode,
        ``-xi2 - cost`` where it does not (``cost`` is :meth:`move_cost`, 0 for stop).
        Elementwise on bools, numpy arrays or torch tensors (float64 there: no float32
        constant, so every path gives the same bits)."""
        return _where(final, self.terminal_reward(recognized), -self.xi2) - cost

    @property
    def start_view(self) -> int | None:
        """The fixed start view index, or None when starts are uniform over the 605 views."""
        s = str(self.start).strip().lower()
        if s == "uniform":
            return None
        try:
            v = int(s)
        except ValueError:
            v = -1
        if not 0 <= v < N_VIEWS:
            raise EnvConfigError(
                f"EnvConfig.start={self.start!r}: expected 'uniform' or a view index 0..{N_VIEWS - 1}"
            )
        return v

    @property
    def n_actions(self) -> int:
        """Size of the joint action space, 7 * A (type-major: index = type * A + range)."""
        return N_TYPES * self.max_range

    def replace(self, **changes: Any) -> EnvConfig:
        """A copy with some fields changed (validated); unknown names are an error."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise EnvConfigError(f"unknown EnvConfig field(s) {unknown}: expected among {sorted(names)}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every field by name (what runs and exports record)."""
        return dataclasses.asdict(self)


def make_config(config: EnvConfig | dict[str, Any] | None = None, **overrides: Any) -> EnvConfig:
    """An :class:`EnvConfig` from a config, a dict of fields (e.g. a TOML section) or None."""
    if config is None:
        config = EnvConfig()
    elif isinstance(config, dict):
        config = EnvConfig().replace(**config)
    elif not isinstance(config, EnvConfig):
        raise EnvConfigError(f"config={config!r}: expected an EnvConfig, a dict of its fields or None")
    return config.replace(**overrides) if overrides else config

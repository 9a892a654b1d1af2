"""Q heads (``head`` plugins): map the state s_t to Q-values over (type, range) actions.

A head is an ``nn.Module`` whose ``forward(s)`` returns a tuple of Q tensors ("branches")
and which knows how to act greedily, read the Q of taken actions and bootstrap a TD
target from them (the math is in :mod:`uevavd.policy.targets`). s: (..., state_dim)
float32; masks: (..., 7, A) bool from the environment.
"""

from __future__ import annotations

from typing import Literal, Protocol, runtime_checkable

import torch
from torch import nn

from ..config_rules import ConfigError, check_widths
from . import targets as T


@runtime_checkable
class QHead(Protocol):
    """What a head (``head`` plugin) provides; ``policy/contract.py`` checks it before a run.

    ``forward(s)`` maps states (..., state_dim) to a tuple of ``n_branches`` Q tensors (the
    branches, e.g. Q_type (..., 7) and Q_range (..., A)); ``greedy(q, mask)`` returns the
    greedy (type, range) indices, each (...) int64, among the actions ``mask`` (..., 7, A)
    allows (None: all); ``taken(q, a_type, a_range)`` the Q of the taken actions (..., K), one
    column per TD target the head learns; ``bootstrap(q_online, q_target, mask)`` the double-DQN
    bootstrap values (..., K) at the next states (the online net's greedy actions evaluated by
    the target net); ``weights(a_type)`` (..., K) the weight of each column in the loss (a
    branch the taken action does not use, such as stop's range, weighs 0).
    """

    state_dim: int
    n_branches: int

    def __call__(self, s: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """States (..., state_dim) -> the branches' Q tensors (``forward``, as an nn.Module)."""

    def greedy(self, q: tuple[torch.Tensor, ...], mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The greedy (type, range) indices among the allowed actions."""

    def taken(self, q: tuple[torch.Tensor, ...], a_type: torch.Tensor, a_range: torch.Tensor) -> torch.Tensor:
        """The Q of the taken actions, (..., K)."""

    def bootstrap(self, q_online: tuple[torch.Tensor, ...], q_target: tuple[torch.Tensor, ...],
                  mask: torch.Tensor | None) -> torch.Tensor:
        """The double-DQN bootstrap values at the next states, (..., K)."""

    def weights(self, a_type: torch.Tensor) -> torch.Tensor:
        """Each TD column's weight in the loss for the taken action types, (..., K)."""


def _mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inp, hidden), nn.ReLU(), nn.Linear(hidden, out))


class BranchingDuelingHead(nn.Module):
    """Two-channel dueling head: shared value V(s), advantages A_type (7) and A_range (A);
    Q_type = V + A_type - mean A_type, Q_range = V + A_range - mean A_range."""

    n_branches = 2

    def __init__(self, state_dim: int, hidden: int, n_types: int, n_ranges: int, td_target: str) -> None:
        super().__init__()
        if td_target not in ("mean", "indep"):
            raise ValueError(f"td_target={td_target!r}: expected 'mean' or 'indep'")
        self.state_dim, self.n_types, self.n_ranges, self.td_target = state_dim, n_types, n_ranges, td_target
        self.value = _mlp(state_dim, hidden, 1)
        self.adv_type = _mlp(state_dim, hidden, n_types)
        self.adv_range = _mlp(state_dim, hidden, n_ranges)

    def forward(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """s (..., state_dim) -> (Q_type (..., 7), Q_range (..., A))."""
        v = self.value(s)
        return T.dueling(v, self.adv_type(s)), T.dueling(v, self.adv_range(s))

    def greedy(self, q: tuple[torch.Tensor, ...], mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The allowed type with the highest Q_type, then that type's allowed range with the
        highest Q_range (stop's range is 0)."""
        return T.branch_greedy(q[0], q[1], mask)

    def taken(self, q: tuple[torch.Tensor, ...], a_type: torch.Tensor, a_range: torch.Tensor) -> torch.Tensor:
        """(..., K=2): Q_type(s, a_type), Q_range(s, a_range)."""
        return torch.stack(
            [q[0].gather(-1, a_type[..., None])[..., 0], q[1].gather(-1, a_range[..., None])[..., 0]], dim=-1
        )

    def bootstrap(
        self, q_online: tuple[torch.Tensor, ...], q_target: tuple[torch.Tensor, ...], mask: torch.Tensor | None
    ) -> torch.Tensor:
        """Both branches' targets at the online net's greedy action, evaluated by the target
        net: their mean (``td_target = "mean"``) or each its own (``"indep"``)."""
        a_type, a_range = self.greedy(q_online, mask)
        return T.branch_bootstrap(q_target[0], q_target[1], a_type, a_range, self.td_target)

    def weights(self, a_type: torch.Tensor) -> torch.Tensor:
        """(..., 2): the type branch always counts; the range branch only where a move was taken."""
        return T.branch_weights(a_type)


class JointDuelingHead(nn.Module):
    """Standard dueling DQN over the 7*A joint actions (type-major: index = type*A + range).

    Stop ignores its range (as in the environment), so it is one action: greedy choices and
    the Q of a taken stop use its range-0 entry only (:func:`~uevavd.policy.targets.joint_index`),
    which keeps stop's experience in one value and the max from picking among its copies."""

    n_branches = 1

    def __init__(self, state_dim: int, hidden: int, n_types: int, n_ranges: int) -> None:
        super().__init__()
        self.state_dim, self.n_types, self.n_ranges = state_dim, n_types, n_ranges
        self.value = _mlp(state_dim, hidden, 1)
        self.advantage = _mlp(state_dim, hidden, n_types * n_ranges)

    def forward(self, s: torch.Tensor) -> tuple[torch.Tensor]:
        return (T.dueling(self.value(s), self.advantage(s)),)

    def greedy(self, q: tuple[torch.Tensor, ...], mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        return T.joint_greedy(q[0], mask, self.n_ranges)

    def taken(self, q: tuple[torch.Tensor, ...], a_type: torch.Tensor, a_range: torch.Tensor) -> torch.Tensor:
        return q[0].gather(-1, T.joint_index(a_type, a_range, self.n_ranges)[..., None])

    def bootstrap(
        self, q_online: tuple[torch.Tensor, ...], q_target: tuple[torch.Tensor, ...], mask: torch.Tensor | None
    ) -> torch.Tensor:
        a_type, a_range = self.greedy(q_online, mask)
        return self.taken(q_target, a_type, a_range)

    def weights(self, a_type: torch.Tensor) -> torch.Tensor:
        return torch.ones(*a_type.shape, 1, device=a_type.device)


class EnsembleBranchingHead(nn.Module):
    """``members`` two-channel dueling heads on one state (an ensemble for acting).

    Each member learns its own double-DQN target (its own greedy next action, valued by its own
    target copy), so the members differ only by their initial weights and agree where the data
    pins the values down. The ensemble acts greedily on each branch's ``mean - kappa * std``
    over the members: ``kappa > 0`` prefers actions the members agree are good (on an unfamiliar
    context they disagree, and a flight there costs), ``kappa = 0`` acts on the mean, ``kappa < 0``
    on an optimistic bound (EDE's exploration where the members disagree)."""

    def __init__(self, state_dim: int, hidden: int, n_types: int, n_ranges: int, td_target: str, members: int,
                 kappa: float) -> None:
        super().__init__()
        self.state_dim, self.n_types, self.n_ranges, self.kappa = state_dim, n_types, n_ranges, kappa
        self.members = nn.ModuleList(BranchingDuelingHead(state_dim, hidden, n_types, n_ranges, td_target)
                                     for _ in range(members))
        self.n_branches = 2 * members

    def forward(self, s: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(q for member in self.members for q in member(s))

    def _bound(self, q: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        """Each branch's ``mean - kappa * std`` over the members (population std)."""
        out = []
        for branch in (torch.stack(q[0::2]), torch.stack(q[1::2])):
            mean = branch.mean(0)
            out.append(mean - self.kappa * branch.std(0, correction=0) if self.kappa else mean)
        return out[0], out[1]

    def greedy(self, q: tuple[torch.Tensor, ...], mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        return T.branch_greedy(*self._bound(q), mask)

    def taken(self, q: tuple[torch.Tensor, ...], a_type: torch.Tensor, a_range: torch.Tensor) -> torch.Tensor:
        """(..., 2 * members): each member's Q_type(s, a_type), Q_range(s, a_range)."""
        return torch.cat([m.taken(q[2 * i:2 * i + 2], a_type, a_range) for i, m in enumerate(self.members)], -1)

    def bootstrap(
        self, q_online: tuple[torch.Tensor, ...], q_target: tuple[torch.Tensor, ...], mask: torch.Tensor | None
    ) -> torch.Tensor:
        return torch.cat([m.bootstrap(q_online[2 * i:2 * i + 2], q_target[2 * i:2 * i + 2], mask)
                          for i, m in enumerate(self.members)], -1)

    def weights(self, a_type: torch.Tensor) -> torch.Tensor:
        return T.branch_weights(a_type).repeat(*([1] * a_type.dim()), len(self.members))


def build_branching_dueling(
    *,
    state_dim: int = 512,
    hidden: int = 256,
    n_types: int = 7,
    n_ranges: int = 4,
    td_target: Literal["mean", "indep"] = "mean",
) -> BranchingDuelingHead:
    """MAP's two-channel dueling head; ``td_target`` "mean" (BDQ) or "indep"."""
    check_widths("head", state_dim=state_dim, hidden=hidden)
    return BranchingDuelingHead(state_dim, hidden, n_types, n_ranges, td_target)


def build_joint_dueling(
    *, state_dim: int = 512, hidden: int = 256, n_types: int = 7, n_ranges: int = 4
) -> JointDuelingHead:
    """Dueling head over the 28 joint (type, range) actions."""
    check_widths("head", state_dim=state_dim, hidden=hidden)
    return JointDuelingHead(state_dim, hidden, n_types, n_ranges)


#: The largest |kappa| of the ensemble head: Q-values are O(1), so beyond it the members' spread
#: alone decides, and a far larger one overflows float32.
MAX_KAPPA = 1000.0


def build_ensemble_branching(
    *,
    state_dim: int = 512,
    hidden: int = 256,
    n_types: int = 7,
    n_ranges: int = 4,
    td_target: Literal["mean", "indep"] = "mean",
    members: int = 5,
    kappa: float = 1.0,
) -> EnsembleBranchingHead:
    """``members`` two-channel dueling heads acting on ``mean - kappa * std`` of their Q-values."""
    check_widths("head", state_dim=state_dim, hidden=hidden)
    if isinstance(members, bool) or not isinstance(members, int) or not 2 <= members <= 32:
        raise ConfigError(f"head.members = {members!r}: expected an integer in 2..32")
    if isinstance(kappa, bool) or not isinstance(kappa, int | float) or not abs(kappa) <= MAX_KAPPA:
        raise ConfigError(f"head.kappa = {kappa!r}: expected a number in [-{MAX_KAPPA:g}, {MAX_KAPPA:g}] (0: act "
                          "on the members' mean; past that bound the spread alone decides and the Q-values overflow)")
    return EnsembleBranchingHead(state_dim, hidden, n_types, n_ranges, td_target, members, float(kappa))

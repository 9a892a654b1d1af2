"""Pure functions of the Q heads: dueling aggregation, masked greedy actions, TD targets.

Conventions: ``mask`` is the environment's (N, 7, A) bool action mask (True = the move
stays on the grid without clamping; stop always True). Branch tensors are listed in
the order (type, range). ``K`` below is the number of branches (2 for the branching
head, 1 for the joint head).
"""

from __future__ import annotations

from typing import Literal

import torch

from ..data.grid import STOP  # noqa: F401  (re-exported: heads import it from here)

NEG = -1e9


def dueling(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Q = V + (A - mean A): value (..., 1), advantage (..., n) -> (..., n)."""
    return value + advantage - advantage.mean(dim=-1, keepdim=True)


def masked_argmax(q: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """argmax over the last axis among allowed entries: (..., n), (..., n) bool -> (...,) int64.

    Rows where nothing is allowed fall back to the unmasked argmax."""
    if mask is None:
        return q.argmax(dim=-1)
    blocked = ~mask & mask.any(dim=-1, keepdim=True)
    return q.masked_fill(blocked, NEG).argmax(dim=-1)


def type_mask(mask: torch.Tensor) -> torch.Tensor:
    """(N, 7, A) -> (N, 7): a type is allowed when at least one of its ranges is."""
    return mask.any(dim=-1)


def range_mask(mask: torch.Tensor, a_type: torch.Tensor) -> torch.Tensor:
    """(N, 7, A), (N,) -> (N, A): the ranges allowed for the chosen type (all for stop)."""
    return mask.gather(-2, a_type[..., None, None].expand(*a_type.shape, 1, mask.shape[-1]))[..., 0, :]


def branch_greedy(
    q_type: torch.Tensor, q_range: torch.Tensor, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Greedy (type, range) of the branching head: the best allowed type, then the best
    range allowed for that type. (..., 7), (..., A), (..., 7, A) -> (...,), (...,) int64."""
    if mask is None:
        return q_type.argmax(-1), q_range.argmax(-1)
    a_type = masked_argmax(q_type, type_mask(mask))
    a_range = masked_argmax(q_range, range_mask(mask, a_type))
    return a_type, a_range


def joint_index(a_type: torch.Tensor, a_range: torch.Tensor, n_ranges: int) -> torch.Tensor:
    """Index into the joint head's 7*A outputs (type-major). Stop ignores its range, so it is
    one action: any stop maps to its range-0 entry (the other three are never read)."""
    return a_type * n_ranges + torch.where(a_type == STOP, torch.zeros_like(a_range), a_range)


def joint_greedy(q: torch.Tensor, mask: torch.Tensor | None, n_ranges: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Greedy (type, range) of the joint head: (..., 7*A), (..., 7, A) -> (...,), (...,).

    Stop counts once (its range-0 entry, see :func:`joint_index`): a max over four copies of
    the same action would bias its value upwards."""
    one_stop = torch.ones(q.shape[-1] // n_ranges, n_ranges, dtype=torch.bool, device=q.device)
    one_stop[STOP, 1:] = False
    allowed = one_stop if mask is None else mask & one_stop
    flat = masked_argmax(q, allowed.flatten(-2).expand(q.shape))
    return flat // n_ranges, flat % n_ranges


def branch_bootstrap(
    q_type_target: torch.Tensor,
    q_range_target: torch.Tensor,
    a_type_next: torch.Tensor,
    a_range_next: torch.Tensor,
    mode: Literal["mean", "indep"] = "mean",
) -> torch.Tensor:
    """Next-state values of the branching head, (..., K=2), double-DQN style.

    The target network evaluates the online network's greedy branch actions:
    v_type = Q_type^-(s', a_type*), v_range = Q_range^-(s', a_range*). ``"mean"`` (BDQ,
    the default) shares one value, the mean over branches, for both; ``"indep"`` keeps
    each branch's own. When the greedy next type is stop, the range is irrelevant, so the
    range branch's value is replaced by the type branch's (in both modes).
    """
    v_type = q_type_target.gather(-1, a_type_next[..., None])[..., 0]
    v_range = q_range_target.gather(-1, a_range_next[..., None])[..., 0]
    v_range = torch.where(a_type_next == STOP, v_type, v_range)
    if mode == "mean":
        v = 0.5 * (v_type + v_range)
        return torch.stack([v, v], dim=-1)
    if mode == "indep":
        return torch.stack([v_type, v_range], dim=-1)
    raise ValueError(f"td_target={mode!r}: expected 'mean' or 'indep'")


def td_target(
    reward: torch.Tensor, done: torch.Tensor, next_values: torch.Tensor, gamma: float
) -> torch.Tensor:
    """y = r + gamma * (1 - done) * v(s'): (...,), (...,) bool, (..., K) -> (..., K)."""
    keep = (~done).to(next_values.dtype)[..., None]
    return reward[..., None] + gamma * keep * next_values


def branch_weights(a_type: torch.Tensor) -> torch.Tensor:
    """(..., K=2) loss weights of the branching head: a stop's range is not an action the
    agent took (the environment ignores it), so the range branch gets no loss on stops."""
    w_range = (a_type != STOP).float()
    return torch.stack([torch.ones_like(w_range), w_range], dim=-1)

"""The viewpoint grid and the action model of UEVAVD (docs/environment.md).

The target stands at the origin. The UAV stands on a regular grid of viewpoints:

* x, y in {-50, -40, ..., 50} metres (11 values each),
* z in {60, 70, ..., 100} metres (5 values),

605 viewpoints per context, indexed ``(ix * 11 + iy) * 5 + iz``.

An action is a pair ``(type, range)``: type in ``ACTION_TYPES`` (indices 0..6,
``stop`` = 6) and range index 0..3 meaning 1..4 grid steps of 10 m. A move that would
leave the grid is clamped to its edge. The movement *cost* of Eq. 2 uses the requested
range; the *path length* uses the distance actually flown.

Everything here is pure numpy and precomputed once as lookup tables over
(view, type, range), so that an environment step is an array lookup.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: Grid coordinates in metres along each axis.
XS: tuple[int, ...] = tuple(range(-50, 51, 10))
YS: tuple[int, ...] = tuple(range(-50, 51, 10))
ZS: tuple[int, ...] = tuple(range(60, 101, 10))
NX, NY, NZ = len(XS), len(YS), len(ZS)
#: Viewpoints per context (11 * 11 * 5).
N_VIEWS = NX * NY * NZ
#: Metres between neighbouring viewpoints.
STEP_M = 10.0

#: Action types in index order. forward = +y, backward = -y, left = -x, right = +x,
#: down = -z, up = +z, stop ends the episode (and ignores its range).
ACTION_TYPES: tuple[str, ...] = ("forward", "backward", "left", "right", "down", "up", "stop")
N_TYPES = len(ACTION_TYPES)
STOP = 6
#: Default maximum range A (range indices 0..A-1 mean 1..A grid steps).
DEFAULT_MAX_RANGE = 4

#: The grid's left-right mirror (world x to -x): each action type's mirror image, left and right
#: swapped (:func:`mirror_views` for the viewpoints).
MIRROR_TYPES: tuple[int, ...] = (0, 1, 3, 2, 4, 5, 6)

# Unit displacement in grid steps (dix, diy, diz) of each action type.
_DIRECTIONS = np.array(
    [(0, 1, 0), (0, -1, 0), (-1, 0, 0), (1, 0, 0), (0, 0, -1), (0, 0, 1), (0, 0, 0)],
    dtype=np.int64,
)


def view_index(ix: int, iy: int, iz: int) -> int:
    """Index of the viewpoint at grid indices ``(ix, iy, iz)``.

    Raises ``ValueError`` naming the offending axis when an index is off the grid.
    """
    for name, value, size in (("ix", ix, NX), ("iy", iy, NY), ("iz", iz, NZ)):
        if not 0 <= int(value) < size:
            raise ValueError(f"{name}={value} is off the grid: expected 0..{size - 1}")
    return (int(ix) * NY + int(iy)) * NZ + int(iz)


def grid_indices(view: int | np.ndarray) -> tuple:
    """Grid indices ``(ix, iy, iz)`` of view index(es) (scalar or integer array)."""
    v = np.asarray(view)
    if np.any((v < 0) | (v >= N_VIEWS)):
        bad = v[(v < 0) | (v >= N_VIEWS)].ravel()[0] if v.ndim else int(v)
        raise ValueError(f"view index {bad} is off the grid: expected 0..{N_VIEWS - 1}")
    iz = v % NZ
    iy = (v // NZ) % NY
    ix = v // (NZ * NY)
    if v.ndim == 0:
        return int(ix), int(iy), int(iz)
    return ix, iy, iz


def view_coords(view: int | np.ndarray) -> np.ndarray:
    """UAV position in metres, shape (3,) or (..., 3) float64, (x, y, z), target at origin."""
    ix, iy, iz = grid_indices(view)
    out = np.stack(
        [np.asarray(ix) * STEP_M + XS[0], np.asarray(iy) * STEP_M + YS[0], np.asarray(iz) * STEP_M + ZS[0]],
        axis=-1,
    ).astype(np.float64)
    return out


def mirror_views() -> np.ndarray:
    """(605,) int64: each viewpoint's left-right mirror image (x to -x, y and z kept); applying
    it twice gives every view back."""
    ix, iy, iz = grid_indices(np.arange(N_VIEWS))
    return (((NX - 1 - ix) * NY + iy) * NZ + iz).astype(np.int64)


def coords_to_view(x: float, y: float, z: float) -> int:
    """View index of the grid point at (x, y, z) metres; must lie exactly on the grid."""
    idx = []
    for name, value, axis in (("x", x, XS), ("y", y, YS), ("z", z, ZS)):
        if value not in axis:
            raise ValueError(
                f"{name}={value} m is not a grid coordinate: expected one of {list(axis)}"
            )
        idx.append(axis.index(int(value)))
    return view_index(*idx)


@dataclass(frozen=True)
class Transitions:
    """Lookup tables over (view, type, range index), each of shape (605, 7, A).

    * ``next_view`` int64: the view after the (clamped) move; ``stop`` stays.
    * ``clamped`` bool: the requested move would have left the grid.
    * ``steps`` int64: grid steps actually flown (0 for stop or a move into the edge).
    * ``metres`` float64: metres actually flown (``steps * 10``).
    * ``mask`` bool: True where the move is allowed without clamping; ``stop`` is always
      allowed. ``~mask`` marks exactly the moves that would be clamped.
    """

    next_view: np.ndarray
    clamped: np.ndarray
    steps: np.ndarray
    metres: np.ndarray
    mask: np.ndarray

    @property
    def max_range(self) -> int:
        return int(self.next_view.shape[2])


@lru_cache(maxsize=8)
def transitions(max_range: int = DEFAULT_MAX_RANGE) -> Transitions:
    """Precomputed transition tables for ranges 1..``max_range`` (read-only arrays)."""
    if max_range < 1:
        raise ValueError(f"max_range={max_range}: expected an integer >= 1")
    views = np.arange(N_VIEWS)
    ix, iy, iz = grid_indices(views)
    pos = np.stack([ix, iy, iz], axis=-1)  # (V, 3)
    sizes = np.array([NX, NY, NZ])
    ranges = np.arange(1, max_range + 1)
    # requested target position (V, T, R, 3)
    req = pos[:, None, None, :] + _DIRECTIONS[None, :, None, :] * ranges[None, None, :, None]
    got = np.clip(req, 0, sizes - 1)
    clamped = np.any(req != got, axis=-1)
    steps = np.abs(got - pos[:, None, None, :]).sum(-1)
    next_view = (got[..., 0] * NY + got[..., 1]) * NZ + got[..., 2]
    tables = Transitions(
        next_view=next_view.astype(np.int64),
        clamped=clamped,
        steps=steps.astype(np.int64),
        metres=steps.astype(np.float64) * STEP_M,
        mask=~clamped,
    )
    for arr in (tables.next_view, tables.clamped, tables.steps, tables.metres, tables.mask):
        arr.setflags(write=False)
    return tables


def check_action(a_type: int, a_range: int, max_range: int = DEFAULT_MAX_RANGE) -> None:
    """Raise ``ValueError`` naming the value unless ``(a_type, a_range)`` is a valid action."""
    if not 0 <= int(a_type) < N_TYPES:
        raise ValueError(
            f"action type {a_type} is out of range: expected 0..{N_TYPES - 1} {ACTION_TYPES}"
        )
    if not 0 <= int(a_range) < max_range:
        raise ValueError(
            f"action range index {a_range} is out of range: expected 0..{max_range - 1} "
            f"(1..{max_range} grid steps)"
        )


def move(view: int, a_type: int, a_range: int, max_range: int = DEFAULT_MAX_RANGE) -> tuple[int, int, float, bool]:
    """Apply one action: ``(next_view, steps_flown, metres_flown, clamped)``."""
    check_action(a_type, a_range, max_range)
    t = transitions(max_range)
    grid_indices(view)  # validates
    return (
        int(t.next_view[view, a_type, a_range]),
        int(t.steps[view, a_type, a_range]),
        float(t.metres[view, a_type, a_range]),
        bool(t.clamped[view, a_type, a_range]),
    )


def action_mask(view: int, max_range: int = DEFAULT_MAX_RANGE) -> np.ndarray:
    """(7, A) bool: True where the move stays on the grid without clamping; stop always True."""
    grid_indices(view)
    return transitions(max_range).mask[view].copy()


def flat_action(a_type: int, a_range: int, max_range: int = DEFAULT_MAX_RANGE) -> int:
    """Index of ``(type, range)`` in the joint ``Discrete(7 * A)`` space (type-major)."""
    check_action(a_type, a_range, max_range)
    return int(a_type) * max_range + int(a_range)


def unflat_action(a: int, max_range: int = DEFAULT_MAX_RANGE) -> tuple[int, int]:
    """Inverse of :func:`flat_action`."""
    if not 0 <= int(a) < N_TYPES * max_range:
        raise ValueError(f"joint action {a} is out of range: expected 0..{N_TYPES * max_range - 1}")
    return int(a) // max_range, int(a) % max_range

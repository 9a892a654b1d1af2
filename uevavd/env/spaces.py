"""The env's spaces and its action-mask forms, one definition for the single and the vector env.

Observations: ``features`` (D,) float32 (stored as float16, whose finite range bounds them),
``box`` (4,) in [0, 1], ``action_mask`` (7, A) int8 and ``t`` (decisions so far, 0..T_max); with
``EnvConfig.pose``, ``pose`` (3,) float32, the viewpoint's (x, y, z) in metres, target at the origin.
Actions: MultiDiscrete (type 7, range A), or, in the vector env's ``"flat"`` form, one
Discrete(7 x A) index with the joint mask.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from ..data.grid import N_TYPES, STOP, XS, YS, ZS
from .config import EnvConfig

F16_MAX = float(np.finfo(np.float16).max)


def observation_space(feature_dim: int, config: EnvConfig, *, actions: str = "multi") -> spaces.Dict:
    """One env's observation space (``actions="flat"``: the joint mask flattened, 7 x A)."""
    a = config.max_range
    mask = (spaces.Box(0, 1, (N_TYPES * a,), np.int8) if actions == "flat"
            else spaces.Box(0, 1, (N_TYPES, a), np.int8))
    entries = {
        "features": spaces.Box(-F16_MAX, F16_MAX, (feature_dim,), np.float32),
        "box": spaces.Box(0.0, 1.0, (4,), np.float32),
        "action_mask": mask,
        "t": spaces.Discrete(config.t_max + 1),
    }
    if config.pose:
        entries["pose"] = spaces.Box(np.array([XS[0], YS[0], ZS[0]], np.float32),
                                     np.array([XS[-1], YS[-1], ZS[-1]], np.float32), dtype=np.float32)
    return spaces.Dict(entries)


def action_space(config: EnvConfig, *, actions: str = "multi") -> spaces.Space:
    """One env's action space: MultiDiscrete (type, range), or Discrete(7 x A) for ``"flat"``."""
    a = config.max_range
    return spaces.Discrete(N_TYPES * a) if actions == "flat" else spaces.MultiDiscrete([N_TYPES, a])


def action_masks(mask: np.ndarray, actions: str) -> np.ndarray:
    """(N, 7, A) allowed-action masks -> the form of the action space: ``"flat"`` the joint
    mask (N, 7 x A); ``"multi"`` (N, 7 + A), a type where any of its ranges is allowed (stop
    always), then every range (the joint rule cannot be split per dimension)."""
    mask = np.asarray(mask, dtype=bool)
    if actions == "flat":
        return mask.reshape(mask.shape[0], -1)
    types = mask.any(-1)
    types[:, STOP] = True
    return np.concatenate([types, np.ones((mask.shape[0], mask.shape[-1]), bool)], axis=1)

"""The env's spaces and its action-mask forms, one definition for the single and the vector env.

Observations: ``features`` (D,) float32 (stored as float16, whose finite range bounds them),
``box`` (4,) in [0, 1], ``action_mask`` (7, A) int8 and ``t`` (decisions so far, 0..T_max); with
``EnvConfig.pose``, ``pose`` (3,) float32, the viewpoint's (x, y, z) in metres, target at the origin.
Actions: MultiDiscrete (type 7, range A), or, in the ``actions="flat"`` form, one
Discrete(7 x A) index with the joint mask. With ``observation="flat"`` the observation is one
float32 vector, ``[features, box, (pose,) t, action_mask (7 x A)]`` (:data:`FLAT_PARTS`), the
layout of :func:`uevavd.env.offline.flat_observation` and :class:`~uevavd.env.offline.FlatPolicy`;
``observation="masked"`` gives ``{"observations": that vector, "action_mask": (7 x A,) float32}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from ..data.grid import N_TYPES, STOP, XS, YS, ZS
from .config import EnvConfig

F16_MAX = float(np.finfo(np.float16).max)
#: The parts of the flat observation, in order ("pose" only where the observation has it).
FLAT_PARTS = ("features", "box", "pose", "t", "action_mask")
#: The optional parts of the observation: the EnvConfig field that adds each, and its width in the flat vector.
OPTIONAL_PARTS = {"pose": ("pose", 3)}
#: The observation forms: the Dict of the paper's parts; one flat float32 vector; or that
#: vector as ``"observations"`` beside the joint mask as ``"action_mask"`` (float32), the
#: convention of RLlib's action-masking modules.
OBSERVATION_FORMS = ("dict", "flat", "masked")
#: The action forms: MultiDiscrete (type, range), or one Discrete(7 x A) index.
ACTION_FORMS = ("multi", "flat")


def flatten_observation(obs: dict[str, Any]) -> np.ndarray:
    """``[features, box, (pose,) t, action_mask]`` as float32 from numpy parts, one observation
    or a batch (the mask (..., 7, A) or already joint (..., 7 x A); ``mask`` is taken for
    ``action_mask`` as the batched interface names it)."""
    parts = []
    for key in FLAT_PARTS:
        if key == "pose" and key not in obs:
            continue
        value = np.asarray(obs[key] if key in obs or key != "action_mask" else obs["mask"])
        if key == "t":
            value = value[..., None]
        elif key == "action_mask" and value.ndim >= 2 and value.shape[-2] == N_TYPES:
            value = value.reshape(*value.shape[:-2], -1)
        parts.append(value.astype(np.float32))
    return np.concatenate(parts, axis=-1)


def present_parts(obs: Any) -> tuple[str, ...]:
    """The parts an observation (or a Dict space's ``spaces``) holds, in the flat vector's order
    (the batched interface's ``mask`` counts as ``action_mask``)."""
    return tuple(k for k in FLAT_PARTS if k in obs or (k == "action_mask" and "mask" in obs))


def parts_mismatch(who: str, width: int, have_width: int, have_parts: tuple[str, ...]) -> str | None:
    """Why ``who``, built on flat observations of ``width`` floats, cannot act on an env whose
    flat observations have ``have_width`` floats and the parts ``have_parts``, naming the part
    that differs and the setting that adds it; None where the widths agree."""
    if width == have_width:
        return None
    head = f"{who} takes observations of {width} floats, this env's have {have_width}"
    for part, (_, n) in OPTIONAL_PARTS.items():
        if width - have_width == (n if part not in have_parts else -n):
            return f"{head}: {_part_advice(part, part not in have_parts)}"
    return (f"{head} ({', '.join(have_parts)}): a table of another encoder (features) or an env of another "
            "max_range (the mask); evaluate on the table and env config it was trained on")


def parts_differ(who: str, parts: tuple[str, ...], have_parts: tuple[str, ...]) -> str | None:
    """Why ``who``, built on observations of ``parts``, cannot act on an env whose observations
    have ``have_parts``, naming the setting; None where they agree."""
    for part in OPTIONAL_PARTS:
        if (part in parts) != (part in have_parts):
            return f"{who}: {_part_advice(part, part in parts)}"
    return None


def _part_advice(part: str, built_with: bool) -> str:
    field, n = OPTIONAL_PARTS[part]
    if built_with:
        return (f"it was built with the {part} ({n} floats) and this env has none; evaluate with "
                f"EnvConfig({field}=True) (env.{field} = true)")
    return f"it was built without the {part} ({n} floats) and this env has it; evaluate with EnvConfig({field}=False)"


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


def flat_observation_space(feature_dim: int, config: EnvConfig) -> spaces.Box:
    """The ``observation="flat"`` form's space: float32 ``[features, box, (pose,) t, mask]``,
    each part's bounds as in the Dict form (t in 0..T_max, the joint mask in {0, 1})."""
    return flat_space(observation_space(feature_dim, config, actions="flat"))


def flat_space(space: spaces.Dict) -> spaces.Box:
    """The Box of :func:`flatten_observation` over observations of the Dict ``space`` (the
    env's, or :class:`~uevavd.env.wrappers.DiscreteActions`' with its joint mask): every flat
    route's one layout."""
    parts = space.spaces
    low, high = [], []
    for key in FLAT_PARTS:
        if key not in parts:
            continue
        space = parts[key]
        if isinstance(space, spaces.Discrete):  # t
            low.append(np.zeros(1)), high.append(np.full(1, space.n - 1))
        else:
            low.append(np.asarray(space.low, np.float64).ravel()), high.append(np.asarray(space.high, np.float64).ravel())
    return spaces.Box(np.concatenate(low).astype(np.float32), np.concatenate(high).astype(np.float32), dtype=np.float32)


def form_space(feature_dim: int, config: EnvConfig, *, actions: str, observation: str) -> spaces.Space:
    """One env's observation space in the given forms (:data:`OBSERVATION_FORMS`)."""
    if observation == "dict":
        return observation_space(feature_dim, config, actions=actions)
    flat = flat_observation_space(feature_dim, config)
    if observation == "flat":
        return flat
    return spaces.Dict({"observations": flat,
                        "action_mask": spaces.Box(0.0, 1.0, (N_TYPES * config.max_range,), np.float32)})


def in_form(obs: dict[str, Any], observation: str) -> dict[str, Any] | np.ndarray:
    """An observation (or a batch) of the Dict form in the given form."""
    if observation == "dict":
        return obs
    flat = flatten_observation(obs)
    if observation == "flat":
        return flat
    mask = np.asarray(obs["action_mask"], np.float32)
    return {"observations": flat, "action_mask": mask.reshape(*flat.shape[:-1], -1)}


def check_forms(actions: str, observation: str) -> None:
    """Refuse an unknown action or observation form, naming the accepted ones."""
    if actions not in ACTION_FORMS:
        raise ValueError(f"actions={actions!r}: expected one of {ACTION_FORMS}")
    if observation not in OBSERVATION_FORMS:
        raise ValueError(f"observation={observation!r}: expected one of {OBSERVATION_FORMS}")


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

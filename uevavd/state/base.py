"""State estimators: from observations o_1..o_t to the state s_t the Q head reads.

Every estimator starts with the same :class:`ObservationEncoder` (docs/agents.md):
g_t = [ReLU(Linear(D -> 512)) on the table feature, ReLU(Linear(4 -> 32)) on the box]
(544-d). Estimators then map g_t (single view) or g_1..g_t (recurrent) to s_t.

Shapes: features (B, T, D) float32 table features, boxes (B, T, 4) float32 XYXY
normalised to [0, 1] (all zero = occluded). An estimator that reads the viewpoint's pose
(``pose = True``, the ``state.pose`` setting) takes boxes (B, T, 7): the box, then the pose
(x, y, z) in metres relative to the target, the env's ``pose`` entry (``env.pose``); see
:func:`estimator_boxes`. Sequences start at the episode's first
observation; padding after an episode's end is allowed (causal: position t never reads
positions > t).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import nn

from ..config_rules import ConfigError, check_flag
from ..data.grid import XS, YS, ZS
from ..data.splits import TARGETS

#: The pose's centre and half-span per axis (metres): the encoder reads (pose - centre) / span, in [-1, 1].
POSE_CENTRE = ((XS[0] + XS[-1]) / 2, (YS[0] + YS[-1]) / 2, (ZS[0] + ZS[-1]) / 2)
POSE_SPAN = ((XS[-1] - XS[0]) / 2, (YS[-1] - YS[0]) / 2, (ZS[-1] - ZS[0]) / 2)
#: Columns of an estimator's boxes input: the box (4), then the pose (3) where it reads one.
BOX_COLUMNS, POSE_COLUMNS = 4, 3
#: The recognizer's class probabilities a table built with ``perception.recognizer_in_state`` ends its features with.
RECOGNIZER_COLUMNS = len(TARGETS)


def reads_pose(estimator: Any) -> bool:
    """Whether a state estimator declares that it reads the pose (its optional ``pose``
    attribute, False where absent: the paper's estimators read the image and the box only)."""
    return bool(getattr(estimator, "pose", False))


def reads_image(estimator: Any) -> bool:
    """Whether a state estimator reads the table's image features: True unless its
    :class:`ObservationEncoder` is built without them (``state.image = false``); a plugin's
    estimator without that encoder counts as reading them."""
    return bool(getattr(getattr(estimator, "encoder", None), "reads_image", True))


def reads_recognizer(estimator: Any) -> bool:
    """Whether a state estimator reads the recognizer's class probabilities (sorted) at the end of
    the table's features without the image's (``state.image = false``, ``state.recognizer = true``)."""
    return bool(getattr(getattr(estimator, "encoder", None), "recognizer_columns", 0))


def check_recognizer(image: Any, recognizer: Any) -> bool:
    """``state.recognizer`` checked for a built-in estimator: a TOML boolean, and true only beside
    ``state.image = false`` (the image's features already end with the recognizer's probabilities)."""
    if check_flag("state", "recognizer", recognizer) and image is not False:
        raise ConfigError("state.recognizer = true: expected it beside state.image = false (with the image's "
                          "features the state reads the recognizer's probabilities after them already)")
    return recognizer


def estimator_boxes(estimator: Any, box: torch.Tensor, pose: torch.Tensor | None) -> torch.Tensor:
    """What ``estimator`` reads as its ``boxes``: ``box`` (..., 4) itself, or, for an estimator
    that reads the pose, ``[box, pose]`` (..., 7) with ``pose`` (..., 3) metres (the
    observation's ``pose``). Raises ValueError where it needs a pose and the observation has none."""
    if not reads_pose(estimator):
        return box
    if pose is None:
        raise ValueError("the state estimator reads the viewpoint's pose (state.pose = true), but the observation "
                         "has none: set env.pose = true")
    return torch.cat([box, pose.to(box.dtype)], dim=-1)


class ObservationEncoder(nn.Module):
    """g_t = [ReLU(W_img f + b), ReLU(W_box b + c)]: (..., D), (..., 4) -> (..., image_dim + box_dim).

    With ``pose_dim`` > 0 the boxes carry the pose too, (..., 7) = [box, pose metres], and g_t
    gains its own embedding, ReLU(W_pose p + e) of the pose scaled to [-1, 1] per axis
    (:data:`POSE_CENTRE`, :data:`POSE_SPAN`): (..., image_dim + box_dim + pose_dim).

    With ``image`` False the encoder reads no image: its image part is that of an all-zero
    feature vector, ReLU(b), whatever the view (g_t keeps its width and its weights' names).
    With ``recognizer`` as well it reads the features' last :data:`RECOGNIZER_COLUMNS` columns
    only, the recognizer's class probabilities of a table built with
    ``perception.recognizer_in_state``, sorted from the largest: ReLU(W p + b) of how sure the
    recognizer is, whichever class it names. The reward reads the true class's probability
    against a threshold, the same for every class, so the state does not learn which class a
    view shows, which would not carry over to a target it never trained on."""

    def __init__(self, feature_dim: int, image_dim: int = 512, box_dim: int = 32, pose_dim: int = 0,
                 image: bool = True, recognizer: bool = False) -> None:
        super().__init__()
        if feature_dim < 1 or image_dim < 1 or box_dim < 1 or pose_dim < 0:
            raise ValueError(
                f"ObservationEncoder sizes must be >= 1: feature_dim={feature_dim}, "
                f"image_dim={image_dim}, box_dim={box_dim} (pose_dim={pose_dim} >= 0)"
            )
        self.feature_dim, self.image_dim, self.box_dim, self.pose_dim = feature_dim, image_dim, box_dim, pose_dim
        if image and recognizer:
            raise ValueError("an encoder that reads the image's features reads the recognizer's probabilities "
                             "after them already: set image = false to read the recognizer's alone")
        if recognizer and feature_dim <= RECOGNIZER_COLUMNS:
            raise ValueError(f"feature_dim={feature_dim}: a table with the recognizer's {RECOGNIZER_COLUMNS} class "
                             "probabilities after the image's features has more columns")
        self.reads_image = bool(image)
        self.recognizer_columns = RECOGNIZER_COLUMNS if recognizer else 0
        self.image = nn.Linear(feature_dim, image_dim)
        self.box = nn.Linear(BOX_COLUMNS, box_dim)
        if pose_dim:  # not in the paper's estimators' state dicts: their files load as before
            self.pose = nn.Linear(POSE_COLUMNS, pose_dim)
            self.register_buffer("pose_centre", torch.tensor(POSE_CENTRE), persistent=False)
            self.register_buffer("pose_span", torch.tensor(POSE_SPAN), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.image_dim + self.box_dim + self.pose_dim

    @property
    def box_columns(self) -> int:
        """Columns of the boxes input: 4, or 7 with the pose."""
        return BOX_COLUMNS + (POSE_COLUMNS if self.pose_dim else 0)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """g_t = :meth:`combine` (:meth:`project` (features), boxes)."""
        return self.combine(self.project(features), boxes)

    def project(self, features: torch.Tensor) -> torch.Tensor:
        """ReLU(W_img f + b): (..., D) -> (..., image_dim); a pure function of the view, so
        evaluation can compute it once per (scene, view) and gather it per step."""
        if features.shape[-1] != self.feature_dim:
            raise ValueError(
                f"features have {features.shape[-1]} channels but the encoder was built for "
                f"{self.feature_dim}; build the state estimator with feature_dim={features.shape[-1]}"
            )
        if self.recognizer_columns:  # sorted: which class is likeliest is not the state's to read
            k = self.recognizer_columns
            ranked = features[..., -k:].sort(dim=-1, descending=True).values
            return torch.relu(F.linear(ranked, self.image.weight[:, -k:], self.image.bias))
        if not self.reads_image:
            return torch.relu(self.image.bias).expand(*features.shape[:-1], self.image_dim)
        return torch.relu(self.image(features))

    def combine(self, image: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """[projected image, ReLU(W_box b + c)(, ReLU(W_pose p + e))] -> g_t (..., out_dim)."""
        if boxes.shape[-1] != self.box_columns:
            raise ValueError(f"boxes have {boxes.shape[-1]} columns but the encoder reads {self.box_columns} "
                             + ("(the box, then the pose: set env.pose = true)" if self.pose_dim else "(the box)"))
        if not self.pose_dim:
            return torch.cat([image, torch.relu(self.box(boxes))], dim=-1)
        pose = (boxes[..., BOX_COLUMNS:] - self.pose_centre) / self.pose_span
        return torch.cat([image, torch.relu(self.box(boxes[..., :BOX_COLUMNS])), torch.relu(self.pose(pose))], dim=-1)


@runtime_checkable
class StateEstimator(Protocol):
    """What a ``state`` plugin builds (an ``nn.Module``)."""

    feature_dim: int  #: D, the table feature size it reads
    state_dim: int  #: size of s_t
    recurrent: bool  #: True when s_t depends on earlier observations
    # Optional: ``pose: bool`` - True when it reads the viewpoint's pose; its ``boxes`` are then
    # (..., 7), the box and the pose in metres (:func:`estimator_boxes`). The built-ins take it as
    # the ``state.pose`` setting; a plugin's builder that accepts ``pose`` gets it the same way.

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """(B, T, D), (B, T, 4) float32 -> (B, T, state_dim) float32: s_t for every t."""
        ...

    def initial_hidden(self, n: int, device: torch.device | str = "cpu") -> torch.Tensor:
        """(n, H) float32 memory at an episode start (H = 0 when not recurrent)."""
        ...

    def step(
        self, features: torch.Tensor, boxes: torch.Tensor, hidden: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One decision: (N, D), (N, 4), (N, H) -> s_t (N, state_dim), new hidden (N, H)."""
        ...

    # Optional (the built-ins have it): ``step_encoded(g, hidden)`` - like ``step`` from an
    # already encoded g_t (N, input_dim), and an ``encoder`` (:class:`ObservationEncoder`).
    # Evaluation then projects each (scene, view) once instead of once per visit. A recurrent
    # estimator may further offer :class:`InputGateCache`.


@runtime_checkable
class InputGateCache(Protocol):
    """Optional capability of a recurrent estimator (the built-in GRU has it): its input
    gates depend on g_t alone, so an evaluator can compute them once per (scene, view, box),
    gather them per step and step the cell from them, with the actions of ``step``."""

    gate_width: int  #: columns of the input gates (3 H for a GRU)

    def caches_input_gates(self) -> bool:
        """True when :meth:`step_from_gates` gives ``step_encoded``'s results bit for bit."""
        ...

    def input_gates(self, g: torch.Tensor) -> torch.Tensor:
        """(N, input_dim) g_t -> (N, gate_width) input gates."""
        ...

    def step_from_gates(self, gates: torch.Tensor, hidden: torch.Tensor, *, from_zero: bool,
                        buffer: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """One decision from ``gates`` (N, gate_width; may be overwritten): s_t (N, state_dim)
        and h_t (N, H). ``from_zero``: every row starts its episode (h = 0); ``buffer(name,
        rows, width)`` returns a reusable float32 work tensor."""
        ...

"""MAP's state estimator: an MLP on the current observation only."""

from __future__ import annotations

import torch
from torch import nn

from ..config_rules import check_flag, check_widths
from .base import ObservationEncoder, check_recognizer


class SingleViewState(nn.Module):
    """s_t = ReLU(Linear(g_t)): (B, T, D), (B, T, 4) -> (B, T, state_dim); no memory."""

    recurrent = False

    def __init__(self, feature_dim: int, input_dim: int, box_dim: int, state_dim: int, pose_dim: int = 0,
                 image: bool = True, recognizer: bool = False) -> None:
        super().__init__()
        if input_dim <= box_dim:
            raise ValueError(f"input_dim={input_dim} must exceed box_dim={box_dim} (g_t = image + box)")
        self.feature_dim, self.state_dim, self.pose = feature_dim, state_dim, pose_dim > 0
        self.encoder = ObservationEncoder(feature_dim, input_dim - box_dim, box_dim, pose_dim, image, recognizer)
        self.mlp = nn.Linear(input_dim + pose_dim, state_dim)

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.mlp(self.encoder(features, boxes)))

    def initial_hidden(self, n: int, device: torch.device | str = "cpu") -> torch.Tensor:
        return torch.zeros(n, 0, device=device)

    def step(
        self, features: torch.Tensor, boxes: torch.Tensor, hidden: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.step_encoded(self.encoder(features, boxes), hidden)

    def step_encoded(self, g: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.relu(self.mlp(g)), hidden


def build_single_view(
    *, feature_dim: int = 2048, input_dim: int = 544, box_dim: int = 32, state_dim: int = 512, pose: bool = False,
    pose_dim: int = 32, image: bool = True,
    recognizer: bool = False,
) -> SingleViewState:
    """MAP's estimator. ``feature_dim`` (D of the table) is passed by the trainer at build
    time; g_t has ``input_dim`` = (input_dim - box_dim) image + ``box_dim`` box channels, and
    with ``pose`` (``state.pose``; needs ``env.pose``) ``pose_dim`` more for the viewpoint's pose;
    with ``image`` false (``state.image``) it reads no image features, and with ``recognizer`` as well
    (``state.recognizer``) the recognizer's class probabilities alone (:class:`ObservationEncoder`)."""
    check_widths("state", input_dim=input_dim, box_dim=box_dim, state_dim=state_dim,
                 **({"pose_dim": pose_dim} if check_flag("state", "pose", pose) else {}))
    return SingleViewState(feature_dim, input_dim, box_dim, state_dim, pose_dim if pose else 0,
                           check_flag("state", "image", image), check_recognizer(image, recognizer))

"""The task's left-right mirror as an augmentation of the updates (``train.mirror``).

World x to -x maps the task's distribution onto itself (docs/generalisation.md, "Past the rule:
the mirror"): the grid is symmetric in x, the camera's pixel centres are symmetric about the
image centre, the street layouts are mirrored at random in x, the sun's azimuth is uniform and
each vehicle model is symmetric across its length. Of one episode it maps the boxes' columns,
the pose's x, the views and the moves left and right; the recognizer's answers are kept, since
no recognizer here is trained to be mirror-invariant.
"""

from __future__ import annotations

from typing import Any

import torch

from ..data.grid import MIRROR_TYPES, mirror_views
from ..env.gate import box_visible


class MirrorAugment:
    """Augmentation by the task's left-right mirror (``train.mirror``): each replayed episode of
    an update, with probability ``p`` from its own generator (saved with the run), is seen as
    its mirror image: its boxes' columns reversed (x1, x2 to 1 - x2, 1 - x1; a hidden box stays
    empty), its views mirrored where the pose, the grid's edges and the pose rule are read, and
    its moves left and right swapped; its rewards, and the answers of where a flight pays (read
    at the views it saw), are kept. Only for estimators that read no image features."""

    def __init__(self, p: float, *, seed: int, device: torch.device | str) -> None:
        self.p = float(p)
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(seed)
        self.views = torch.as_tensor(mirror_views(), device=device)
        self.types = torch.tensor(MIRROR_TYPES, dtype=torch.int64, device=device)

    def draw(self, n: int) -> torch.Tensor:
        """(n,) bool: which of n episodes are seen mirrored."""
        return torch.rand(n, generator=self.generator, device=self.generator.device) < self.p

    def apply(self, flip: torch.Tensor, views: torch.Tensor, a_type: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """``flip`` (B,), views (B, L), action types (B, T) -> the views and types as the
        mirrored episodes see them."""
        return (torch.where(flip[:, None], self.views[views], views),
                torch.where(flip[:, None], self.types[a_type], a_type))

    @staticmethod
    def boxes(boxes: torch.Tensor, flip: torch.Tensor) -> torch.Tensor:
        """(N, 4) normalised XYXY boxes, (N,) bool -> the boxes, mirrored where ``flip``."""
        mirrored = torch.stack([1.0 - boxes[:, 2], boxes[:, 1], 1.0 - boxes[:, 0], boxes[:, 3]], dim=1)
        flip = flip & box_visible(boxes)
        return torch.where(flip[:, None], mirrored, boxes)

    def state_dict(self) -> dict[str, Any]:
        return {"rng": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["rng"])

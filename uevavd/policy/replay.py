"""Prioritised replay of whole episodes, stored as table indices (no feature copies).

An episode is at most T_max decisions over T_max + 1 observations. It is stored as the
scene index and the views it saw; features, boxes and masks are looked up from the
observation table when a batch is sampled, so the buffer holds a few ints per step and
a GRU can be unrolled from the episode's start. All storage is preallocated torch
tensors; sampling is proportional to priority**alpha (torch.multinomial with a seeded
generator, whose state is checkpointed with the buffer).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import SAMPLINGS


@dataclass
class EpisodeBatch:
    """B sampled episodes. views (B, T+1) int64; a_type, a_range (B, T) int64; reward (B, T)
    float32; valid (B, T) bool (decision t happened); done (B, T) bool (decision t ended
    it); scene (B,) int64; index (B,) int64 buffer slots; weight (B,) float32 IS weights."""

    scene: torch.Tensor
    views: torch.Tensor
    a_type: torch.Tensor
    a_range: torch.Tensor
    reward: torch.Tensor
    valid: torch.Tensor
    done: torch.Tensor
    index: torch.Tensor
    weight: torch.Tensor



class EpisodeReplay:
    """Ring buffer of ``capacity`` episodes of at most ``t_max`` decisions."""

    def __init__(self, capacity: int, t_max: int, *, alpha: float = 0.6, eps: float = 1e-3, seed: int = 0,
                 sampling: str = "portable", device: torch.device | str = "cpu") -> None:
        """``sampling`` (``TrainConfig.replay_sampling``): "portable" raises each priority to
        alpha once, when it is written, with Python's scalar ``math.pow`` (float64);
        multinomial takes those weights as they are (its CPU kernel sums them in order) and
        the importance weights (N P(i))^-beta / max_j (N P(j))^-beta = (w_i / min_j w_j)^-beta
        of the batch need no total, so the draws are the same bits under torch's AVX-512 and
        AVX2 kernels. "vectorised" (every run before world version 5) raises and sums the
        whole buffer with torch's vectorised kernels at each draw, whose last bits depend on
        the CPU's vector width."""
        if capacity < 1 or t_max < 1:
            raise ValueError(f"EpisodeReplay: capacity={capacity} and t_max={t_max} must be >= 1")
        if sampling not in SAMPLINGS:
            raise ValueError(f"EpisodeReplay: sampling={sampling!r}, expected one of {SAMPLINGS}")
        self.capacity, self.t_max, self.alpha, self.eps = capacity, t_max, alpha, eps
        self.portable = sampling == "portable"
        self.device = torch.device(device)
        z = dict(device=self.device)
        self.scene = torch.zeros(capacity, dtype=torch.int64, **z)
        self.views = torch.zeros(capacity, t_max + 1, dtype=torch.int64, **z)
        self.a_type = torch.zeros(capacity, t_max, dtype=torch.int64, **z)
        self.a_range = torch.zeros(capacity, t_max, dtype=torch.int64, **z)
        self.reward = torch.zeros(capacity, t_max, dtype=torch.float32, **z)
        self.length = torch.zeros(capacity, dtype=torch.int64, **z)
        self.priority = torch.zeros(capacity, dtype=torch.float32, **z)
        self.priority_alpha = torch.zeros(capacity, dtype=torch.float64, **z)  # priority**alpha (portable sampling)
        self.ptr = 0
        self.size = 0
        self.max_priority = 1.0
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, scene: torch.Tensor, views: torch.Tensor, a_type: torch.Tensor, a_range: torch.Tensor,
            reward: torch.Tensor, length: torch.Tensor) -> None:
        """Store n finished episodes: scene (n,), views (n, T+1), a_type/a_range/reward (n, T),
        length (n,) decisions taken (1..T). New episodes get the highest priority seen."""
        n = int(scene.shape[0])
        if n == 0:
            return
        if n > self.capacity:
            raise ValueError(f"adding {n} episodes to a buffer of capacity {self.capacity}")
        idx = (self.ptr + torch.arange(n, device=self.device)) % self.capacity
        self.scene[idx] = scene.to(self.device)
        self.views[idx] = views.to(self.device)
        self.a_type[idx] = a_type.to(self.device)
        self.a_range[idx] = a_range.to(self.device)
        self.reward[idx] = reward.to(self.device, torch.float32)
        self.length[idx] = length.to(self.device)
        self.priority[idx] = self.max_priority
        if self.portable:
            self._raise_to_alpha(idx)
        self.ptr = (self.ptr + n) % self.capacity
        self.size = min(self.capacity, self.size + n)

    def sample(self, batch_size: int, beta: float) -> EpisodeBatch:
        if self.size == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        if self.portable:
            idx = torch.multinomial(self.priority_alpha[: self.size], batch_size, replacement=True, generator=self.generator)
            picked = self.priority_alpha[idx].tolist()
            low = min(picked)
            w = torch.tensor([math.pow(v / low, -beta) for v in picked], dtype=torch.float64, device=self.device)
        else:
            p = self.priority[: self.size] ** self.alpha
            probs = p / p.sum()
            idx = torch.multinomial(probs, batch_size, replacement=True, generator=self.generator)
            w = (self.size * probs[idx]) ** (-beta)
            w = w / w.max()
        steps = torch.arange(self.t_max, device=self.device)
        length = self.length[idx]
        return EpisodeBatch(
            scene=self.scene[idx], views=self.views[idx], a_type=self.a_type[idx], a_range=self.a_range[idx],
            reward=self.reward[idx], valid=steps[None] < length[:, None], done=steps[None] == (length[:, None] - 1),
            index=idx, weight=w.float(),
        )

    def update_priorities(self, index: torch.Tensor, td_abs: torch.Tensor) -> None:
        """Per-episode priority = mean |TD error| over its steps + eps; (B,), (B,)."""
        pr = td_abs.detach().to(self.device, torch.float32) + self.eps
        self.priority[index] = pr
        self.max_priority = max(self.max_priority, float(pr.max()))
        if self.portable:  # from the stored priorities: an index sampled twice keeps one value
            self._raise_to_alpha(index)

    def _raise_to_alpha(self, index: torch.Tensor) -> None:
        """priority_alpha[index] = priority[index] ** alpha, element by element in Python's float64."""
        self.priority_alpha[index] = torch.tensor([math.pow(v, self.alpha) for v in self.priority[index].tolist()],
                                          dtype=torch.float64, device=self.device)

    # -- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "scene": self.scene.cpu(), "views": self.views.cpu(), "a_type": self.a_type.cpu(),
            "a_range": self.a_range.cpu(), "reward": self.reward.cpu(), "length": self.length.cpu(),
            "priority": self.priority.cpu(), "ptr": self.ptr, "size": self.size,
            "max_priority": self.max_priority, "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        for name in ("scene", "views", "a_type", "a_range", "reward", "length", "priority"):
            mine = getattr(self, name)
            if state[name].shape != mine.shape:
                raise ValueError(f"replay {name}: checkpoint shape {tuple(state[name].shape)} != {tuple(mine.shape)}")
            mine.copy_(state[name])
        self.ptr, self.size, self.max_priority = int(state["ptr"]), int(state["size"]), float(state["max_priority"])
        if self.portable:  # derived from the priorities: not checkpointed
            self._raise_to_alpha(torch.arange(self.size, device=self.device))
        self.generator.set_state(state["generator"])

"""Prioritized Level Replay over the training contexts (Jiang et al. 2021), for DQN.

Each new training episode's context is drawn from ``P = (1 - rho) * P_S + rho * P_C``:

* ``P_S``, the score term: contexts ranked by their score, the learning potential, weighted
  ``h = (1 / rank) ** (1 / temperature)`` and normalised. A context's score is the mean |TD
  error| of its episodes in the learner's batches (what prioritised replay already computes),
  averaged over time (each batch moves it :data:`SCORE_EMA` of the way). A context not yet
  scored ranks first (the paper plays unseen levels before replaying seen ones).
* ``P_C``, the staleness term: proportional to the episodes started since the context was last
  started, so a context whose score has gone stale is played again.

``rho`` is ``train.plr_staleness``, ``temperature`` ``train.plr_temperature``. The paper
scores a level by its latest episode's GAE magnitude (an actor-critic's); with a replay buffer
the TD errors of its replayed episodes are the DQN counterpart (as prioritised replay uses
them). The state (scores, starts) is part of a run's checkpoint, so a resumed run samples the
contexts an uninterrupted one would.
"""

from __future__ import annotations

from typing import Any

import torch

#: How far one learner batch moves a context's score towards its episodes' mean |TD error|.
SCORE_EMA = 0.1


class LevelReplay:
    """Context weights for :class:`~uevavd.env.batched.BatchedAODEnv` (``scene_weights``),
    over its ``n`` scenes (local indices)."""

    def __init__(self, n: int, *, temperature: float, staleness: float, device: torch.device | str = "cpu") -> None:
        self.temperature, self.staleness = float(temperature), float(staleness)
        self.scores = torch.zeros(n, dtype=torch.float64, device=device)
        self.scored = torch.zeros(n, dtype=torch.bool, device=device)
        self.last_start = torch.zeros(n, dtype=torch.int64, device=device)
        self.starts = 0

    def started(self, local: torch.Tensor) -> None:
        """Episodes started on these (k,) local scenes."""
        if local.numel():
            self.starts += int(local.numel())
            self.last_start[local] = self.starts

    def score(self, local: torch.Tensor, td: torch.Tensor) -> None:
        """A learner batch: its (B,) episodes' local scenes and mean |TD errors|."""
        n = self.scores.numel()
        total = torch.zeros(n, dtype=torch.float64, device=self.scores.device).index_add_(0, local, td.double())
        count = torch.zeros(n, dtype=torch.float64, device=self.scores.device).index_add_(
            0, local, torch.ones_like(td, dtype=torch.float64))
        hit = count > 0
        mean = total[hit] / count[hit]
        old = self.scores[hit]
        self.scores[hit] = torch.where(self.scored[hit], old + SCORE_EMA * (mean - old), mean)
        self.scored |= hit

    def weights(self) -> torch.Tensor:
        """(n,) float64 sampling probabilities of the scenes."""
        n = self.scores.numel()
        effective = torch.where(self.scored, self.scores, torch.full_like(self.scores, float("inf")))
        order = torch.argsort(effective, descending=True, stable=True)
        rank = torch.empty(n, dtype=torch.float64, device=self.scores.device)
        rank[order] = torch.arange(1, n + 1, dtype=torch.float64, device=self.scores.device)
        h = rank.reciprocal() ** (1.0 / self.temperature)
        p_score = h / h.sum()
        stale = (self.starts - self.last_start).double()
        p_stale = stale / stale.sum() if bool(stale.sum() > 0) else torch.full_like(stale, 1.0 / n)
        return (1.0 - self.staleness) * p_score + self.staleness * p_stale

    def state_dict(self) -> dict[str, Any]:
        return {"scores": self.scores.cpu(), "scored": self.scored.cpu(), "last_start": self.last_start.cpu(),
                "starts": self.starts}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for key in ("scores", "scored", "last_start"):
            getattr(self, key).copy_(state[key])
        self.starts = int(state["starts"])


def level_replay(cfg: Any, env: Any) -> LevelReplay | None:
    """The run's context sampler over ``env``'s scenes: None for ``train.context_sampling =
    "uniform"``."""
    if cfg.context_sampling != "level_replay":
        return None
    return LevelReplay(len(env.tensors.scenes), temperature=cfg.plr_temperature, staleness=cfg.plr_staleness,
                       device=env.device)

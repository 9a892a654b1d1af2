"""Acting during training: the seeds a run derives, and the collector that owns acting.

:class:`EpisodeCollector` steps the batched env epsilon-greedily from the network, keeps the
running episodes (views, actions, rewards, the estimator's memory) and hands each finished one
to the caller whole, as Tianshou's ``Collector`` and CleanRL's rollout loop do. Its
``state_dict`` is what a checkpoint needs to resume acting exactly where it stopped.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from ..env.batched import BatchedAODEnv
from ..state.base import estimator_boxes
from .acting import epsilon_greedy
from .level_replay import LevelReplay


@dataclasses.dataclass(frozen=True)
class RunSeeds:
    """Every random stream of a run, derived from its one seed in one place."""

    network: int  #: torch's global stream, when the network initialises
    replay: int  #: the replay buffer's sampling
    env: int  #: the env's start contexts and views
    acting: int  #: epsilon-greedy exploration
    feature_dropout: int  #: the features' augmentation (train.feature_dropout)
    rule_bootstrap: int  #: the rule gate's resamples of the training contexts (train.rule_ensemble)
    mirror: int  #: which replayed episodes are seen mirrored (train.mirror)

    @classmethod
    def of(cls, seed: int) -> RunSeeds:
        return cls(network=seed, replay=seed + 1, env=seed + 2, acting=seed + 3, feature_dropout=seed + 4,
                   rule_bootstrap=seed + 5, mirror=seed + 6)


@dataclasses.dataclass
class Finished:
    """Episodes that ended in one batched step, whole: ``scene`` (k,), ``views`` (k, T_max + 1),
    ``types`` / ``ranges`` / ``rewards`` (k, T_max), ``lengths`` (k,) decisions, ``returns``
    (k,) discounted returns."""

    scene: torch.Tensor
    views: torch.Tensor
    types: torch.Tensor
    ranges: torch.Tensor
    rewards: torch.Tensor
    lengths: torch.Tensor
    returns: torch.Tensor


class EpisodeCollector:
    """``n`` envs acting from ``net`` with epsilon-greedy exploration (its own generator),
    the memory restarting at every episode's first decision."""

    #: the running episodes' tensors a checkpoint holds (beside the env's state and the generator's)
    EPISODE_KEYS = ("ep_views", "ep_type", "ep_range", "ep_reward", "hidden")

    def __init__(self, env: BatchedAODEnv, net: Any, *, seed: int, device: torch.device,
                 contexts: LevelReplay | None = None, pays: Any = None) -> None:
        n, tmax = env.n_envs, env.config.t_max
        self.pays = pays  # where a flight pays (PaysLabels; train.stop_gate "pays" or "rule"), else None
        self.env, self.net, self.n = env, net, n
        self.contexts = contexts  # the new episodes' context sampler (None: uniform)
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(seed)
        self.rows = torch.arange(n, device=device)
        # running episodes: views o_0..o_T, actions and rewards so far
        self.ep_views = torch.zeros(n, tmax + 1, dtype=torch.int64, device=device)
        self.ep_type = torch.zeros(n, tmax, dtype=torch.int64, device=device)
        self.ep_range = torch.zeros(n, tmax, dtype=torch.int64, device=device)
        self.ep_reward = torch.zeros(n, tmax, dtype=torch.float32, device=device)
        self.hidden = net.initial_hidden(n, device)
        self.obs: dict[str, torch.Tensor] | None = None

    def reset(self) -> None:
        if self.contexts is not None:
            self.env.scene_weights = self.contexts.weights()
        self.obs = self.env.reset()
        if self.contexts is not None:
            self.contexts.started(self.env.tensors.local[self.obs["scene"]])

    def score(self, scene: torch.Tensor, td: torch.Tensor) -> None:
        """A learner batch's episodes (table scene indices) and their mean |TD errors|, for the
        context sampler."""
        if self.contexts is not None:
            self.contexts.score(self.env.tensors.local[scene], td)

    def step(self, epsilon: float) -> Finished | None:
        """One decision in every env; the episodes it ended, or None."""
        assert self.obs is not None, "reset() or load_state_dict() first"
        obs, ar = self.obs, self.rows
        t = obs["t"]
        with torch.no_grad():
            self.hidden = self.hidden * (t != 0)[:, None].to(self.hidden.dtype)
            boxes = estimator_boxes(self.net.estimator, obs["box"], obs.get("pose"))
            q, self.hidden = self.net.step(obs["features"], boxes, self.hidden)
            pays = self.pays.at(obs["scene"], obs["view"], t) if self.pays is not None else None
            mask = self.net.allowed(obs["mask"], obs["box"], training=True, pays=pays,  # train.stop_gate
                                    view=obs["view"], t=t)
            a_type, a_range = self.net.head.greedy(q, mask)
            a_type, a_range = epsilon_greedy(a_type, a_range, mask, epsilon, self.generator)
        self.ep_views[ar, t] = obs["view"]
        self.ep_type[ar, t] = a_type
        self.ep_range[ar, t] = a_range
        scene = obs["scene"]
        if self.contexts is not None:
            self.env.scene_weights = self.contexts.weights()
        self.obs, reward, done, info = self.env.step(a_type, a_range)
        self.ep_reward[ar, t] = reward
        if not bool(done.any()):
            return None
        if self.contexts is not None:
            self.contexts.started(self.env.tensors.local[self.obs["scene"][done]])
        # finished episodes whole (at most T_max decisions, T_max + 1 views)
        idx = done.nonzero()[:, 0]
        self.ep_views[idx, t[idx] + 1] = info["final_view"][idx]
        out = Finished(scene[idx], self.ep_views[idx], self.ep_type[idx], self.ep_range[idx], self.ep_reward[idx],
                       t[idx] + 1, info["final_return"][idx])
        self.ep_reward[idx] = 0.0
        return out

    def state_dict(self) -> dict[str, Any]:
        extra = {} if self.contexts is None else {"level_replay": self.contexts.state_dict()}
        return {"env": self.env.state_dict(), "act_rng": self.generator.get_state(),
                **{k: getattr(self, k).cpu() for k in self.EPISODE_KEYS}, **extra}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.env.load_state_dict(state["env"])
        if self.contexts is not None:
            self.contexts.load_state_dict(state["level_replay"])
        self.generator.set_state(state["act_rng"])
        for key in self.EPISODE_KEYS:
            getattr(self, key).copy_(state[key])
        self.obs = self.env.observe()

"""Training settings of the DQN agents (the ``[train]`` section of a method config)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

from ..config_rules import ConfigError

#: ``TrainConfig.gamma``'s default; at this value it follows ``env.gamma``.
DEFAULT_GAMMA = 0.9
#: Upper bounds of the sizes a run allocates, and of a seed (numpy's and torch's generators
#: take any, but a run derives several from it and records it in JSON).
MAX_BUFFER_EPISODES = 10_000_000
MAX_N_ENVS = 65_536
MAX_SEED = 2**32 - 1
#: Gradient updates per batched env step: far above any schedule that learns (the presets use 4).
MAX_UPDATES_PER_STEP = 1024

#: What a run recorded before a training setting existed trained with (see
#: :func:`uevavd.policy.rundir.with_legacy_settings`).
LEGACY_TRAIN = {"replay_sampling": "vectorised", "context_sampling": "uniform", "plr_temperature": 0.1,
                "plr_staleness": 0.1, "feature_dropout": 0.0, "aux_recognition": 0.0,
                "stop_gate": "none", "stop_threshold": 0.5, "imitation": "none", "imitation_fraction": 1.0,
                "rule_ensemble": 0, "rule_margin": 0.0, "mirror": 0.0}
#: What a run may imitate (``train.imitation``).
IMITATIONS = ("none", "visibility_oracle")
#: How training picks each new episode's context (``train.context_sampling``).
CONTEXT_SAMPLINGS = ("uniform", "level_replay")
#: ``train.stop_gate``: where the policy may only stop. "none"; "box", wherever the observed
#: target box is non-empty, in training (acting and TD targets) and in acting; "learned",
#: wherever a stop probe on s_t predicts that the recognizer recognises the current view with
#: probability above ``train.stop_threshold``, in greedy acting only; "pays", the box gate
#: opened where a flight pays: in training where the oracle's best reachable return from the
#: view beats stopping there, in greedy acting where a probe on s_t, trained on that answer
#: over the box-visible views, predicts it with probability above ``train.stop_threshold``;
#: "rule", the pose rule (``pose_seek``) wherever the box is hidden, and where it is visible the
#: "pays" gate with the rule's advantage as its answer: a flight now, the rule after, beats stopping.
STOP_GATES = ("none", "box", "learned", "pays", "rule")
#: How a buffer can draw its batches (``TrainConfig.replay_sampling``; see
#: :class:`uevavd.policy.replay.EpisodeReplay`).
SAMPLINGS = ("portable", "vectorised")


@dataclass(frozen=True)
class TrainConfig:
    """Double DQN with prioritised replay of whole episodes. Paper values where published
    (Adam, lr 1e-4, 300,000 episodes); the rest chosen to learn well and fast on CPU."""

    episodes: int = 300_000
    """Training episodes in total (the paper's 300,000)."""
    lr: float = 1e-4
    """Adam learning rate (paper: 1e-4)."""
    batch_size: int = 64
    """Episodes per gradient update; each is unrolled over its (T_max) decisions."""
    buffer_episodes: int = 50_000
    """Replay capacity in whole episodes (oldest overwritten first)."""
    n_envs: int = 64
    """Episodes run in parallel by the batched environment."""
    learning_starts: int = 2_000
    """Episodes collected with the exploration policy before the first update."""
    updates_per_step: float = 1.0
    """Gradient updates per batched environment step (fractions accumulate)."""
    target_update: int = 100
    """Gradient updates between copies of the online network into the target network."""
    eps_start: float = 1.0
    """Initial epsilon of the epsilon-greedy exploration."""
    eps_end: float = 0.05
    """Final epsilon, reached after ``eps_fraction`` of the training episodes."""
    eps_fraction: float = 0.3
    """Fraction of the training episodes over which epsilon decays linearly."""
    per_alpha: float = 0.6
    """Prioritised replay exponent (0 = uniform sampling)."""
    per_beta: float = 0.4
    """Initial importance-sampling exponent, annealed linearly to 1 over training."""
    per_eps: float = 1e-3
    """Added to every episode's priority (mean |TD error| of its steps) so none starves."""
    gamma: float = 0.9
    """Deprecated: the TD target's discount is ``env.gamma``, the one of the reported return
    and the oracle. Left at 0.9 (the default, which the shipped method files still carry)
    it follows ``env.gamma``; any other value must equal ``env.gamma`` or the run is
    refused (see :func:`resolve_gamma`)."""
    grad_clip: float = 10.0
    """Clip the global gradient norm to this (0 disables)."""
    epoch_episodes: int = 25_000
    """Training episodes per epoch; the policy is evaluated after every epoch."""
    eval_splits: tuple[str, ...] = ("train", "hard")
    """Splits (or aliases) evaluated after every epoch."""
    eval_contexts: int = 10
    """Contexts per split in the per-epoch evaluations, evenly spaced (0 = all; each is
    evaluated from all 605 start views). ``uevavd evaluate`` always uses all."""
    checkpoint_every: int = 1
    """Epochs between checkpoints (the last epoch, and the last of a call stopped by
    ``max_epochs``, always write one)."""
    device: str = "auto"
    """"auto" (CUDA when available), "cpu" or "cuda[:i]"."""
    seed: int = 0
    """Seeds network init, exploration, replay sampling and the environment."""
    threads: int = 1
    """torch CPU threads for the run, the caller's count restored after it. An update's float
    sums round by how they are split between threads, so the weights depend on the count: a
    fixed one gives the same run on every machine (``uevavd train`` and ``uevavd ablate``
    train the same weights). 0 takes the caller's count (torch's default is the cores;
    ``ablate`` gives such runs ``cores // workers``): faster at the paper's sizes on an idle
    CPU, other weights on another machine. Recorded in the run, checked on resume."""
    loss: Literal["huber", "mse"] = "huber"
    """TD loss (Huber is the usual choice for DQN)."""
    replay_sampling: Literal["portable", "vectorised"] = "portable"
    """How prioritised replay draws its batches. "portable": each priority**alpha is computed
    once, when written, by Python's scalar float64 pow, and sampled as it is, so a run samples
    the same episodes, and trains the same weights, on every x86 CPU. "vectorised": torch's
    vectorised pow and sum over the whole buffer at each draw (every run before world version
    5), whose last bits depend on the CPU's vector width (AVX-512 or AVX2), so a CPU without
    AVX-512 trains other weights. Recorded in the run and checked on resume; a run recorded
    without it trained "vectorised" (docs/agents.md, "What a run's weights depend on")."""
    context_sampling: Literal["uniform", "level_replay"] = "uniform"
    """How training picks each new episode's context: "uniform" (the paper's), or
    "level_replay", Prioritized Level Replay over the training contexts (Jiang et al. 2021;
    :mod:`uevavd.policy.level_replay`): by each context's learning potential, the mean |TD
    error| of its replayed episodes, mixed with how long ago it was last played."""
    plr_temperature: float = 0.1
    """Level replay: the rank prioritisation's temperature (lower: the top contexts dominate)."""
    plr_staleness: float = 0.1
    """Level replay: the share of the staleness term (contexts not played for long) in the mix."""
    feature_dropout: float = 0.0
    """Augmentation of the table's features in the updates: each feature of each replayed view
    zeroed with this probability (the rest scaled up), from the run's own stream; 0 = none."""
    aux_recognition: float = 0.0
    """An auxiliary objective: the weight of a linear probe's loss predicting, from the state,
    whether the recognizer recognises the current view (0 = none)."""
    stop_gate: Literal["none", "box", "learned", "pays", "rule"] = "none"
    """Where the agent may only stop (:data:`STOP_GATES`): "none"; "box",
    wherever the observed target box is non-empty, in training (its actions and its TD targets)
    and in acting, so its values are learned on the decisions where the target is hidden;
    "learned", wherever a stop probe on the state, trained beside the Q network on whether the
    recognizer recognises the current view (its own loss and optimizer; the Q network's updates
    are those of the method without it), predicts recognition above ``stop_threshold``, in
    greedy acting only; "pays", the box gate opened where a flight pays: in training (its
    actions and TD targets) where the oracle's best return reachable from the view, with the
    decisions left, beats stopping there; in greedy acting where a probe on the state, trained
    on that answer over the views whose box is visible (its own loss and optimizer), predicts
    it above ``stop_threshold``; "rule", anchored to the pose rule: wherever the box is hidden
    the action is ``pose_seek``'s (its number of moves chosen on the training contexts), in
    acting and in the TD targets, and where it is visible the "pays" gate with the rule's exact
    advantage as its answer (:func:`uevavd.env.rule_values.rule_values`): whether a flight now,
    the rule followed after, beats stopping. Not with ``imitation``."""
    stop_threshold: float = 0.5
    """The learned, "pays" and "rule" gates' threshold on their probe's probability."""
    rule_ensemble: int = 0
    """The rule gate's probe (``stop_gate = "rule"``): 0, one probe of whether a departure pays
    (read against ``stop_threshold``); K >= 2, K linear regressors of the best move's advantage
    over the rule, each fit on its own bootstrap resample of the training contexts (not of
    seeds), the gate opening in acting only where the smallest of the K exceeds ``rule_margin``."""
    rule_margin: float = 0.0
    """The rule ensemble's margin: the advantage over the rule (in return units) that the
    ensemble's lowest prediction must exceed for a departure."""
    mirror: float = 0.0
    """Augmentation by the task's left-right mirror: each replayed episode of an update seen, with
    this probability, as its mirror image (world x to -x: the boxes' columns reversed, the pose's
    x negated, the moves left and right swapped, the rule's and the grid's edges mirrored), its
    rewards kept; 0 = none. The world's distribution is symmetric under it; the recognizer is not
    trained to be, so a mirrored episode is one of a mirrored world with the same recognitions.
    Only for estimators that read no image features (``state.image = false``)."""
    imitation: Literal["none", "visibility_oracle"] = "none"
    """"visibility_oracle": DAgger (Ross et al. 2011) with the visibility oracle as the expert. The
    student acts (epsilon-greedy, as in every run), and every decision it takes is labelled with
    the oracle's action for the steps left (its plan from that view with T_max set to them,
    :func:`uevavd.env.visibility_oracle.visibility_plans`); the updates minimise the
    cross-entropy of the head's type and range branches with those labels instead of the TD
    loss, over the replayed episodes (the aggregated dataset); with ``stop_gate = "box"``, over the
    decisions where the gate leaves the choice to the student (the box hidden). Needs a table
    with visible fractions and a head with a type and a range branch."""
    imitation_fraction: float = 1.0
    """The share of the training episodes that imitate (``imitation``); the updates after it
    are the usual double-DQN ones, from the imitated weights."""

    def __post_init__(self) -> None:
        """Ranges, not only types: a value that would crash training later (a zero
        divisor) or silently learn nothing is refused here, before a run directory exists."""
        def need(ok: bool, key: str, what: str) -> None:
            if not ok:
                raise ConfigError(f"train.{key} = {getattr(self, key)!r}: expected {what}")

        for key in ("episodes", "batch_size", "buffer_episodes", "n_envs", "target_update", "epoch_episodes",
                    "checkpoint_every"):
            need(isinstance(getattr(self, key), int) and getattr(self, key) >= 1, key, "an integer >= 1")
        for key in ("learning_starts", "eval_contexts", "threads", "seed"):
            need(isinstance(getattr(self, key), int) and getattr(self, key) >= 0, key, "an integer >= 0")
        # sizes that allocate: past these a typo fails as an allocation traceback (or the kernel's kill)
        need(self.buffer_episodes <= MAX_BUFFER_EPISODES, "buffer_episodes",
             f"at most {MAX_BUFFER_EPISODES:,} episodes (the replay buffer is allocated whole)")
        need(self.n_envs <= MAX_N_ENVS, "n_envs", f"at most {MAX_N_ENVS:,} environments stepped side by side")
        need(self.seed <= MAX_SEED, "seed", f"an integer in 0..{MAX_SEED} (2**32 - 1)")
        need(isinstance(self.lr, int | float) and 0 < self.lr <= 1, "lr",
             "a learning rate in (0, 1] (Adam's; a larger or infinite one diverges mid-run)")
        for f in dataclasses.fields(self):  # inf or NaN in any number would hang or crash a run mid-way
            v = getattr(self, f.name)
            need(not isinstance(v, float) or math.isfinite(v), f.name, "a finite number")
        need(0 < self.updates_per_step <= MAX_UPDATES_PER_STEP, "updates_per_step",
             f"a number in (0, {MAX_UPDATES_PER_STEP}] (gradient updates per batched step)")
        for key in ("eps_start", "eps_end", "per_beta"):
            need(0.0 <= getattr(self, key) <= 1.0, key, "a number in [0, 1]")
        need(0.0 < self.eps_fraction <= 1.0, "eps_fraction", "a share of training in (0, 1]")
        # priorities are float32 and raised to alpha: past these they overflow mid-run, after the files exist
        need(0 <= self.per_alpha <= 10, "per_alpha", "a prioritisation exponent in [0, 10] (the paper's PER uses 0.6)")
        need(0 < self.per_eps <= 1, "per_eps", "a small priority floor in (0, 1]")
        need(self.replay_sampling in SAMPLINGS, "replay_sampling", f"one of {SAMPLINGS}")
        need(self.context_sampling in CONTEXT_SAMPLINGS, "context_sampling", f"one of {CONTEXT_SAMPLINGS}")
        need(isinstance(self.plr_temperature, int | float) and 0.0 < self.plr_temperature <= 100.0,
             "plr_temperature", "a temperature in (0, 100]")
        need(isinstance(self.plr_staleness, int | float) and 0.0 <= self.plr_staleness <= 1.0, "plr_staleness",
             "a share in [0, 1]")
        need(isinstance(self.feature_dropout, int | float) and 0.0 <= self.feature_dropout < 1.0, "feature_dropout",
             "a probability in [0, 1)")
        need(isinstance(self.aux_recognition, int | float) and 0.0 <= self.aux_recognition <= 100.0, "aux_recognition",
             "a loss weight in [0, 100]")
        need(self.stop_gate in STOP_GATES, "stop_gate", f"one of {STOP_GATES}")
        need(self.imitation in IMITATIONS, "imitation", f"one of {IMITATIONS}")
        need(isinstance(self.imitation_fraction, int | float) and 0.0 < self.imitation_fraction <= 1.0,
             "imitation_fraction", "a share of training in (0, 1]")
        need(isinstance(self.stop_threshold, int | float) and 0.0 <= self.stop_threshold <= 1.0, "stop_threshold",
             "a probability in [0, 1]")
        # a setting nothing reads under the options chosen is a mistake, not a no-op: refuse it
        need(self.stop_threshold == 0.5 or self.stop_gate in ("learned", "pays", "rule"), "stop_threshold",
             f"its default 0.5: only the learned, pays and rule stop gates read it, and train.stop_gate is {self.stop_gate!r} "
             "(set train.stop_gate, or leave train.stop_threshold out)")
        need(isinstance(self.rule_ensemble, int) and not isinstance(self.rule_ensemble, bool)
             and (self.rule_ensemble == 0 or 2 <= self.rule_ensemble <= 64), "rule_ensemble",
             "0 (one probe) or an ensemble size in [2, 64]")
        need(isinstance(self.rule_margin, int | float) and -1.0 <= self.rule_margin <= 1.0, "rule_margin",
             "an advantage in [-1, 1]")
        need(self.rule_ensemble == 0 or self.stop_gate == "rule", "rule_ensemble",
             f"its default 0: only the rule stop gate reads it, and train.stop_gate is {self.stop_gate!r} "
             "(set train.stop_gate = 'rule', or leave train.rule_ensemble out)")
        need(self.rule_margin == 0.0 or self.rule_ensemble, "rule_margin",
             "its default 0.0: only the rule gate's ensemble reads it (set train.rule_ensemble, or leave "
             "train.rule_margin out)")
        need(self.stop_threshold == 0.5 or not self.rule_ensemble, "stop_threshold",
             "its default 0.5: the rule gate's ensemble reads train.rule_margin instead")
        need(self.stop_gate != "rule" or self.imitation == "none", "stop_gate",
             "not 'rule' with train.imitation: the rule gate trains by the TD loss (leave train.imitation out, "
             "or use stop_gate 'box' or 'pays')")
        need(isinstance(self.mirror, int | float) and 0.0 <= self.mirror <= 1.0, "mirror", "a probability in [0, 1]")
        need(self.mirror == 0.0 or self.imitation == "none", "mirror",
             "0 with train.imitation: the expert's labels are not mirrored (leave one of them out)")
        need(self.imitation_fraction == 1.0 or self.imitation != "none", "imitation_fraction",
             "its default 1.0: it is the share of training that imitates, and train.imitation is 'none' (set "
             "train.imitation, or leave train.imitation_fraction out)")
        need(0.0 < self.gamma <= 1.0, "gamma", "a discount in (0, 1]")
        need(self.grad_clip >= 0, "grad_clip", "a number >= 0 (0 disables clipping)")
        need(self.learning_starts < self.episodes, "learning_starts",
             f"fewer episodes than train.episodes = {self.episodes}, or no gradient update would ever run "
             "(lower train.learning_starts or train more episodes)")
        need(self.buffer_episodes >= self.batch_size, "buffer_episodes",
             f"at least train.batch_size = {self.batch_size} episodes")

    def resolve_gamma(self, env_gamma: float) -> TrainConfig:
        """This config with ``gamma`` set to the one discount of the run (``env.gamma``).

        ``train.gamma`` is a deprecated alias: at its default (0.9) it follows ``env.gamma``
        (so ``--set env.gamma=0.99`` changes the TD target too), equal to ``env.gamma`` it is
        accepted, and any other value raises :class:`uevavd.config.ConfigError` naming both
        (a TD discount other than the return's would optimise another objective than the
        one reported)."""
        if self.gamma == env_gamma:
            return self
        if self.gamma == DEFAULT_GAMMA:
            return self.replace(gamma=float(env_gamma))
        raise ConfigError(
            f"train.gamma = {self.gamma} and env.gamma = {env_gamma} differ, but a run has one discount "
            "(the TD target's, the reported return's and the oracle's): set only env.gamma "
            "(train.gamma is deprecated; left at 0.9 it follows env.gamma)"
        )

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with ``changes`` (checked as the constructor checks them)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """The settings as a plain dict (what a run's ``settings.json`` records)."""
        d = dataclasses.asdict(self)
        d["eval_splits"] = list(self.eval_splits)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """The settings of :meth:`to_dict`'s dict; an unknown key is refused by name."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown train settings {unknown}; accepted: {sorted(names)}")
        data = dict(data)
        if "eval_splits" in data:
            data["eval_splits"] = tuple(data["eval_splits"])
        return cls(**data)

    def epsilon(self, episodes_done: int, total: int | None = None) -> float:
        """Linear decay from ``eps_start`` to ``eps_end`` over ``eps_fraction`` of training."""
        total = total or self.episodes
        span = max(1.0, self.eps_fraction * total)
        frac = min(1.0, episodes_done / span)
        return self.eps_start + frac * (self.eps_end - self.eps_start)

    def imitating(self, episodes_done: int) -> bool:
        """Whether the updates after ``episodes_done`` training episodes imitate (``imitation``)."""
        return self.imitation != "none" and episodes_done < self.imitation_fraction * self.episodes

    def beta(self, episodes_done: int, total: int | None = None) -> float:
        """The importance-sampling exponent after ``episodes_done`` of ``total`` episodes:
        ``per_beta`` annealed linearly to 1."""
        total = total or self.episodes
        return min(1.0, self.per_beta + (1.0 - self.per_beta) * episodes_done / max(1, total))

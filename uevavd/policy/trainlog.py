"""A training run's counters and clock (:class:`Loop`, which its checkpoint holds) and what it
shows of them (:class:`TrainLog`: TensorBoard scalars and the progress bar)."""

from __future__ import annotations

import dataclasses
import json
import time
from collections import deque
from typing import Any

import numpy as np

from .learner import Learner
from .rundir import RunDir


@dataclasses.dataclass
class Loop:
    """The training loop's counters and clock, which a checkpoint holds."""

    episodes: int = 0  #: finished training episodes
    env_steps: int = 0  #: batched env steps times n_envs
    epoch: int = 0  #: epochs ended (each evaluated)
    credit: float = 0.0  #: gradient updates owed (updates_per_step accrues, each update spends 1)
    wall: float = 0.0  #: training wall time in seconds, evaluations and checkpoints excluded



class TrainLog:
    """The run's TensorBoard scalars and progress bar; ``t0`` is where training time counts from."""

    def __init__(self, run: Any, progress: bool) -> None:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm.auto import tqdm

        self.run, self.progress = run, progress
        self.writer = SummaryWriter(str(RunDir(run.out).tensorboard))
        if not run.loop.episodes:  # the run's settings, once, as TensorBoard's text and hparams
            _log_settings(self.writer, run.settings)
        self.bar = tqdm(total=run.cfg.episodes, initial=min(run.loop.episodes, run.cfg.episodes), unit="ep",
                        desc=f"train {run.spec.name}", disable=not progress, dynamic_ncols=True)
        self.recent: deque[float] = deque(maxlen=1000)
        self.t0 = time.perf_counter() - run.loop.wall
        self.loss = float("nan")
        self.eps = float("nan")

    def episodes_done(self, returns: list[float]) -> None:
        loop = self.run.loop
        self.recent.extend(returns)
        self.bar.update(len(returns))
        if self.progress and (loop.env_steps // self.run.cfg.n_envs) % 50 == 0:
            self.bar.set_postfix(ret=f"{np.mean(self.recent):.3f}", eps=f"{self.run.cfg.epsilon(loop.episodes):.2f}",
                                 loss=f"{self.loss:.4f}", refresh=False)

    def update(self, eps: float) -> None:
        _log_update(self.writer, self.run.learner, self.loss, eps,
                    self.run.loop.episodes / max(time.perf_counter() - self.t0, 1e-9))

    def epoch(self, loop: Loop) -> float:
        ret = float(np.mean(self.recent)) if self.recent else float("nan")
        for key, value in (("recent_return", ret), ("epsilon", self.eps), ("loss", self.loss),
                           ("episodes_per_s", loop.episodes / max(loop.wall, 1e-9))):
            self.writer.add_scalar(f"train/{key}", value, loop.episodes)
        return ret

    def evaluation(self, split: str, summary: dict[str, Any], episodes: int) -> None:
        for key, value in summary.items():
            if isinstance(value, int | float):
                self.writer.add_scalar(f"eval_{split}/{key}", value, episodes)

    def close(self) -> None:
        self.bar.close()
        self.writer.close()


def _log_update(writer: Any, learner: Learner, loss: float, eps: float, episodes_per_s: float) -> None:
    """The update's diagnostics at step = gradient updates (every TB_EVERY_UPDATES)."""
    step = learner.updates
    writer.add_scalar("update/loss", loss, step)
    for key, value in learner.stats.items():
        writer.add_scalar(f"update/{key}", value, step)
    writer.add_scalar("update/epsilon", eps, step)
    writer.add_scalar("update/episodes_per_s", episodes_per_s, step)


def _log_settings(writer: Any, settings: dict[str, Any]) -> None:
    flat = {f"train.{k}": v for k, v in settings["train"].items()}
    flat.update({f"env.{k}": v for k, v in settings["env"].items()})
    flat.update({k: settings[k] for k in ("method", "seed", "state", "head", "table_key", "threads")})
    hparams = {k: v if isinstance(v, int | float | str | bool) else str(v) for k, v in flat.items()}
    writer.add_text("settings", "```\n" + json.dumps(settings, indent=1, default=str) + "\n```", 0)
    from torch.utils.tensorboard.summary import hparams as hparams_summaries

    for summary in hparams_summaries(hparams, {"eval_train/mean_return": float("nan")}):
        writer._get_file_writer().add_summary(summary)  # in this run's event file (add_hparams opens another)

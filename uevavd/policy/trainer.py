"""Training loop of MAP / Memo-MAP / IBE-MAP: double DQN over whole replayed episodes.

Reads top to bottom like CleanRL's ``dqn.py``: settings, seeding, setup (or resume),
one loop that acts in N parallel environments, stores finished episodes, learns, and
after every epoch evaluates, logs and checkpoints. Run directory::

    method.toml     the resolved method spec          settings.json  every setting
    checkpoint.pt   atomic, exact-resume state        evals.jsonl    one row per epoch x split
    tb/             TensorBoard scalars               done.json      written when finished
    policy.safetensors  the network alone, with its method and settings (written when finished)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import remove_temporaries
from ..config import MethodSpec, PerceptionSection
from ..config_rules import ConfigError, dotted_get
from ..data.grid import N_TYPES
from ..env.baselines import pose_seek_moves
from ..env.batched import BatchedAODEnv, EnvTensors
from ..env.config import EnvConfig
from ..env.evaluate import evaluate_policy
from ..runtime import resolve_device, torch_threads
from ..state.base import RECOGNIZER_COLUMNS, reads_image, reads_recognizer
from ..table import load_table
from ..version import __version__
from .acting import GreedyPolicy
from .checkpoint import (
    CheckpointError,
    checkpoint_meta,
    load_checkpoint,
    save_checkpoint,
    save_policy_file,
)
from .collector import EpisodeCollector, RunSeeds
from .config import TrainConfig
from .contract import build_checked_network
from .imitation import OracleLabels, check_branches
from .learner import FeatureDropout, FeatureLookup, FlightPays, Learner, RecognitionProbe
from .level_replay import level_replay
from .mirror import MirrorAugment
from .replay import EpisodeReplay
from .rule_gate import RulePays
from .rundir import (
    RunDir,
    RunDirError,
    check_run_dir,
    evals_digest,
    run_lock,
    write_done,
    write_evals,
    write_settings,
)
from .trainlog import Loop, TrainLog

#: Gradient updates between TensorBoard points of the update's diagnostics (``update/*``).
TB_EVERY_UPDATES = 100


def _versions() -> dict[str, str]:
    return {"uevavd": __version__, "torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version()}


class PerceptionMismatch(RunDirError):
    """A table built for another perception config than the method trained on it."""


#: The perception keys a table's recorded config must share with the method trained on it.
TABLE_PERCEPTION_KEYS = ("segmenter.name", "decompose", "gray_seed", "encoder.name", "encoder.weights", "classifier.name",
                         "recognizer_in_state")


def check_table_perception(perception: PerceptionSection, table: Any, method: str) -> None:
    """Refuse a table built for another perception config than ``method``'s (its
    ``meta.json`` records the method's ``[perception]``): raw features for IBE-MAP, or a
    ResNet18 table for a ResNet50 method, would train and record a run that is not what its
    ``method.toml`` says. Tables made with ``from_arrays`` (no recorded perception) pass."""
    recorded = (table.meta.get("config") or {}).get("perception")
    if not isinstance(recorded, dict):
        return
    absent = {"recognizer_in_state": False}  # a table records it only when true
    recorded, want = {**absent, **recorded}, {**absent, **perception.as_dict()}
    diffs = [f"perception.{k}: table {dotted_get(recorded, k)!r}, method {dotted_get(want, k)!r}"
             for k in TABLE_PERCEPTION_KEYS if dotted_get(recorded, k) != dotted_get(want, k)]
    if diffs:
        raise PerceptionMismatch(f"table {table.path or table.key} was built for another perception config than "
                                 f"method {method!r} ({'; '.join(diffs)}): build its table with `uevavd prepare DATA "
                                 f"--method {method}` (with the same --preset and --set) and pass that one")


class _Evaluator:
    """Per-epoch evaluation on each split, its device tensors built once."""

    def __init__(self, table: Any, cfg: TrainConfig, env_cfg: EnvConfig, device: torch.device,
                 net: Any) -> None:
        self.device = device
        self.features = torch.from_numpy(np.array(table.features)).to(device)
        # the greedy policy reads the table's features itself when the estimator offers the
        # encoded fast path; an estimator without it (a plugin's) needs them in every obs
        needs = GreedyPolicy(net, device=device, features=self.features).needs_features
        net.train()
        self.tensors = {}
        for split in cfg.eval_splits:
            ctx = table.contexts[table.select(split, train_per_block=env_cfg.train_per_block,
                                              holdout_block=env_cfg.holdout_block)]
            if cfg.eval_contexts and cfg.eval_contexts < len(ctx):
                ctx = ctx[np.linspace(0, len(ctx) - 1, cfg.eval_contexts).round().astype(int)]
            self.tensors[split] = EnvTensors(table, split, env_cfg, device=device, contexts=ctx,
                                             with_features=needs)

    def __call__(self, net: Any) -> dict[str, dict[str, Any]]:
        out = {split: evaluate_policy(tb, split, GreedyPolicy(net, device=self.device, features=self.features)).summary()
               for split, tb in self.tensors.items()}
        net.train()
        return out


def train(
    spec: MethodSpec,
    table: Any,
    *,
    out: Path,
    episodes: int | None = None,
    seed: int = 0,
    device: str = "auto",
    progress: bool = True,
    overrides: dict | None = None,
    max_epochs: int | None = None,
) -> Path:
    """Train ``spec`` on an observation table (or its folder) into run directory ``out``.

    Resumes an unfinished run of the same spec, table and settings; refuses a directory
    holding another configuration (naming what differs), or one another process is
    training into (:func:`~uevavd.policy.rundir.run_lock`); returns at once for a finished
    run. ``max_epochs`` stops this call after that many epochs (a later call resumes).
    """
    if max_epochs is not None and (isinstance(max_epochs, bool) or not isinstance(max_epochs, int) or max_epochs < 1):
        raise ConfigError(f"max_epochs = {max_epochs!r}: expected an integer >= 1 (epochs this call trains), "
                          "or None for the whole run")
    # train.threads and the seeded torch RNG for the run only: the caller's after it
    with run_lock(out), torch_threads(None), contextlib.ExitStack() as caller_state:
        return _train(spec, table, out=Path(out), episodes=episodes, seed=seed, device=device, progress=progress,
                      overrides=overrides, max_epochs=max_epochs, caller_state=caller_state)


#: Checkpoint keys of earlier versions of the learner's optional parts.
LEGACY_PARTS = {"feature_dropout": "augment", "aux_recognition": "aux"}


@dataclasses.dataclass
class _Run:
    """One training run's parts, built (and every input checked) before anything is written."""

    out: Path
    spec: MethodSpec
    cfg: TrainConfig
    settings: dict[str, Any]
    net: Any
    learner: Learner
    replay: EpisodeReplay
    collector: EpisodeCollector
    lookup: FeatureLookup
    evaluator: _Evaluator
    loop: Loop = dataclasses.field(default_factory=Loop)
    evals: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    def parts(self) -> dict[str, Any]:
        """What a checkpoint holds beside the collector's state and the counters, by key."""
        return {"net": self.net, "target": self.learner.target, "optimizer": self.learner.optimizer,
                "replay": self.replay, **self.learner.parts()}

    def save(self) -> None:
        save_checkpoint(RunDir(self.out).checkpoint, {
            "meta": checkpoint_meta(self.settings), **{k: v.state_dict() for k, v in self.parts().items()},
            "updates": self.learner.updates, **self.collector.state_dict(), "loop": dataclasses.asdict(self.loop),
            "evals": json.dumps(self.evals)})

    def resume(self) -> bool:
        """Load the run's checkpoint, if it has one (its settings checked against this run's)."""
        path = RunDir(self.out).checkpoint
        if not path.is_file():
            return False
        ck = load_checkpoint(path, expect=self.settings)
        for key, part in self.parts().items():
            part.load_state_dict(ck[key] if key in ck else ck[LEGACY_PARTS[key]])
        self.learner.updates = int(ck["updates"])
        self.collector.load_state_dict(ck)
        for key, value in ck["loop"].items():  # in place: the loop reads this object
            setattr(self.loop, key, value)
        self.evals = json.loads(ck["evals"])
        return True


def _train(spec: MethodSpec, table: Any, *, out: Path, episodes: int | None, seed: int, device: str,
           progress: bool, overrides: dict | None, max_epochs: int | None, caller_state: contextlib.ExitStack) -> Path:
    run = _setup(spec.with_overrides(overrides), load_table(table), Path(out), episodes=episodes, seed=seed,
                 device=device, caller_state=caller_state)
    if run is None:  # finished already
        return Path(out)
    cfg, loop = run.cfg, run.loop
    if not run.resume():
        run.collector.reset()
    log = TrainLog(run, progress)
    epochs_this_call = 0
    try:  # the writer's thread and the bar end with the loop, also when a checkpoint fails
        while loop.episodes < cfg.episodes:
            # act: epsilon-greedy over allowed actions; store finished episodes whole
            log.eps = cfg.epsilon(loop.episodes)
            finished = run.collector.step(log.eps)
            loop.env_steps += cfg.n_envs
            if finished is not None:
                run.replay.add(finished.scene, finished.views, finished.types, finished.ranges, finished.rewards,
                               finished.lengths)
                loop.episodes += int(finished.lengths.numel())
                log.episodes_done(finished.returns.tolist())
            # learn: updates_per_step gradient updates per batched step, on average
            if len(run.replay) >= cfg.learning_starts:
                loop.credit += cfg.updates_per_step
                while loop.credit >= 1.0:
                    loop.credit -= 1.0
                    _update(run, log)
            # epoch end: evaluate, log, checkpoint
            if loop.episodes >= (loop.epoch + 1) * cfg.epoch_episodes or loop.episodes >= cfg.episodes:
                epochs_this_call += 1
                # stopping this call (max_epochs) always checkpoints, whatever checkpoint_every says
                stop = max_epochs is not None and epochs_this_call >= max_epochs and loop.episodes < cfg.episodes
                _end_epoch(run, log, stop)
                if stop:
                    break
    finally:
        log.close()
    if loop.episodes >= cfg.episodes:
        # the shareable policy (the network alone), then the mark that the run is finished
        save_policy_file(RunDir(run.out).policy, run.net.state_dict(),
                         RunDir(run.out).method.read_text(encoding="utf-8"), run.settings)
        write_done(run.out, run.settings, {
            "episodes": loop.episodes, "env_steps": loop.env_steps, "updates": run.learner.updates,
            "wall_s": loop.wall, "final_eval": run.evals[-len(cfg.eval_splits):] if cfg.eval_splits else [],
            "evals_rows": len(run.evals), "evals_digest": evals_digest(run.evals)})
    return run.out


def _setup(spec: MethodSpec, table: Any, out: Path, *, episodes: int | None, seed: int, device: str,
           caller_state: contextlib.ExitStack) -> _Run | None:
    """Every setting checked, the run's parts built, then (only then) its settings and method
    written; None for a finished run."""
    check_table_perception(spec.perception, table, spec.name)
    cfg = spec.train_config(seed=seed, **({"episodes": episodes} if episodes is not None else {}))
    env_cfg = spec.env
    cfg = cfg.resolve_gamma(env_cfg.gamma)  # one discount: env.gamma (train.gamma is deprecated)
    dev = resolve_device(device if device != "auto" else cfg.device)
    settings = {
        "method": spec.name, "spec_hash": spec.hash, "table_key": table.key,
        "table_path": str(table.path) if table.path else None, "feature_dim": table.feature_dim,
        "table_identity": table.perception_identity,
        "seed": seed, "train": cfg.to_dict(), "env": env_cfg.to_dict(), "n_types": N_TYPES,
        "n_ranges": env_cfg.max_range, "t_max": env_cfg.t_max, "state": spec.state.name, "head": spec.head.name,
        "device": str(dev), "versions": _versions(),
    }
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    settings["threads"] = torch.get_num_threads()  # results depend on it: recorded, checked on resume
    check_run_dir(out, settings)
    if RunDir(out).finished:
        return None
    # a killed save's temp files (a checkpoint's is full size; the policy's ends .tmp.safetensors)
    remove_temporaries(out)
    # the network initialises from torch's global RNG (on the CPU, then moved); seeded here,
    # the caller's streams (the CPU's, the run's GPU's) restored after the run
    seeds = RunSeeds.of(cfg.seed)
    caller_state.enter_context(torch.random.fork_rng(devices=[dev] if dev.type == "cuda" else []))
    torch.random.default_generator.manual_seed(seeds.network)
    if dev.type == "cuda":
        with torch.cuda.device(dev):
            torch.cuda.manual_seed(seeds.network)
    # each component checked against its kind's rules (one line naming the broken one) before
    # anything of the run is written; a table without the train or an eval split is refused here too
    net = build_checked_network(spec.state, spec.head, table.feature_dim, n_ranges=env_cfg.max_range)
    net = net.set_stop_gate(cfg.stop_gate, cfg.stop_threshold, ensemble=cfg.rule_ensemble,
                            margin=cfg.rule_margin).to(dev)
    feature_dropout = (FeatureDropout(cfg.feature_dropout, seed=seeds.feature_dropout, device=dev)
                       if cfg.feature_dropout else None)
    aux_recognition = (RecognitionProbe(net.estimator.state_dim, cfg.aux_recognition).to(dev)
                       if cfg.aux_recognition else None)
    recognizer = reads_recognizer(net.estimator)  # the table's last columns: the recognizer's probabilities
    if recognizer and not spec.perception.recognizer_in_state:
        raise ConfigError("state.recognizer = true: expected perception.recognizer_in_state = true (the table's "
                          "features then end with the recognizer's class probabilities the state reads)")
    if recognizer and len(table.class_names) != RECOGNIZER_COLUMNS:
        raise ConfigError(f"state.recognizer = true: expected a table of {RECOGNIZER_COLUMNS} classes, the state's "
                          f"recognizer columns; table {table.path or table.key} has {len(table.class_names)}")
    if cfg.mirror and (recognizer or reads_image(net.estimator)):
        raise ConfigError(f"train.mirror = {cfg.mirror}: expected 0 for a state that reads the table's features (they "
                          "are not mirrored): set state.image = false and leave state.recognizer out, or leave "
                          "train.mirror out")
    mirror = MirrorAugment(cfg.mirror, seed=seeds.mirror, device=dev) if cfg.mirror else None
    replay = EpisodeReplay(cfg.buffer_episodes, env_cfg.t_max, alpha=cfg.per_alpha, eps=cfg.per_eps,
                           seed=seeds.replay, sampling=cfg.replay_sampling, device=dev)
    env = BatchedAODEnv(table, "train", cfg.n_envs, env_cfg, device=dev, seed=seeds.env, features_dtype=torch.float16)
    imitation = None
    if cfg.imitation != "none":  # DAgger: the expert's labels, and a head whose branches they fit
        with torch.no_grad():
            check_branches(net.head(torch.zeros(1, net.estimator.state_dim, device=dev)), env_cfg.max_range)
        imitation = OracleLabels(env.tensors)
    pays = FlightPays(env.tensors) if cfg.stop_gate == "pays" else None
    if cfg.stop_gate == "rule":  # the pose rule's moves, chosen on the training contexts, travel with the network
        net.rule_moves.fill_(pose_seek_moves(table, env_cfg)[0])
        pays = RulePays(env.tensors, int(net.rule_moves), ensemble=cfg.rule_ensemble, seed=seeds.rule_bootstrap)
    learner = Learner(net, lr=cfg.lr, gamma=cfg.gamma, grad_clip=cfg.grad_clip, loss=cfg.loss,
                      feature_dropout=feature_dropout, aux_recognition=aux_recognition, imitation=imitation,
                      pays=pays, mirror=mirror)
    lookup = FeatureLookup(env.tensors)
    evaluator = _Evaluator(table, cfg, env_cfg, dev, net)
    out.mkdir(parents=True, exist_ok=True)
    # settings.json first: it is what makes the folder this run's, so a kill between the two
    # writes leaves a run that resumes (method.toml is rewritten on every call)
    write_settings(out, settings)
    spec.save(RunDir(out).method)
    collector = EpisodeCollector(env, net, seed=seeds.acting, device=dev, contexts=level_replay(cfg, env), pays=pays)
    return _Run(out, spec, cfg, settings, net, learner, replay, collector, lookup, evaluator)


def _update(run: _Run, log: TrainLog) -> None:
    """One gradient update on a prioritised batch of replayed episodes."""
    cfg = run.cfg
    batch = run.replay.sample(cfg.batch_size, cfg.beta(run.loop.episodes))
    log.loss, td = run.learner.update(batch, run.lookup, imitate=cfg.imitating(run.loop.episodes))
    run.replay.update_priorities(batch.index, td)
    run.collector.score(batch.scene, td)  # the context sampler's scores (train.context_sampling)
    if run.learner.updates % cfg.target_update == 0:
        run.learner.sync_target()
    if run.learner.updates % TB_EVERY_UPDATES == 0:
        log.update(cfg.epsilon(run.loop.episodes))


def _end_epoch(run: _Run, log: TrainLog, stop: bool) -> None:
    """Evaluate on each split, log, and checkpoint (every ``checkpoint_every`` epochs, at the
    end, and when this call stops); none of it counts as training time."""
    cfg, loop = run.cfg, run.loop
    loop.epoch += 1
    loop.wall = time.perf_counter() - log.t0
    paused = time.perf_counter()
    ret = log.epoch(loop)
    if cfg.eval_splits:
        for split, summary in run.evaluator(run.net).items():
            row = {("eval_episodes" if k == "episodes" else k): v for k, v in summary.items()}
            run.evals.append({"epoch": loop.epoch, "episodes": loop.episodes, "wall_s": loop.wall,
                              "split": split, **row})
            log.evaluation(split, summary, loop.episodes)
        write_evals(run.out, run.evals)
    if loop.epoch % cfg.checkpoint_every == 0 or loop.episodes >= cfg.episodes or stop:
        run.save()
    log.writer.flush()
    log.bar.set_postfix(ret=f"{ret:.3f}", eps=f"{log.eps:.2f}", loss=f"{log.loss:.4f}")
    log.t0 += time.perf_counter() - paused


__all__ = ["train", "TrainConfig", "RunDirError", "PerceptionMismatch", "CheckpointError"]

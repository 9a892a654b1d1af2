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
import json
import platform
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_write, atomic_write_json, remove_temporaries
from ..config import ConfigError, MethodSpec, PerceptionSection
from ..env.aod_env import load_table, select_scenes
from ..env.batched import BatchedAODEnv, EnvTensors
from ..env.config import EnvConfig
from ..env.evaluate import evaluate_policy
from ..perception.nets import resolve_device
from ..runtime import torch_threads
from .acting import GreedyPolicy, epsilon_greedy
from .checkpoint import (
    CheckpointError,
    checkpoint_meta,
    load_checkpoint,
    save_checkpoint,
    save_policy_file,
)
from .config import TrainConfig
from .contract import build_checked_network
from .learner import FeatureLookup, Learner
from .replay import EpisodeReplay
from .rundir import RUN_KEYS, RunDir, RunDirError, check_run_dir, read_settings, run_lock, run_spec

#: Gradient updates between TensorBoard points of the update's diagnostics (``update/*``).
TB_EVERY_UPDATES = 100


def _versions() -> dict[str, str]:
    from .. import __version__

    return {"uevavd": __version__, "torch": torch.__version__, "numpy": np.__version__,
            "python": platform.python_version()}


class PerceptionMismatch(RunDirError):
    """A table built for another perception config than the method trained on it."""


#: The perception keys a table's recorded config must share with the method trained on it.
TABLE_PERCEPTION_KEYS = ("segmenter.name", "decompose", "gray_seed", "encoder.name", "encoder.weights", "classifier.name")


def check_table_perception(perception: PerceptionSection, table: Any, method: str) -> None:
    """Refuse a table built for another perception config than ``method``'s (its
    ``meta.json`` records the method's ``[perception]``): raw features for IBE-MAP, or a
    ResNet18 table for a ResNet50 method, would train and record a run that is not what its
    ``method.toml`` says. Tables made with ``from_arrays`` (no recorded perception) pass."""
    recorded = (table.meta.get("config") or {}).get("perception")
    if not isinstance(recorded, dict):
        return
    want = perception.as_dict()

    def get(d: dict, dotted: str):
        head, _, rest = dotted.partition(".")
        v = d.get(head)
        if rest:
            return v.get(rest) if hasattr(v, "get") else None
        return v

    diffs = [f"perception.{k}: table {get(recorded, k)!r}, method {get(want, k)!r}"
             for k in TABLE_PERCEPTION_KEYS if get(recorded, k) != get(want, k)]
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
            ctx = table.contexts[select_scenes(table, split, train_per_block=env_cfg.train_per_block)]
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


def _train(spec: MethodSpec, table: Any, *, out: Path, episodes: int | None, seed: int, device: str,
           progress: bool, overrides: dict | None, max_epochs: int | None, caller_state: contextlib.ExitStack) -> Path:
    # -- settings -----------------------------------------------------------------------------
    spec = spec.with_overrides(overrides)
    table = load_table(table)
    check_table_perception(spec.perception, table, spec.name)
    cfg = spec.train_config(seed=seed, **({"episodes": episodes} if episodes is not None else {}))
    env_cfg = spec.env
    cfg = cfg.resolve_gamma(env_cfg.gamma)  # one discount: env.gamma (train.gamma is deprecated)
    dev = resolve_device(device if device != "auto" else cfg.device)
    out = Path(out)
    state_name, head_name = spec.state.name, spec.head.name
    settings = {
        "method": spec.name, "spec_hash": spec.hash, "table_key": table.key,
        "table_path": str(table.path) if table.path else None, "feature_dim": table.feature_dim,
        "table_identity": table.perception_identity,
        "seed": seed, "train": cfg.to_dict(), "env": env_cfg.to_dict(), "n_types": 7,
        "n_ranges": env_cfg.max_range, "t_max": env_cfg.t_max, "state": state_name, "head": head_name,
        "device": str(dev), "versions": _versions(),
    }
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    settings["threads"] = torch.get_num_threads()  # results depend on it: recorded, checked on resume
    check_run_dir(out, settings)
    if RunDir(out).finished:
        return out
    # a killed save's temp files (a checkpoint's is full size; the policy's ends .tmp.safetensors)
    remove_temporaries(out)

    # -- seeding and setup (everything that can refuse the input, before the run directory
    # is written: a table without the train or an eval split leaves no half-made run) --------
    # the network initialises from torch's global RNG (on the CPU, then moved); seeded here,
    # the caller's streams (the CPU's, the run's GPU's) restored after the run
    caller_state.enter_context(torch.random.fork_rng(devices=[dev] if dev.type == "cuda" else []))
    torch.random.default_generator.manual_seed(cfg.seed)
    if dev.type == "cuda":
        with torch.cuda.device(dev):
            torch.cuda.manual_seed(cfg.seed)
    # each component checked against its kind's rules (one line naming the broken one) before
    # anything of the run is written
    net = build_checked_network(spec.state, spec.head, table.feature_dim, n_ranges=env_cfg.max_range).to(dev)
    learner = Learner(net, lr=cfg.lr, gamma=cfg.gamma, grad_clip=cfg.grad_clip, loss=cfg.loss)
    replay = EpisodeReplay(cfg.buffer_episodes, env_cfg.t_max, alpha=cfg.per_alpha, eps=cfg.per_eps,
                           seed=cfg.seed + 1, sampling=cfg.replay_sampling, device=dev)
    env = BatchedAODEnv(table, "train", cfg.n_envs, env_cfg, device=dev, seed=cfg.seed + 2,
                        features_dtype=torch.float16)
    lookup = FeatureLookup(env.tensors)
    evaluator = _Evaluator(table, cfg, env_cfg, dev, net)
    out.mkdir(parents=True, exist_ok=True)
    # settings.json first: it is what makes the folder this run's, so a kill between the two
    # writes leaves a run that resumes (method.toml is rewritten on every call)
    atomic_write_json(RunDir(out).settings, settings, sort_keys=True)
    spec.save(RunDir(out).method)
    act_gen = torch.Generator(device=dev)
    act_gen.manual_seed(cfg.seed + 3)
    n, tmax = cfg.n_envs, env_cfg.t_max
    ar = torch.arange(n, device=dev)
    # running episodes: views o_0..o_T, actions and rewards so far
    ep_views = torch.zeros(n, tmax + 1, dtype=torch.int64, device=dev)
    ep_type = torch.zeros(n, tmax, dtype=torch.int64, device=dev)
    ep_range = torch.zeros(n, tmax, dtype=torch.int64, device=dev)
    ep_reward = torch.zeros(n, tmax, dtype=torch.float32, device=dev)
    hidden = net.initial_hidden(n, dev)
    loop = {"episodes": 0, "env_steps": 0, "epoch": 0, "credit": 0.0, "wall": 0.0}
    evals: list[dict[str, Any]] = []
    ckpt_path = RunDir(out).checkpoint
    if ckpt_path.is_file():
        ck = load_checkpoint(ckpt_path, expect=settings)
        net.load_state_dict(ck["net"])
        learner.target.load_state_dict(ck["target"])
        learner.optimizer.load_state_dict(ck["optimizer"])
        learner.updates = int(ck["updates"])
        replay.load_state_dict(ck["replay"])
        env.load_state_dict(ck["env"])
        act_gen.set_state(ck["act_rng"])
        for name, tensor in (("ep_views", ep_views), ("ep_type", ep_type), ("ep_range", ep_range),
                             ("ep_reward", ep_reward), ("hidden", hidden)):
            tensor.copy_(ck[name])
        loop.update(ck["loop"])
        evals = json.loads(ck["evals"])
        obs = env.observe()
    else:
        obs = env.reset()

    def checkpoint() -> None:
        save_checkpoint(ckpt_path, {
            "meta": checkpoint_meta(settings), "net": net.state_dict(), "target": learner.target.state_dict(),
            "optimizer": learner.optimizer.state_dict(), "updates": learner.updates,
            "replay": replay.state_dict(), "env": env.state_dict(), "act_rng": act_gen.get_state(),
            "ep_views": ep_views.cpu(), "ep_type": ep_type.cpu(), "ep_range": ep_range.cpu(),
            "ep_reward": ep_reward.cpu(), "hidden": hidden.cpu(), "loop": dict(loop), "evals": json.dumps(evals),
        })

    from torch.utils.tensorboard import SummaryWriter
    from tqdm.auto import tqdm

    writer = SummaryWriter(str(RunDir(out).tensorboard))
    if not loop["episodes"]:  # the run's settings, once, as TensorBoard's text and hparams
        _log_settings(writer, settings)
    bar = tqdm(total=cfg.episodes, initial=min(loop["episodes"], cfg.episodes), unit="ep",
               desc=f"train {spec.name}", disable=not progress, dynamic_ncols=True)
    recent: deque[float] = deque(maxlen=1000)
    epochs_this_call = 0
    t0 = time.perf_counter() - loop["wall"]
    loss_val = float("nan")

    # -- the loop -------------------------------------------------------------------------------
    try:  # the writer's thread and the bar end with the loop, also when a checkpoint fails
        while loop["episodes"] < cfg.episodes:
            # act: epsilon-greedy over allowed actions; the GRU memory restarts at t = 0
            t = obs["t"]
            with torch.no_grad():
                hidden = hidden * (t != 0)[:, None].to(hidden.dtype)
                q, hidden = net.step(obs["features"], obs["box"], hidden)
                a_type, a_range = net.head.greedy(q, obs["mask"])
                eps = cfg.epsilon(loop["episodes"])
                a_type, a_range = epsilon_greedy(a_type, a_range, obs["mask"], eps, act_gen)
            ep_views[ar, t] = obs["view"]
            ep_type[ar, t] = a_type
            ep_range[ar, t] = a_range
            scene = obs["scene"]
            obs, reward, done, info = env.step(a_type, a_range)
            ep_reward[ar, t] = reward
            loop["env_steps"] += n

            # store finished episodes whole (at most T_max decisions, T_max + 1 views)
            if bool(done.any()):
                idx = done.nonzero()[:, 0]
                ep_views[idx, t[idx] + 1] = info["final_view"][idx]
                replay.add(scene[idx], ep_views[idx], ep_type[idx], ep_range[idx], ep_reward[idx], t[idx] + 1)
                ep_reward[idx] = 0.0
                k = int(idx.numel())
                loop["episodes"] += k
                recent.extend(info["final_return"][idx].tolist())
                bar.update(k)
                if progress and (loop["env_steps"] // n) % 50 == 0:
                    bar.set_postfix(ret=f"{np.mean(recent):.3f}", eps=f"{cfg.epsilon(loop['episodes']):.2f}",
                                    loss=f"{loss_val:.4f}", refresh=False)

            # learn
            if len(replay) >= cfg.learning_starts:
                loop["credit"] += cfg.updates_per_step
                while loop["credit"] >= 1.0:
                    loop["credit"] -= 1.0
                    batch = replay.sample(cfg.batch_size, cfg.beta(loop["episodes"]))
                    loss_val, td = learner.update(batch, lookup)
                    replay.update_priorities(batch.index, td)
                    if learner.updates % cfg.target_update == 0:
                        learner.sync_target()
                    if learner.updates % TB_EVERY_UPDATES == 0:
                        _log_update(writer, learner, loss_val, cfg.epsilon(loop["episodes"]),
                                    loop["episodes"] / max(time.perf_counter() - t0, 1e-9))

            # epoch end: evaluate, log, checkpoint
            if loop["episodes"] >= (loop["epoch"] + 1) * cfg.epoch_episodes or loop["episodes"] >= cfg.episodes:
                loop["epoch"] += 1
                epochs_this_call += 1
                loop["wall"] = time.perf_counter() - t0
                paused = time.perf_counter()  # evaluation, logging and checkpoints are not training time
                ret = float(np.mean(recent)) if recent else float("nan")
                writer.add_scalar("train/recent_return", ret, loop["episodes"])
                writer.add_scalar("train/epsilon", eps, loop["episodes"])
                writer.add_scalar("train/loss", loss_val, loop["episodes"])
                writer.add_scalar("train/episodes_per_s", loop["episodes"] / max(loop["wall"], 1e-9), loop["episodes"])
                if cfg.eval_splits:
                    for split, summary in evaluator(net).items():
                        row = {("eval_episodes" if k == "episodes" else k): v for k, v in summary.items()}
                        evals.append({"epoch": loop["epoch"], "episodes": loop["episodes"], "wall_s": loop["wall"],
                                      "split": split, **row})
                        for key, value in summary.items():
                            if isinstance(value, int | float):
                                writer.add_scalar(f"eval_{split}/{key}", value, loop["episodes"])
                    atomic_write(RunDir(out).evals, "".join(json.dumps(r, default=str) + "\n" for r in evals))
                # stopping this call (max_epochs) always checkpoints, whatever checkpoint_every says
                stop = max_epochs is not None and epochs_this_call >= max_epochs and loop["episodes"] < cfg.episodes
                if loop["epoch"] % cfg.checkpoint_every == 0 or loop["episodes"] >= cfg.episodes or stop:
                    checkpoint()
                writer.flush()
                bar.set_postfix(ret=f"{ret:.3f}", eps=f"{eps:.2f}", loss=f"{loss_val:.4f}")
                t0 += time.perf_counter() - paused
                if stop:
                    break
    finally:
        bar.close()
        writer.close()
    if loop["episodes"] >= cfg.episodes:
        # the shareable policy (the network alone), then the mark that the run is finished
        save_policy_file(RunDir(out).policy, net.state_dict(), RunDir(out).method.read_text(encoding="utf-8"),
                         settings)
        atomic_write_json(RunDir(out).done, {"episodes": loop["episodes"], "env_steps": loop["env_steps"],
                                             "updates": learner.updates, "wall_s": loop["wall"],
                                             "final_eval": evals[-len(cfg.eval_splits):] if cfg.eval_splits else []},
                          sort_keys=True)
    return out


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


__all__ = ["train", "TrainConfig", "RunDirError", "PerceptionMismatch", "CheckpointError", "RUN_KEYS", "read_settings", "run_spec"]

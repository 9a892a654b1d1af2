"""Reference rows from off-the-shelf RL: Stable-Baselines3's DQN and PPO on the same table.

``uevavd ablate --sb3 dqn,ppo`` adds, for each recognizer and seed, one run of each agent on
the first method's table (MAP's) under the default setting's reward, through the library's
Gymnasium env (``DiscreteActions(AODEnv)``), for as many env steps as that method's run of
the same recognizer and seed took (its ``done.json``). Network widths follow the method
(``net_arch`` = g_t, s_t, head hidden), with its learning rate and the env's gamma;
everything else is SB3's default. Each is evaluated greedily from every (context, start) pair
of every split, like the baselines, and enters ``results.csv`` as a reference row
(``episodes = -1``): reported beside the baselines with an interval over recognizers and seeds,
never counted among the paper's methods by the claims. A finished agent's evaluation is
cached in its run folder (``runs/<agent>/default/rec<r>/seed<k>/final_eval.json``), so a
resumed ablation does not train it again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import read_sealed_json, write_sealed_json
from ..config import load_method
from ..env.aod_env import AODEnv
from ..env.evaluate import evaluate_policy
from ..env.wrappers import DiscreteActions
from ..policy.rundir import RunDir, read_done
from ..runtime import torch_threads
from ..table import ObservationTable
from .plan import DEFAULT_SETTING, SB3_AGENTS, env_config
from .results import contexts_covered, metric_row, per_context_rows


def sb3_rows(plan: Any, jobs: list, tables: dict[int, Path], splits: list[str], log
             ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(result rows, per-context rows) of every agent of ``plan.sb3`` (see the module doc)."""
    first = plan.methods[0]
    runs = {(j.recognizer, j.seed): j for j in jobs if j.method == first and j.setting == "default"}
    config = env_config(plan, DEFAULT_SETTING)
    rows, ctx_rows = [], []
    for agent in plan.sb3:
        for r in plan.recognizers:
            for seed in plan.seeds:
                out = plan.out / "runs" / agent / "default" / f"rec{r}" / f"seed{seed}"
                cache = RunDir(out).final_eval
                done = read_sealed_json(cache)  # None where missing, damaged or edited: trained again
                if done is None:
                    job = runs[(r, seed)]
                    steps = int(read_done(job.out)["env_steps"])
                    log(f"  {agent} rec{r} seed{seed}: {steps:,} env steps on {first}'s table")
                    done = _train_and_evaluate(agent, job, tables[r], config, steps, seed, splits)
                    write_sealed_json(cache, done)
                base = {"method": agent, "recognizer": r, "seed": seed, "setting": "default"}
                for split, summary in done["splits"].items():
                    rows.append({**base, **DEFAULT_SETTING, "episodes": -1, "final": True, "split": split,
                                 "eval_contexts": contexts_covered(summary), **metric_row(summary),
                                 "wall_s": done["wall_s"]})
                    ctx_rows += [{**base, "split": split, **c} for c in summary["per_context"]]
    return rows, ctx_rows


def sb3_widths(spec: Any) -> list[int]:
    """The method's layer widths as an SB3 ``net_arch``: g_t (= h_t of a GRU estimator), s_t,
    the head's hidden layer."""
    return [int(spec["state.input_dim"]), int(spec["state.state_dim"]), int(spec["head.hidden"])]


def _train_and_evaluate(agent: str, job: Any, table_path: Path, config: Any, steps: int, seed: int,
                        splits: list[str]) -> dict[str, Any]:
    import stable_baselines3 as sb3

    from ..env.sb3 import SB3Policy, silent_logger

    spec = load_method(job.spec_path)
    table = ObservationTable.load(table_path)
    env = DiscreteActions(AODEnv(table, "train", config))
    widths = sb3_widths(spec)
    with torch_threads(spec.train_config().threads or job.threads):  # as the method's runs
        model = getattr(sb3, SB3_AGENTS[agent])("MultiInputPolicy", env, learning_rate=float(spec["train.lr"]),
                                                gamma=config.gamma, policy_kwargs={"net_arch": widths}, seed=seed,
                                                device="cpu", verbose=0)
        model.set_logger(silent_logger())
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps)
        wall = time.perf_counter() - t0
        policy = SB3Policy(model, config.max_range)
        out: dict[str, Any] = {"agent": agent, "env_steps": int(model.num_timesteps), "wall_s": wall, "splits": {}}
        for split in splits:
            res = evaluate_policy(table, split, policy, config)
            out["splits"][split] = {**res.summary(), "contexts": int(np.unique(res.context).size),
                                    "per_context": per_context_rows(res)}
    return out

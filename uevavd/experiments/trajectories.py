"""Fig. 8's observation sequences: the start view each method's trajectory is shown from,
and the trajectories of the first seed's policies from it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..env.baselines import RandomPolicy
from ..env.config import make_config
from ..env.evaluate import evaluate_policy
from ..env.oracle import OraclePolicy
from ..policy.acting import load_policy
from ..table import ObservationTable, load_table
from .jobs import Job
from .plan import DEFAULT_SETTING, Plan, env_config
from .results import is_done


def pick_trajectory_start(table, config) -> tuple[int, int]:
    """A hard-test (table scene index, start view) where passive fails and the oracle
    succeeds, the kind of start Fig. 8 shows: the start view is not recognised (passive
    stops there and fails) and the oracle's optimal episode from it ends at a recognised
    view. The first hard scene (table order) that has such a start is taken, and in it
    the start whose target is least visible (ties: the lowest view index). Deterministic.

    ``table``: an :class:`~uevavd.table.ObservationTable` or its folder;
    ``config``: the env config of the episodes (thre, C, T_max). Without such a start in
    the hard split it falls back to the least visible start where passive fails, then to
    view 0 of the first hard scene.
    """

    tbl = load_table(table)
    config = make_config(config)
    hard = tbl.scene_indices("hard")
    if not len(hard):
        return 0, 0
    passive_ok = config.recognized(tbl.true_class_probs())  # passive stops at once: recognised iff its start view is
    res = evaluate_policy(tbl, "hard", OraclePolicy(tbl, config), config)
    oracle_ok = np.zeros_like(passive_ok)
    oracle_ok[res.scene, res.start_view] = res.recognized
    vis = np.nan_to_num(tbl.visible, nan=1.0)
    for wanted in (~passive_ok & oracle_ok, ~passive_ok):
        for s in hard:
            candidates = np.flatnonzero(wanted[s])
            if len(candidates):
                return int(s), int(candidates[np.argmin(vis[s, candidates])])
    return int(hard[0]), 0


def trajectory_rows(plan: Plan, jobs: list[Job], tables: dict[str, Path]) -> list[dict[str, Any]]:
    """The greedy episode of each final default-setting policy (first recognizer, seed 0),
    random and oracle, from the same hard-test start; ``tables``: the first recognizer's."""

    config = env_config(plan, DEFAULT_SETTING)
    first = tables[plan.methods[0]]
    scene, start = pick_trajectory_start(first, config)
    out = []

    def one(name: str, seed: int, policy, table_path: Path, env=config) -> None:
        tbl = ObservationTable.load(table_path)
        context = int(tbl.contexts[scene])
        res = evaluate_policy(tbl, "hard", policy, env, contexts=[context])
        i = int(np.flatnonzero(res.start_view == start)[0])
        views = [int(v) for v in res.trajectories[i] if v >= 0]
        out.append({
            "method": name, "seed": seed, "setting": "default", "scene": tbl.scenes[scene],
            "context": context, "split": "hard", "start_view": start, "views": views,
            "recognized": bool(res.recognized[i]), "correct": bool(res.correct[i]), "return": float(res.ret[i]),
        })

    for job in jobs:
        if job.setting == "default" and job.seed == 0 and job.recognizer == plan.recognizers[0] and is_done(job):
            # under the method's own env: the same reward and horizon, and the observation it reads (env.pose)
            one(job.method, 0, load_policy(job.out), Path(job.table), plan.spec(job.method).env)
    tbl = ObservationTable.load(first)
    one("random", 0, RandomPolicy(seed=0), first)
    one("oracle", 0, OraclePolicy(tbl, config), first)
    return out


# -- the driver -----------------------------------------------------------------------------

"""Result rows: each finished run's exhaustive final evaluation (cached beside it), its
per-epoch rows, the registered baselines under every setting, and per-context rows."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import read_sealed_json, write_sealed_json
from ..data.grid import N_VIEWS
from ..env.baselines import baseline_entries
from ..env.config import make_config
from ..env.evaluate import evaluate_gated, evaluate_policy, stopping_summary
from ..policy.acting import load_policy
from ..policy.rundir import RunDir, read_done, read_evals, read_settings
from ..table import ObservationTable
from .plan import SWEEPABLE, AblationError, Job, Plan, env_config
from .report_data import ROOM, STOPPING

log = logging.getLogger(__name__)

RESULT_COLUMNS = [
    "method", "recognizer", "seed", "setting", "thre", "C", "episodes", "final", "split", "eval_contexts", "return",
    "accuracy", "recognition", "path_m", "path_steps", "stop_rate", "steps", "wall_s", *STOPPING, *ROOM,
]
#: Per-context rows of every final evaluation (``contexts.csv``).
CONTEXT_COLUMNS = [
    "method", "recognizer", "seed", "setting", "split", "context", "target", "terrain", "return", "accuracy",
    "recognition", "path_m", "stop_rate", "steps", *STOPPING, *ROOM,
]

def is_done(job: Job) -> bool:
    return RunDir(job.out).finished


def _final_eval_key(run: Path) -> dict[str, Any]:
    """What the cached final evaluation depends on: the finished run (its episode and
    update counts), its env config, its table and the splits."""

    settings = read_settings(run)
    done = read_done(run)
    splits = list(settings.get("train", {}).get("eval_splits") or ["train", "hard"])
    return {"protocol": "every context of the split x all 605 start views, greedy policy, and behind the stop gate",
            "episodes": int(done["episodes"]), "updates": int(done.get("updates", -1)),
            "wall_s": float(done.get("wall_s", float("nan"))), "env": settings["env"],
            "table_key": settings["table_key"], "splits": splits}


def final_eval(job: Job, *, device: str | None = None) -> dict[str, Any] | None:
    """The exhaustive evaluation of a finished run's final policy: every context of each
    of the run's ``train.eval_splits`` x all 605 start views, greedy, under the run's own
    env config (its setting's thre and C). Cached in ``<run>/final_eval.json`` (written
    atomically; recomputed when missing, unreadable or made for another run state).
    Returns ``{"key": ..., "splits": {split: summary + "contexts"}}``, or None for an
    unfinished run.

    The per-epoch evaluations in ``evals.jsonl`` use only ``train.eval_contexts`` evenly
    spaced contexts per split; the results' ``final`` rows come from here instead, so they
    are comparable with the baselines, which are evaluated on every context too.
    """

    run = Path(job.out)
    if not is_done(job):
        return None
    key = json.loads(json.dumps(_final_eval_key(run)))  # as it reads back from JSON
    path = RunDir(run).final_eval
    if path.is_file():
        cached = read_sealed_json(path)  # None where damaged or edited: recomputed
        if cached is None:
            log.warning("%s is damaged or was edited since it was written: evaluating the run again", path)
        if isinstance(cached, dict) and cached.get("key") == key and all(
                "per_context" in v and "hidden_return" in v for v in cached.get("splits", {}).values()):
            return cached
    table = ObservationTable.load(Path(job.table))
    if table.key != key["table_key"]:
        raise AblationError(f"{run}: the run was trained on table {key['table_key']}, but {job.table} holds "
                            f"table {table.key}; cannot evaluate its final policy")
    config = make_config(key["env"])
    dev = device or job.device
    policy = load_policy(run, device=dev)
    splits = {}
    for split in key["splits"]:
        res, gated = evaluate_gated(table, split, policy, config, device=dev)
        splits[split] = {**stopping_summary(res, gated), "contexts": int(np.unique(res.context).size),
                         "per_context": per_context_rows(res, gated)}
    out = {"key": key, "splits": splits}
    write_sealed_json(path, out, fsync=True)
    return out

def per_context_rows(res, gated=None) -> list[dict[str, Any]]:
    """One record per context of an evaluation: context, target and the summary's means; with
    ``gated`` (the same evaluation behind the stop gate), its mean return as ``gated_return``."""
    df = res.per_context()
    if gated is not None:
        df["gated_return"] = gated.per_context()["mean_return"].to_numpy()
    return [{"context": int(r["context"]), "target": str(r["target"]), **metric_row(r)}
            for r in df.to_dict(orient="records")]


def context_terrains(data: Path | None) -> dict[int, str]:
    """``{context: "urban (training)" | "urban (shifted)" | "woodland (training)"}`` from the
    scenes' ``scene.json`` (synthetic worlds); empty where the data does not record it."""
    out: dict[int, str] = {}
    if data is None:
        return out
    for meta_path in Path(data).glob("[0-9][0-9][0-9]/scene.json"):
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(meta, dict) and meta.get("context") is not None and meta.get("terrain"):
            out[int(meta["context"])] = f"{meta['terrain']} ({meta.get('placement', 'training')})"
    return out


def metric_row(summary: dict[str, Any]) -> dict[str, Any]:
    return {
        "return": summary["mean_return"],
        "accuracy": summary["accuracy"],
        "recognition": summary["recognition_rate"],
        "path_m": summary["path_m"],
        "path_steps": summary["path_steps"],
        "stop_rate": summary["stop_rate"],
        "steps": summary["steps_per_episode"],
        # absent from evaluations written before the diagnosis existed
        **{k: summary.get(k, float("nan")) for k in (*STOPPING, *ROOM)},
    }


def contexts_covered(summary: dict[str, Any]) -> int:
    """Contexts an evaluation covered (each from all 605 start views); -1 if unknown."""
    if "contexts" in summary:
        return int(summary["contexts"])
    n = summary.get("eval_episodes", summary.get("episodes"))
    return int(n) // N_VIEWS if n is not None else -1


def run_rows(job: Job, setting: dict[str, float], *, device: str | None = None) -> list[dict[str, Any]]:
    """Rows of one run: its learning curve from ``evals.jsonl`` (one row per epoch x split,
    ``train.eval_contexts`` contexts each, ``final=False``) and, for a finished run, the
    exhaustive evaluation of its final policy (:func:`final_eval`: every context,
    ``final=True``, at the run's last episode count)."""
    rows = []
    base = {"method": job.method, "recognizer": job.recognizer, "seed": job.seed, "setting": job.setting,
            **recorded_setting(job, setting)}
    for r in read_evals(job.out):  # each row checked: an edited digit is refused, naming the line
        rows.append({**base, "episodes": int(r["episodes"]), "final": False, "split": r["split"],
                     "eval_contexts": contexts_covered(r), **metric_row(r),
                     "wall_s": float(r.get("wall_s", float("nan")))})
    final = final_eval(job, device=device)
    if final is not None:
        for split, summary in final["splits"].items():
            rows.append({**base, "episodes": int(final["key"]["episodes"]), "final": True, "split": split,
                         "eval_contexts": contexts_covered(summary), **metric_row(summary),
                         "wall_s": float(final["key"]["wall_s"])})
    return rows


def recorded_setting(job: Job, setting: dict[str, Any]) -> dict[str, Any]:
    """The setting's reward constants (thre, C) as the run recorded them in its
    ``settings.json`` (the env config it trained and was evaluated under), so a row never
    states another value than its run used; the plan's for a run not started yet, and for
    the other swept keys (the results' columns of those hold each method's resolved value)."""
    if not RunDir(job.out).settings.is_file():  # not started; a damaged or edited one is refused
        return dict(setting)
    env = read_settings(job.out).get("env") or {}
    return {k: env.get(SWEEPABLE[k].partition(".")[2], v) if k in SWEEPABLE else v for k, v in setting.items()}


def baseline_rows(plan: Plan, tables: dict[int, Path], splits: Sequence[str], log
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every registered baseline (:func:`uevavd.env.baselines.baseline_entries`; a
    "seeded" one once per RL seed) under every setting, on every split, on each
    recognizer's table. Returns (result rows, per-context rows)."""

    cache = plan.out / "baselines.json"
    done = read_sealed_json(cache) if cache.is_file() else {}
    if done is None:  # damaged, or edited since written: its numbers are not used
        log(f"  {cache} is damaged or was edited since it was written: evaluating the baselines again")
        done = {}
    entries = baseline_entries()
    rows, ctx_rows = [], []
    for r, table in tables.items():
        tbl = ObservationTable.load(table)
        for setting_name, setting in plan.all_settings():
            config = env_config(plan, setting)
            todo = [(e, 0) for e in entries if "seeded" not in e.tags]
            todo += [(e, s) for e in entries if "seeded" in e.tags for s in plan.seeds]
            for split in splits:
                for entry, seed in todo:
                    key = f"{tbl.key}|{setting_name}|{split}|{entry.name}|{seed}"
                    if key not in done or "per_context" not in done[key] or "hidden_return" not in done[key]:
                        policy = entry.load()(table=tbl, config=config, seed=seed)
                        if policy is None:  # does not apply to this table
                            continue
                        res = evaluate_policy(tbl, split, policy, config)
                        done[key] = {**res.summary(), "contexts": int(np.unique(res.context).size),
                                     "per_context": per_context_rows(res)}
                    base = {"method": entry.name, "recognizer": r, "seed": seed, "setting": setting_name}
                    rows.append({**base, **setting, "episodes": -1, "final": True, "split": split,
                                 "eval_contexts": contexts_covered(done[key]), **metric_row(done[key]), "wall_s": 0.0})
                    ctx_rows += [{**base, "split": split, **c} for c in done[key]["per_context"]]
    write_sealed_json(cache, done, fsync=True)
    return rows, ctx_rows

"""The ablation runner: world -> classifier -> observation tables -> training -> results.

Every stage reuses what exists: the world and the classifier are cached by their
settings, tables by the hash of everything that produced them, runs by (method spec,
seed); a killed ablation resumes where it stopped. Results go to one tidy file,
``DIR/results.csv`` (a row per method x seed x setting x evaluation point x split),
rebuilt from the run directories at the end, plus ``DIR/report/``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write
from ..config import ConfigError, load_method
from ..data.grid import N_VIEWS
from ..env.config import EnvConfig
from ..hashing import json_digest
from ..presets import load_preset
from .io import atomic_write_text, write_csv

#: The paper's default reward settings; sweeps vary one of them.
DEFAULT_SETTING = {"thre": EnvConfig.thre, "C": EnvConfig.C}
SWEEPABLE = {"thre": "env.thre", "C": "env.C"}
RESULT_COLUMNS = [
    "method", "recognizer", "seed", "setting", "thre", "C", "episodes", "final", "split", "eval_contexts", "return",
    "accuracy", "recognition", "path_m", "path_steps", "stop_rate", "steps", "wall_s",
]
#: Per-context rows of every final evaluation (``contexts.csv``).
CONTEXT_COLUMNS = [
    "method", "recognizer", "seed", "setting", "split", "context", "target", "terrain", "return", "accuracy",
    "recognition", "path_m", "stop_rate", "steps",
]
#: A finished run's exhaustive evaluation of its final policy (every context x 605 starts).
FINAL_EVAL = "final_eval.json"
PRESET_SECTIONS = {"name", "description", "world", "overrides", "classifier", "ablation"}
SECTION_KEYS = {"world": {"seed", "size", "per_block"},
                "ablation": {"methods", "seeds", "recognizers", "sweeps", "sweep_methods"}}


class AblationError(ValueError):
    """Bad ablation input; the message names the value and what is accepted."""


@dataclass(frozen=True)
class Job:
    """One training run: a method at one setting and seed, on one recognizer's table."""

    method: str
    setting: str
    seed: int
    spec_path: str  #: resolved method spec (TOML), written by the driver
    table: str  #: observation table folder
    out: str  #: run directory
    threads: int = 1
    device: str = "cpu"
    recognizer: int = 0  #: which recognizer (its training seed) the table's probabilities come from

    @property
    def key(self) -> str:
        return f"{self.method}/{self.setting}/rec{self.recognizer}/seed{self.seed}"


@dataclass
class Plan:
    """What an ablation will run, resolved from preset + command line."""

    preset: dict[str, Any]
    methods: list[str]
    seeds: list[int]
    sweeps: dict[str, list[float]]
    sweep_methods: list[str]
    out: Path
    data: Path | None = None
    workers: int = 1
    backend: str = "local"
    device: str = "cpu"
    episodes: int | None = None
    gpus_per_run: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)
    #: recognizer seeds: each trains its own recognizer and builds its own tables; every
    #: method x setting x RL seed runs on each, so intervals include recognizer variance
    recognizers: list[int] = field(default_factory=lambda: [0])
    #: off-the-shelf reference agents (``--sb3``), see :mod:`uevavd.experiments.references`;
    #: not part of the fingerprint: adding them to a finished ablation retrains nothing
    sb3: tuple[str, ...] = ()
    #: take the recognizer from the model zoo when it is the one this plan would train
    #: (same train_605 images, same settings; :meth:`uevavd.zoo.Zoo.recognizer_for`)
    use_zoo: bool = True

    def settings(self, method: str) -> list[tuple[str, dict[str, float]]]:
        """(name, {thre, C}) of each setting this method runs: "default" plus its sweeps."""
        out = [("default", dict(DEFAULT_SETTING))]
        if method in self.sweep_methods:
            for key, values in self.sweeps.items():
                for v in values:
                    s = dict(DEFAULT_SETTING, **{key: float(v)})
                    if s != DEFAULT_SETTING:
                        out.append((f"{key}={v:g}", s))
        return out

    def all_settings(self) -> list[tuple[str, dict[str, float]]]:
        seen: dict[str, dict[str, float]] = {}
        for m in self.methods:
            for name, s in self.settings(m):
                seen.setdefault(name, s)
        return list(seen.items())

    def fingerprint(self) -> dict[str, Any]:
        """What makes two ablations comparable: the preset's content and the data source."""
        preset = {k: v for k, v in self.preset.items() if k not in ("ablation", "description")}
        return {"preset": preset, "data": str(self.data) if self.data else None, "episodes": self.episodes,
                "workers": self.workers}


def parse_sweeps(items: Sequence[str] | None) -> dict[str, list[float]]:
    """``["thre=0.2,0.4", "C=0,0.02"]`` -> ``{"thre": [0.2, 0.4], "C": [0.0, 0.02]}``."""
    sweeps: dict[str, list[float]] = {}
    for item in items or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or key not in SWEEPABLE:
            raise AblationError(
                f"--sweep {item!r}: expected KEY=V1,V2,... with KEY one of {sorted(SWEEPABLE)}"
            )
        try:
            sweeps[key] = [float(v) for v in values.split(",") if v.strip()]
        except ValueError:
            raise AblationError(f"--sweep {item!r}: values must be numbers separated by commas") from None
        if not sweeps[key]:
            raise AblationError(f"--sweep {item!r}: no values")
    return sweeps


def make_plan(
    *,
    preset: str,
    out: str | os.PathLike[str],
    methods: Sequence[str] | None = None,
    seeds: int | None = None,
    sweeps: dict[str, list[float]] | None = None,
    sweep_methods: Sequence[str] | None = None,
    data: str | os.PathLike[str] | None = None,
    workers: int | None = None,
    backend: str = "local",
    device: str = "cpu",
    episodes: int | None = None,
    gpus_per_run: float = 0.0,
    recognizers: int | None = None,
    sb3: str | None = None,
    use_zoo: bool = True,
) -> Plan:
    from ..config import known_methods

    try:
        cfg = load_preset(preset)
    except (ValueError, OSError) as exc:  # unknown name (lists the known ones), missing or bad TOML
        raise AblationError(f"--preset: {exc}") from None
    unknown_sections = sorted(set(cfg) - PRESET_SECTIONS)
    if unknown_sections:
        raise AblationError(f"preset {preset!r}: unknown section(s) {unknown_sections}; "
                            f"accepted: {sorted(PRESET_SECTIONS)}")
    for section, keys in SECTION_KEYS.items():
        extra = sorted(set(cfg.get(section, {})) - keys)
        if extra:
            raise AblationError(f"preset {preset!r} [{section}]: unknown key(s) {extra}; accepted: {sorted(keys)}")
    if data is None and "world" not in cfg:
        raise AblationError(f"preset {preset!r} has no [world] section: pass --data DATASET_ROOT")
    abl = cfg.get("ablation", {})
    methods = list(methods or abl.get("methods", ["map", "memo_map", "ibe_map"]))
    known = known_methods()
    for m in methods:
        if m not in known:
            raise AblationError(f"unknown method {m!r}: known methods are {known} (see `uevavd plugins`)")
    n_seeds = int(seeds if seeds is not None else abl.get("seeds", 1))
    if n_seeds < 1:
        raise AblationError(f"--seeds {n_seeds}: expected at least 1")
    n_rec = int(recognizers if recognizers is not None else abl.get("recognizers", 1))
    if n_rec < 1:
        raise AblationError(f"--recognizers {n_rec}: expected at least 1")
    sweeps = dict(sweeps if sweeps is not None else {k: list(v) for k, v in abl.get("sweeps", {}).items()})
    for key in sweeps:
        if key not in SWEEPABLE:
            raise AblationError(f"sweep over {key!r}: accepted keys are {sorted(SWEEPABLE)}")
    if sweep_methods is None:  # the preset's, among the methods run (none of them: no sweep)
        sweep_methods = [m for m in abl.get("sweep_methods", [methods[-1]]) if m in methods]
    sweep_methods = list(sweep_methods)
    unknown = [m for m in sweep_methods if m not in methods]
    if unknown:
        raise AblationError(f"--sweep-methods {unknown} are not among --methods {methods}")
    if not 0.0 <= float(gpus_per_run) <= 8.0:
        raise AblationError(f"--gpus-per-run {gpus_per_run}: expected a share of a GPU, e.g. 0.25 or 1")
    from .references import parse_sb3

    try:
        sb3_agents = parse_sb3(sb3)
    except ValueError as exc:
        raise AblationError(str(exc)) from None
    if backend not in ("local", "ray"):
        raise AblationError(f"--backend {backend!r}: expected 'local' or 'ray'")
    from ..perception.train import TrainSettings

    try:
        TrainSettings(**cfg.get("classifier", {})).check()
    except (TypeError, ValueError) as exc:
        raise AblationError(f"preset {preset!r} [classifier]: {exc} (accepted keys: "
                            f"{sorted(TrainSettings.__dataclass_fields__)})") from None
    for m in methods:
        try:
            load_method(m, overrides=dict(cfg.get("overrides", {})))
        except ConfigError as exc:
            raise AblationError(f"preset {preset!r} [overrides] for method {m!r}: {exc}") from None
    return Plan(
        preset=cfg,
        methods=methods,
        seeds=list(range(n_seeds)),
        sweeps=sweeps,
        sweep_methods=sweep_methods,
        out=Path(out).resolve(),
        data=Path(data).resolve() if data else None,
        workers=int(workers or default_workers()),
        backend=backend,
        device=device,
        episodes=episodes,
        gpus_per_run=float(gpus_per_run),
        recognizers=list(range(n_rec)),
        sb3=sb3_agents,
        use_zoo=bool(use_zoo),
    )


def default_workers() -> int:
    """Parallel processes when ``--workers`` is not given: the number of cores."""
    return max(1, os.cpu_count() or 1)


# -- stages ---------------------------------------------------------------------------------
class _Stage:
    def __init__(self, plan: Plan, name: str, log):
        self.plan, self.name, self.log = plan, name, log

    def __enter__(self):
        self.t0 = time.perf_counter()
        self.log(f"[{self.name}] ...")
        return self

    def __exit__(self, *exc):
        dt = time.perf_counter() - self.t0
        self.plan.stages[self.name] = self.plan.stages.get(self.name, 0.0) + dt
        if exc[0] is None:
            self.log(f"[{self.name}] done in {dt:.1f} s")


def stage_world(plan: Plan, log) -> Path:
    """The dataset root: ``--data`` as given, else the preset's synthetic world (cached)."""
    if plan.data is not None:
        from ..data.reader import read_dataset

        read_dataset(plan.data)  # fails early, naming the files it cannot parse
        return plan.data
    from ..data.synthetic import write_world
    from ..presets import world_contexts, world_root

    world = plan.preset["world"]
    root = world_root(plan.preset)
    write_world(root, contexts=world_contexts(plan.preset), size=int(world["size"]), seed=int(world["seed"]),
                workers=plan.workers, progress=True)
    from ..data.synthetic.quality import format_rows, read_visible, split_rows

    log("  visibility per split:\n" + format_rows(split_rows(read_visible(root))))
    return root


def stage_classifier(plan: Plan, data: Path, log) -> dict[int, Path]:
    """The recognizers, one per recognizer seed (``TrainSettings.seed``: its initialisation of
    the head, held-out viewpoints and augmentation), each cached by (hash of the dataset's
    train_605 images, training settings): a regenerated world under the same path never
    reuses an old classifier."""
    from ..data.reader import read_dataset
    from ..perception.classifier import classifier_cache_path, data_hash, train_records
    from ..perception.train import TrainSettings, train_classifier

    digest = data_hash(train_records(read_dataset(data)))
    out = {}
    for r in plan.recognizers:
        settings = TrainSettings(**{**plan.preset.get("classifier", {}), "seed": r})
        path = classifier_cache_path(digest, settings)
        shipped = _zoo_recognizer(plan, path.name) if not path.is_file() else None
        if path.is_file():
            log(f"  reusing classifier {path}")
        elif shipped is not None:
            atomic_write(path, shipped.read_bytes())
            log(f"  recognizer {r}: the model zoo's ({shipped}, sha256 checked), trained by this preset's recipe on "
                "these train_605 images (--no-zoo trains it here)")
        else:
            train_classifier(data, path, settings=settings, workers=plan.workers, progress=True)
        out[r] = path
    return out


def _zoo_recognizer(plan: Plan, cache_name: str) -> Path | None:
    """The zoo's recognizer when the plan allows it and it has this cache name."""
    if not plan.use_zoo:
        return None
    from ..zoo import Zoo

    zoo = Zoo.find(str(plan.preset.get("name", "")))
    return None if zoo is None else zoo.recognizer_for(cache_name)


def method_overrides(plan: Plan, method: str, setting: dict[str, float]) -> dict[str, Any]:
    over = dict(plan.preset.get("overrides", {}))
    over.update({SWEEPABLE[k]: v for k, v in setting.items()})
    if plan.episodes is not None:
        over["train.episodes"] = int(plan.episodes)
    return over


def env_config(plan: Plan, setting: dict[str, float]):
    """The env config of a setting as the runs see it: the preset's ``env.*`` overrides (of
    the first method; env keys are shared) with the setting's thre and C. The baselines and
    the trajectories use it, so they are judged under the runs' own reward and horizon."""
    from ..env.config import make_config

    spec = load_method(plan.methods[0], overrides=method_overrides(plan, plan.methods[0], setting))
    return make_config(dict(spec.get("env", {}) or {}))


def stage_tables(plan: Plan, data: Path, classifiers: dict[int, Path], log) -> dict[int, dict[str, Path]]:
    """``{recognizer: {method: table}}``: per recognizer, one table per distinct perception
    config among the methods (MAP and Memo-MAP share)."""
    return {r: _tables_of(plan, data, path, log) for r, path in classifiers.items()}


def _tables_of(plan: Plan, data: Path, classifier: Path, log) -> dict[str, Path]:
    from ..perception.prepare import prepare_table, prepare_table_ray

    tables: dict[str, Path] = {}
    by_perception: dict[str, Path] = {}
    for m in plan.methods:
        spec = load_method(m, overrides=method_overrides(plan, m, DEFAULT_SETTING))
        key = json_digest(spec.to_dict().get("perception", {}), 12)
        if key not in by_perception and plan.backend == "ray":
            by_perception[key] = prepare_table_ray(data, spec, classifier_path=classifier, progress=True)
        elif key not in by_perception:
            by_perception[key] = prepare_table(data, spec, classifier_path=classifier, workers=plan.workers,
                                               progress=True)
        tables[m] = by_perception[key]
        log(f"  {m}: table {tables[m]}")
    return tables


def plan_jobs(plan: Plan, tables: dict[int, dict[str, Path]]) -> list[Job]:
    jobs = []
    for m in plan.methods:
        for setting_name, setting in plan.settings(m):
            spec = load_method(m, overrides=method_overrides(plan, m, setting))
            spec_path = plan.out / "specs" / f"{m}-{setting_name}.toml"
            if not spec_path.is_file() or load_method(spec_path).hash != spec.hash:
                spec.save(spec_path)
            for r in plan.recognizers:
                for seed in plan.seeds:
                    out = plan.out / "runs" / m / setting_name / f"rec{r}" / f"seed{seed}"
                    jobs.append(Job(m, setting_name, seed, str(spec_path), str(tables[r][m]), str(out),
                                    device=plan.device, recognizer=r))
    return jobs


def run_job(job: Job) -> str:
    """Train (or resume, or skip a finished) run, then evaluate its final policy on every
    context (:func:`final_eval`). Runs in a worker process or Ray task."""
    import torch

    from ..policy.trainer import train
    from ..runtime import tune_malloc

    tune_malloc()  # a spawned worker: reuse freed memory as the CLI's process does
    torch.set_num_threads(max(1, job.threads))
    spec = load_method(job.spec_path)
    train(spec, Path(job.table), out=Path(job.out), seed=job.seed, device=job.device, progress=False)
    final_eval(job)
    return job.key


def is_done(job: Job) -> bool:
    return (Path(job.out) / "done.json").is_file()


def _final_eval_key(run: Path) -> dict[str, Any]:
    """What the cached final evaluation depends on: the finished run (its episode and
    update counts), its env config, its table and the splits."""
    from ..policy.trainer import read_settings

    settings = read_settings(run)
    done = json.loads((run / "done.json").read_text(encoding="utf-8"))
    splits = list(settings.get("train", {}).get("eval_splits") or ["train", "hard"])
    return {"protocol": "every context of the split x all 605 start views, greedy policy",
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
    from ..env.config import make_config
    from ..env.evaluate import evaluate_policy
    from ..perception.table import ObservationTable
    from ..policy.agent import load_policy

    run = Path(job.out)
    if not is_done(job):
        return None
    key = json.loads(json.dumps(_final_eval_key(run)))  # as it reads back from JSON
    path = run / FINAL_EVAL
    if path.is_file():
        try:
            cached = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            cached = None  # a damaged cache is recomputed
        if isinstance(cached, dict) and cached.get("key") == key and all(
                "per_context" in v for v in cached.get("splits", {}).values()):
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
        res = evaluate_policy(table, split, policy, config, device=dev)
        splits[split] = {**res.summary(), "contexts": int(np.unique(res.context).size),
                         "per_context": _per_context(res)}
    out = {"key": key, "splits": splits}
    atomic_write_text(path, json.dumps(out, indent=1))
    return out


# -- results --------------------------------------------------------------------------------
def _per_context(res) -> list[dict[str, Any]]:
    """One record per context of an evaluation: context, target and the summary's means."""
    df = res.per_context()
    return [{"context": int(r["context"]), "target": str(r["target"]), **_metric_row(r)}
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


def _metric_row(summary: dict[str, Any]) -> dict[str, Any]:
    return {
        "return": summary["mean_return"],
        "accuracy": summary["accuracy"],
        "recognition": summary["recognition_rate"],
        "path_m": summary["path_m"],
        "path_steps": summary["path_steps"],
        "stop_rate": summary["stop_rate"],
        "steps": summary["steps_per_episode"],
    }


def _contexts(summary: dict[str, Any]) -> int:
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
    path = Path(job.out) / "evals.jsonl"
    rows = []
    base = {"method": job.method, "recognizer": job.recognizer, "seed": job.seed, "setting": job.setting, **setting}
    if path.is_file():
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            r = json.loads(line)
            rows.append({**base, "episodes": int(r["episodes"]), "final": False, "split": r["split"],
                         "eval_contexts": _contexts(r), **_metric_row(r),
                         "wall_s": float(r.get("wall_s", float("nan")))})
    final = final_eval(job, device=device)
    if final is not None:
        for split, summary in final["splits"].items():
            rows.append({**base, "episodes": int(final["key"]["episodes"]), "final": True, "split": split,
                         "eval_contexts": _contexts(summary), **_metric_row(summary),
                         "wall_s": float(final["key"]["wall_s"])})
    return rows


def baseline_rows(plan: Plan, tables: dict[int, Path], splits: Sequence[str], log
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every registered baseline (:func:`uevavd.env.baselines.baseline_entries`; a
    "seeded" one once per RL seed) under every setting, on every split, on each
    recognizer's table. Returns (result rows, per-context rows)."""
    from ..env.baselines import baseline_entries
    from ..env.evaluate import evaluate_policy
    from ..perception.table import ObservationTable

    cache = plan.out / "baselines.json"
    done = json.loads(cache.read_text()) if cache.is_file() else {}
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
                    if key not in done or "per_context" not in done[key]:
                        policy = entry.load()(table=tbl, config=config, seed=seed)
                        if policy is None:  # does not apply to this table
                            continue
                        res = evaluate_policy(tbl, split, policy, config)
                        done[key] = {**res.summary(), "contexts": int(np.unique(res.context).size),
                                     "per_context": _per_context(res)}
                    base = {"method": entry.name, "recognizer": r, "seed": seed, "setting": setting_name}
                    rows.append({**base, **setting, "episodes": -1, "final": True, "split": split,
                                 "eval_contexts": _contexts(done[key]), **_metric_row(done[key]), "wall_s": 0.0})
                    ctx_rows += [{**base, "split": split, **c} for c in done[key]["per_context"]]
    atomic_write_text(cache, json.dumps(done, indent=1))
    return rows, ctx_rows


def pick_trajectory_start(table, config) -> tuple[int, int]:
    """A hard-test (table scene index, start view) where passive fails and the oracle
    succeeds, the kind of start Fig. 8 shows: the start view is not recognised (passive
    stops there and fails) and the oracle's optimal episode from it ends at a recognised
    view. The first hard scene (table order) that has such a start is taken, and in it
    the start whose target is least visible (ties: the lowest view index). Deterministic.

    ``table``: an :class:`~uevavd.perception.table.ObservationTable` or its folder;
    ``config``: the env config of the episodes (thre, C, T_max). Without such a start in
    the hard split it falls back to the least visible start where passive fails, then to
    view 0 of the first hard scene.
    """
    from ..env.aod_env import load_table
    from ..env.config import make_config
    from ..env.evaluate import evaluate_policy
    from ..env.oracle import OraclePolicy

    tbl = load_table(table)
    config = make_config(config)
    hard = tbl.scene_indices("hard")
    if not len(hard):
        return 0, 0
    passive_ok = tbl.correct(config.thre)  # passive stops at once: recognised iff its start view is
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
    from ..env.baselines import RandomPolicy
    from ..env.evaluate import evaluate_policy
    from ..env.oracle import OraclePolicy
    from ..perception.table import ObservationTable
    from ..policy.agent import load_policy

    config = env_config(plan, DEFAULT_SETTING)
    first = tables[plan.methods[0]]
    scene, start = pick_trajectory_start(first, config)
    out = []

    def one(name: str, seed: int, policy, table_path: Path) -> None:
        tbl = ObservationTable.load(table_path)
        context = int(tbl.contexts[scene])
        res = evaluate_policy(tbl, "hard", policy, config, contexts=[context])
        i = int(np.flatnonzero(res.start_view == start)[0])
        views = [int(v) for v in res.trajectories[i] if v >= 0]
        out.append({
            "method": name, "seed": seed, "setting": "default", "scene": tbl.scenes[scene],
            "context": context, "split": "hard", "start_view": start, "views": views,
            "recognized": bool(res.recognized[i]), "correct": bool(res.correct[i]), "return": float(res.ret[i]),
        })

    for job in jobs:
        if job.setting == "default" and job.seed == 0 and job.recognizer == plan.recognizers[0] and is_done(job):
            one(job.method, 0, load_policy(job.out), Path(job.table))
    tbl = ObservationTable.load(first)
    one("random", 0, RandomPolicy(seed=0), first)
    one("oracle", 0, OraclePolicy(tbl, config), first)
    return out


# -- the driver -----------------------------------------------------------------------------
def check_out_dir(plan: Plan) -> None:
    """Refuse a results directory written by another configuration."""
    meta = plan.out / "ablation.json"
    if not meta.is_file():
        if plan.out.exists() and any(plan.out.iterdir()):
            raise AblationError(
                f"--out {plan.out} exists, is not empty and holds no ablation.json: choose a new directory"
            )
        return
    old = json.loads(meta.read_text()).get("fingerprint")
    new = json.loads(json.dumps(plan.fingerprint(), default=str))
    if old != new:
        diff = sorted(k for k in set(old or {}) | set(new) if (old or {}).get(k) != new.get(k))
        raise AblationError(
            f"--out {plan.out} holds an ablation of another configuration (differs in {diff}); "
            "use a new --out directory"
        )


def perception_summary(plan: Plan) -> dict[str, str]:
    """``{method: "encoder NAME (WEIGHTS), segmenter NAME, recognizer NAME"}`` as the runs
    see them, and ``{"recognizer training": settings}``: what the report names as the
    perception every method used."""
    out = {}
    for m in plan.methods:
        p = load_method(m, overrides=method_overrides(plan, m, DEFAULT_SETTING)).to_dict().get("perception", {})
        enc, seg, clf = p.get("encoder", {}), p.get("segmenter", {}), p.get("classifier", {})
        out[m] = (f"encoder {enc.get('name')} ({enc.get('weights', 'default weights')}), segmenter "
                  f"{seg.get('name')}{', decomposed' if p.get('decompose') else ''}, recognizer {clf.get('name')}")
    out["recognizer training"] = json.dumps(plan.preset.get("classifier", {}), sort_keys=True)
    return out


def write_meta(plan: Plan, data: Path | None, status: str) -> None:
    meta = {
        "perception": perception_summary(plan),
        "preset": plan.preset.get("name"),
        "fingerprint": plan.fingerprint(),
        "methods": plan.methods,
        "seeds": len(plan.seeds),
        "recognizers": len(plan.recognizers),
        "sweeps": plan.sweeps,
        "sweep_methods": plan.sweep_methods,
        "backend": plan.backend,
        "data_root": str(data) if data else None,
        "stages": {k: round(v, 2) for k, v in plan.stages.items()},
        "status": status,
    }
    atomic_write_text(plan.out / "ablation.json", json.dumps(meta, indent=1, default=str))


def run_ablation(plan: Plan, *, log=print) -> Path:
    """Run (or resume) the whole ablation; returns the results file."""
    from .backends import run_jobs

    check_out_dir(plan)
    plan.out.mkdir(parents=True, exist_ok=True)
    write_meta(plan, None, "running")
    with _Stage(plan, "world", log):
        data = stage_world(plan, log)
    with _Stage(plan, "classifier", log):
        classifiers = stage_classifier(plan, data, log)
    with _Stage(plan, "tables", log):
        tables = stage_tables(plan, data, classifiers, log)
    write_meta(plan, data, "training")
    jobs = plan_jobs(plan, tables)
    with _Stage(plan, "training", log):
        todo = [j for j in jobs if not is_done(j)]
        log(f"  {len(jobs)} runs, {len(jobs) - len(todo)} finished already, {len(todo)} to run "
            f"on the {plan.backend} backend with {plan.workers} worker(s)")
        run_jobs(todo, backend=plan.backend, workers=plan.workers, log=log, gpus_per_job=plan.gpus_per_run)
    with _Stage(plan, "evaluation", log):
        rows, ctx_rows = [], []
        for job in jobs:
            setting = dict(plan.settings(job.method))[job.setting]
            rows += run_rows(job, setting, device=plan.device)
            final = final_eval(job, device=plan.device)
            base = {"method": job.method, "recognizer": job.recognizer, "seed": job.seed, "setting": job.setting}
            for split, summary in (final or {}).get("splits", {}).items():
                ctx_rows += [{**base, "split": split, **c} for c in summary["per_context"]]
        splits = sorted({r["split"] for r in rows}) or ["train", "hard"]
        first_tables = {r: t[plan.methods[0]] for r, t in tables.items()}
        base_rows, base_ctx = baseline_rows(plan, first_tables, splits, log)
        rows += base_rows
        if plan.sb3:
            from .references import sb3_rows

            ref_rows, ref_ctx = sb3_rows(plan, jobs, first_tables, splits, log)
            rows += ref_rows
            base_ctx += ref_ctx
        terrains = context_terrains(data)
        ctx_rows = [{**c, "terrain": terrains.get(int(c["context"]), "")} for c in ctx_rows + base_ctx]
        from .audit import audit_table, classifier_summary

        audit = {str(r): {"classifier": classifier_summary(classifiers[r]),
                          "splits": audit_table(tables[r][plan.methods[0]], terrains)} for r in plan.recognizers}
        atomic_write_text(plan.out / "recognizer_audit.json", json.dumps(audit, indent=1))
        results = write_csv(plan.out / "results.csv", rows, RESULT_COLUMNS)
        write_csv(plan.out / "contexts.csv", ctx_rows, CONTEXT_COLUMNS)
        traj = trajectory_rows(plan, jobs, tables[plan.recognizers[0]])
        atomic_write_text(plan.out / "trajectories.json", json.dumps(traj, indent=1))
    write_meta(plan, data, "reporting")
    with _Stage(plan, "report", log):
        from .report import write_report

        write_meta(plan, data, "done")
        report = write_report(plan.out)
        log(f"  report: {report}")
    write_meta(plan, data, "done")
    return results


__all__ = [
    "AblationError", "ConfigError", "Job", "Plan", "make_plan", "parse_sweeps", "run_ablation", "run_job",
]

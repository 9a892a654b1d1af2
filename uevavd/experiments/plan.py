"""What an ablation runs: the preset checked and resolved into a :class:`Plan` (methods,
seeds, recognizers, reward settings), and the method overrides and env config each setting
gives its runs."""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import (
    COMPONENT_SECTIONS,
    MethodSpec,
    is_method_path,
    is_shipped,
    load_method,
    method_chain,
)
from ..config_rules import check_count, did_you_mean, thaw
from ..data.splits import PER_BLOCK, TRAIN_PER_BLOCK
from ..env.config import EnvConfig
from ..perception.training.recipe import ClassifierRecipe
from ..presets import load_preset, preset_overrides
from ..runtime import resolve_device, usable_cores
from .axes import SB3_AGENTS as SB3_AGENTS
from .axes import SWEEPABLE as SWEEPABLE
from .axes import AblationError as AblationError
from .axes import file_digest, method_names, parse_sb3, resolved_value, same_value, value_label
from .axes import parse_sweeps as parse_sweeps

#: The paper's three methods, whose claims the report checks.
PAPER_METHODS = ("map", "memo_map", "ibe_map")
#: The paper's default reward settings; sweeps vary one of them.
DEFAULT_SETTING = {"thre": EnvConfig.thre, "C": EnvConfig.C}
#: The method sections whose dotted keys an ablation sweeps; a perception value builds its own
#: observation tables (cached like every table).
SWEEP_SECTIONS = ("env", "train", "state", "head", "perception")
#: The number of training contexts (per target block): swept for every method, on one world
#: that holds the most training contexts asked and every test context (see :func:`make_plan`).
CONTEXTS_KEY = "env.train_per_block"
#: Upper bounds of --seeds and --recognizers (each is a run per method and setting).
MAX_SEEDS = 1000
MAX_RECOGNIZERS = 100

PRESET_SECTIONS = {"name", "description", "world", "overrides", "classifier", "ablation"}
SECTION_KEYS = {"world": {"seed", "size", "per_block"},
                "ablation": {"methods", "seeds", "recognizers", "sweeps", "sweep_methods", "cross"}}


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
    #: draw the report's figures (``--no-figures``: its text and tables only); not part of
    #: the fingerprint, as the report is rewritten from the files at every run
    figures: bool = True
    #: ``--set KEY=V`` of every method: the command line, which wins over the preset and the
    #: method files (:func:`uevavd.config_layers.layer_method`)
    sets: dict[str, Any] = field(default_factory=dict)
    #: method name -> its file, for methods given by path (``--methods my_ibe.toml``)
    method_files: dict[str, str] = field(default_factory=dict)
    #: cross the swept axes (a factorial) instead of varying one key at a time from the default
    cross: bool = False

    def spec(self, method: str, setting: Mapping[str, Any] = DEFAULT_SETTING) -> MethodSpec:
        """The resolved spec of ``method`` under ``setting`` (the preset's overrides, the
        setting's keys, ``--episodes``), loaded once per plan: every stage reads this one."""
        cache = self.__dict__.setdefault("_specs", {})
        key = (method, json.dumps(dict(setting), sort_keys=True, default=str))
        if key not in cache:
            preset, explicit = method_layers(self, setting)
            cache[key] = load_method(self.method_files.get(method, method), preset=preset, overrides=explicit)
        return cache[key]

    def __getstate__(self) -> dict[str, Any]:  # a plan sent to a worker carries no resolved specs
        return {k: v for k, v in self.__dict__.items() if k != "_specs"}

    def settings(self, method: str) -> list[tuple[str, dict[str, Any]]]:
        """(name, {thre, C[, swept keys]}) of each setting this method runs: "default" plus the
        sweeps if it is a sweep method, and the number of training contexts (:data:`CONTEXTS_KEY`)
        whatever it is. One key varied at a time from the default, or with ``cross`` every
        combination of the swept values (a factorial); a value equal to the method's own is its
        default and runs once."""
        spec = self.spec(method) if self.extra_sweeps else None
        axes = []
        for key, values in self.sweeps.items():
            if method in self.sweep_methods or key == CONTEXTS_KEY:
                own = DEFAULT_SETTING[key] if key in SWEEPABLE else resolved_value(spec, key)
                axes.append((key, [v for v in values if not same_value(v, own)]))
        combos: list[dict[str, Any]] = [{}]
        if self.cross:
            for key, values in axes:
                combos = combos + [{**c, key: v} for c in combos for v in values]
        else:
            combos += [{key: v} for key, values in axes for v in values]
        out, seen = [], set()
        for combo in combos:
            name = "+".join(f"{k}={value_label(v)}" for k, v in combo.items()) or "default"
            if name not in seen:
                seen.add(name)
                out.append((name, dict(DEFAULT_SETTING, **combo)))
        return out

    @property
    def extra_sweeps(self) -> list[str]:
        """Swept dotted keys besides the paper's thre and C: each is a column of the results."""
        return [k for k in self.sweeps if k not in SWEEPABLE]

    def all_settings(self) -> list[tuple[str, dict[str, float]]]:
        seen: dict[str, dict[str, float]] = {}
        for m in self.methods:
            for name, s in self.settings(m):
                seen.setdefault(name, s)
        return list(seen.items())

    def fingerprint(self) -> dict[str, Any]:
        """What makes two ablations comparable: the preset's content, the data source, the
        command line's ``--set`` and the content of every method given by path (a changed
        file is another ablation)."""
        preset = {k: v for k, v in self.preset.items() if k not in ("ablation", "description")}
        out = {"preset": preset, "data": str(self.data) if self.data else None, "episodes": self.episodes,
               "workers": self.workers}
        if self.sets:
            out["sets"] = dict(sorted(self.sets.items()))
        if self.method_files:
            out["method_files"] = {m: file_digest(p) for m, p in sorted(self.method_files.items())}
        return out

    def lineage(self, method: str) -> str | None:
        """The paper's method (map, memo_map, ibe_map) that ``method`` derives from: the last of
        them in its inheritance chain, None when none is (the claims judge a derived arm in its
        place where the paper's own is not run)."""
        chain = method_chain(self.method_files.get(method, method))
        paper = [p.stem for p in chain if is_shipped(p) and p.stem in PAPER_METHODS]
        return paper[-1] if paper else None

    def components(self, method: str, setting: Mapping[str, Any] = DEFAULT_SETTING) -> dict[str, Any]:
        """The components a run of ``method`` under ``setting`` uses, as resolved: every component
        section's name and arguments, and the perception switches (what ``ablation.json`` and the
        report name, so that nobody has to trust the preset's text)."""
        spec = self.spec(method, setting)
        out: dict[str, Any] = {s: thaw(spec.get(s)) for s in COMPONENT_SECTIONS if spec.get(s) is not None}
        out["perception.decompose"] = bool(spec.get("perception.decompose", False))
        if spec.preset_notes:
            out["preset keys not applied"] = list(spec.preset_notes)
        return out


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
    world_seed: int | None = None,
    figures: bool = True,
    sets: Mapping[str, Any] | None = None,
    cross: bool | None = None,
) -> Plan:
    try:
        cfg = load_preset(preset)
    except (ValueError, OSError) as exc:  # unknown name (lists the known ones), missing or bad TOML
        raise AblationError(f"--preset: {exc}") from None
    if world_seed is not None:  # another world drawn the same way: a result must not belong to one world
        if "world" not in cfg or data is not None:
            raise AblationError(f"--world-seed {world_seed}: the preset's synthetic world only (not with --data)")
        check_count("--world-seed", world_seed, low=0, high=2**31 - 1, exc=AblationError)
        cfg = {**cfg, "world": {**cfg["world"], "seed": int(world_seed)}}
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
    here = Path(preset).parent if str(preset).endswith(".toml") else Path.cwd()  # the preset's relative paths
    if not methods:  # the preset's, a method file's path read from the preset file's folder
        methods = [str(here / m) if is_method_path(m) and not Path(m).is_absolute() else m
                   for m in abl.get("methods", ["map", "memo_map", "ibe_map"])]
    methods, method_files = method_names(methods)
    if sweep_methods is not None:
        sweep_methods, _ = method_names(sweep_methods, method_files)
    # each seed is a run per method, recognizer and setting: 10**9 seeds was the kernel's kill
    n_seeds = check_count("--seeds", seeds if seeds is not None else abl.get("seeds", 1), high=MAX_SEEDS,
                          exc=AblationError)
    n_rec = check_count("--recognizers", recognizers if recognizers is not None else abl.get("recognizers", 1),
                        high=MAX_RECOGNIZERS, exc=AblationError)
    sweeps = dict(sweeps if sweeps is not None else {k: list(v) for k, v in abl.get("sweeps", {}).items()})
    if CONTEXTS_KEY in sweeps:
        cfg = with_context_axis(cfg, sweeps[CONTEXTS_KEY], from_data=data is not None)
    for key, values in sweeps.items():
        if key in SWEEPABLE:
            for v in values:  # thre=nan or C=-1 would otherwise surface in the runs, or not at all
                try:
                    EnvConfig(**{key: v})
                except ValueError as exc:
                    raise AblationError(f"--sweep {key}={v!r}: {exc}") from None
            continue
        section = key.split(".", 1)[0]
        if section not in SWEEP_SECTIONS or "." not in key:
            hint = did_you_mean(section, SWEEP_SECTIONS) if "." in key else did_you_mean(key, list(SWEEPABLE))
            raise AblationError(f"sweep over {key!r}: expected thre, C or a dotted key of a method's env, train, state, "
                                f"head or perception section{hint}")
        if SWEEPABLE.get(key, key) in (sets or {}):
            raise AblationError(f"--set {key} and --sweep {key} name the same key: sweep it, with the --set value "
                                "among the sweep's values, or set it")
    if sweep_methods is None:  # the preset's, among the methods run (none of them: no sweep)
        by_path = {p: n for n, p in method_files.items()}
        named = [by_path.get(str((here / m).resolve()), m) if is_method_path(m) else m
                 for m in abl.get("sweep_methods", [methods[-1]])]
        sweep_methods = [m for m in named if m in methods]
    sweep_methods = list(sweep_methods)
    unknown = [m for m in sweep_methods if m not in methods]
    if unknown:
        raise AblationError(f"--sweep-methods {unknown} are not among --methods {methods}")
    idle = [k for k in sweeps if k != CONTEXTS_KEY]
    if idle and not sweep_methods:
        raise AblationError(f"--sweep {', '.join(idle)} would run on no method: the preset's sweep methods "
                            f"{abl.get('sweep_methods', [methods[-1]])} are not among --methods {methods}; "
                            "name the methods to sweep with --sweep-methods")
    if not 0.0 <= float(gpus_per_run) <= 8.0:
        raise AblationError(f"--gpus-per-run {gpus_per_run}: expected a share of a GPU, e.g. 0.25 or 1")
    try:
        sb3_agents = parse_sb3(sb3)
    except ValueError as exc:
        raise AblationError(str(exc)) from None
    if backend not in ("local", "ray"):
        raise AblationError(f"--backend {backend!r}: expected 'local' or 'ray'")
    try:  # before any work: a CUDA device that is not there would otherwise surface after the world
        resolve_device(device)
    except ValueError as exc:
        raise AblationError(f"--device: {exc}") from None

    try:
        ClassifierRecipe.from_preset(cfg)
    except ValueError as exc:
        raise AblationError(str(exc)) from None
    plan = Plan(
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
        figures=bool(figures),
        sets=dict(sets or {}),
        method_files=method_files,
        cross=bool(abl.get("cross", False) if cross is None else cross),
    )
    _resolve_specs(plan, preset)
    return plan


def _resolve_specs(plan: Plan, preset: str) -> None:
    """Resolve (and so check, ranges included) every (method, setting) spec the plan runs, once,
    before anything is written: the stages and the runs' spec files read these."""
    for m in plan.methods:
        setting = DEFAULT_SETTING
        try:
            for _, setting in plan.settings(m):
                spec = plan.spec(m, setting)
                spec.env, spec.train_config()  # their ranges (train.episodes >= 1, ...): load_method checks types
        except ValueError as exc:  # ConfigError, EnvConfigError
            swept = {k: v for k, v in setting.items() if k not in DEFAULT_SETTING or DEFAULT_SETTING[k] != v}
            where = (", ".join(f"--sweep {k}={v!r}" for k, v in swept.items()) if swept
                     else f"preset {preset!r} [overrides]" + (f" with --episodes {plan.episodes}"
                                                              if plan.episodes is not None else "")
                     + "".join(f", --set {k}={v!r}" for k, v in plan.sets.items()))
            raise AblationError(f"{where} for method {m!r}: {exc}") from None


def with_context_axis(preset: dict[str, Any], values: Sequence[Any], *, from_data: bool) -> dict[str, Any]:
    """The preset of an ablation that sweeps the number of training contexts per block.

    Its synthetic world holds the most training contexts asked (or the preset's, if more)
    and every test context (Table 1's 5 simple and 5 hard per block), so that every setting
    is evaluated on the same test contexts; a context's images do not depend on which others
    exist, so the scenes, the recognizer and the tables are made once for all settings. The
    default setting keeps the preset's own count (its ``[world] per_block.train``, or an
    ``env.train_per_block`` override), so the default rows are the preset's runs on the
    larger test set. On ``--data`` the world is the data and the default is all its
    training contexts."""
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= TRAIN_PER_BLOCK]
    if bad:
        raise AblationError(f"--sweep {CONTEXTS_KEY}={bad[0]!r}: expected integers in 1..{TRAIN_PER_BLOCK} "
                            "(training contexts per target block)")
    preset = copy.deepcopy(preset)
    over = preset.setdefault("overrides", {})
    if from_data:
        over.setdefault(CONTEXTS_KEY, 0)
        return preset
    world = preset["world"]
    default = int(over.get(CONTEXTS_KEY) or world.get("per_block", {}).get("train", TRAIN_PER_BLOCK))
    world["per_block"] = {**PER_BLOCK, "train": max(default, *values)}
    over[CONTEXTS_KEY] = default
    return preset


def default_workers() -> int:
    """Parallel processes when ``--workers`` is not given: the cores this process may use."""
    return usable_cores()


# -- stages ---------------------------------------------------------------------------------

def method_layers(plan: Plan, setting: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(preset layer, command-line layer)`` of a run's method (:func:`uevavd.config_layers.layer_method`):
    the preset's ``[overrides]`` with the paper's thre and C where the setting keeps them (so a
    method file that sets its own keeps it), and ``--set``, the setting's swept keys (thre and C
    as env keys) and ``--episodes``, which win."""
    preset = preset_overrides(plan.preset)
    explicit = dict(plan.sets)
    for k, v in setting.items():
        kept = k in SWEEPABLE and v == DEFAULT_SETTING[k]
        (preset if kept else explicit)[SWEEPABLE.get(k, k)] = v
    if plan.episodes is not None:
        explicit["train.episodes"] = int(plan.episodes)
    return preset, explicit


def env_config(plan: Plan, setting: dict[str, float]):
    """The env config of a setting as the runs see it: the preset's ``env.*`` overrides (of
    the first method; env keys are shared) with the setting's thre and C. The baselines and
    the trajectories use it, so they are judged under the runs' own reward and horizon. Only
    the setting's env keys apply: a swept key of another section (``head.kappa``) may not
    exist in the first method, and does not change the env."""
    env_only = {k: v for k, v in setting.items() if SWEEPABLE.get(k, k).startswith("env.")}
    return plan.spec(plan.methods[0], env_only).env


@dataclass(frozen=True)
class Job:
    """One training run: a method at one setting and seed, on one recognizer's table."""

    method: str
    setting: str
    seed: int
    spec_path: str  #: resolved method spec (TOML), written by the driver
    table: str  #: observation table folder
    out: str  #: run directory
    threads: int = 1  #: torch threads for a method that sets train.threads = 0 (cores // workers)
    device: str = "cpu"
    recognizer: int = 0  #: which recognizer (its training seed) the table's probabilities come from
    episodes: int = 0  #: the episodes the run trains (its spec's train.episodes), for the progress bar

    @property
    def key(self) -> str:
        return f"{self.method}/{self.setting}/rec{self.recognizer}/seed{self.seed}"

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

from ..config import MethodSpec, known_methods, load_method, parse_override
from ..config_rules import check_count, did_you_mean
from ..data.splits import PER_BLOCK, TRAIN_PER_BLOCK
from ..env.config import EnvConfig
from ..perception.training.classifier import ClassifierRecipe
from ..presets import load_preset, preset_overrides
from ..runtime import resolve_device, usable_cores

#: The paper's default reward settings; sweeps vary one of them.
DEFAULT_SETTING = {"thre": EnvConfig.thre, "C": EnvConfig.C}
#: The paper's two sweeps, by their short names; any other dotted key of a method (env.*,
#: train.*, state.*, head.*; not perception.*, which would need other tables) sweeps too.
SWEEPABLE = {"thre": "env.thre", "C": "env.C"}
#: The method sections whose dotted keys an ablation sweeps (perception keys would need other tables).
SWEEP_SECTIONS = ("env", "train", "state", "head")
#: The number of training contexts (per target block): swept for every method, on one world
#: that holds the most training contexts asked and every test context (see :func:`make_plan`).
CONTEXTS_KEY = "env.train_per_block"
#: Upper bounds of --seeds and --recognizers (each is a run per method and setting).
MAX_SEEDS = 1000
MAX_RECOGNIZERS = 100

PRESET_SECTIONS = {"name", "description", "world", "overrides", "classifier", "ablation"}
SECTION_KEYS = {"world": {"seed", "size", "per_block"},
                "ablation": {"methods", "seeds", "recognizers", "sweeps", "sweep_methods"}}


#: The agents ``--sb3`` accepts, by their row name: SB3 class name.
SB3_AGENTS: dict[str, str] = {"sb3_dqn": "DQN", "sb3_ppo": "PPO"}


def parse_sb3(text: str | None) -> tuple[str, ...]:
    """``"dqn,ppo"`` -> ``("sb3_dqn", "sb3_ppo")``; an unknown name is a ValueError naming the accepted ones."""
    if not text:
        return ()
    names = []
    for part in text.split(","):
        name = f"sb3_{part.strip().lower()}"
        if name not in SB3_AGENTS:
            raise ValueError(f"--sb3 {part.strip()!r}: expected a comma-separated list of "
                             f"{[n.removeprefix('sb3_') for n in SB3_AGENTS]}")
        names.append(name)
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise ValueError("--sb3 needs stable-baselines3: pip install -e \".[sb3]\"") from None
    return tuple(dict.fromkeys(names))



class AblationError(ValueError):
    """Bad ablation input; the message names the value and what is accepted."""


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

    def spec(self, method: str, setting: Mapping[str, Any] = DEFAULT_SETTING) -> MethodSpec:
        """The resolved spec of ``method`` under ``setting`` (the preset's overrides, the
        setting's keys, ``--episodes``), loaded once per plan: every stage reads this one."""
        cache = self.__dict__.setdefault("_specs", {})
        key = (method, json.dumps(dict(setting), sort_keys=True, default=str))
        if key not in cache:
            cache[key] = load_method(method, overrides=method_overrides(self, method, setting))
        return cache[key]

    def __getstate__(self) -> dict[str, Any]:  # a plan sent to a worker carries no resolved specs
        return {k: v for k, v in self.__dict__.items() if k != "_specs"}

    def settings(self, method: str) -> list[tuple[str, dict[str, Any]]]:
        """(name, {thre, C[, swept key]}) of each setting this method runs: "default" plus the
        sweeps if it is a sweep method, and the number of training contexts (:data:`CONTEXTS_KEY`)
        whatever it is (one key varied at a time from the default)."""
        out = [("default", dict(DEFAULT_SETTING))]
        spec = self.spec(method) if self.extra_sweeps else None
        for key, values in self.sweeps.items():
            if method in self.sweep_methods or key == CONTEXTS_KEY:
                for v in values:
                    s = dict(DEFAULT_SETTING, **{key: v})
                    if s != DEFAULT_SETTING and (key in SWEEPABLE or v != resolved_value(spec, key)):
                        out.append((f"{key}={v:g}" if isinstance(v, int | float) else f"{key}={v}", s))
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
        """What makes two ablations comparable: the preset's content and the data source."""
        preset = {k: v for k, v in self.preset.items() if k not in ("ablation", "description")}
        return {"preset": preset, "data": str(self.data) if self.data else None, "episodes": self.episodes,
                "workers": self.workers}


def resolved_value(spec: Any, key: str) -> Any:
    """The value dotted ``key`` has in a resolved spec: the file's, else EnvConfig's or
    TrainConfig's default for env.* and train.* keys (None for a builder argument left unset)."""
    section, _, field_name = key.partition(".")
    if section == "env":
        return getattr(spec.env, field_name, None)
    if section == "train":
        return getattr(spec.train_config(), field_name, None)
    return spec.get(key)


def parse_sweeps(items: Sequence[str] | None) -> dict[str, list[Any]]:
    """``["thre=0.2,0.4", "env.xi2=0.05,0.2"]`` -> ``{"thre": [0.2, 0.4], "env.xi2": [0.05, 0.2]}``.
    thre and C are numbers; a dotted key's values are read like ``--set`` values (TOML:
    ``train.batch_size=32,128`` gives integers). Keys are checked by :func:`make_plan`."""
    sweeps: dict[str, list[Any]] = {}
    for item in items or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise AblationError(f"--sweep {item!r}: expected KEY=V1,V2,... with KEY thre, C or a method's dotted key "
                                "(e.g. env.xi2, train.lr)")
        raw = [v.strip() for v in values.split(",") if v.strip()]
        if key in SWEEPABLE:
            try:
                sweeps[key] = [float(v) for v in raw]
            except ValueError:
                raise AblationError(f"--sweep {item!r}: values must be numbers separated by commas") from None
        else:
            sweeps[key] = [parse_override(f"{key}={v}")[1] for v in raw]
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
    world_seed: int | None = None,
    figures: bool = True,
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
    methods = list(methods or abl.get("methods", ["map", "memo_map", "ibe_map"]))
    known = known_methods()
    for m in methods:
        if m not in known:
            raise AblationError(f"unknown method {m!r}: known methods are {known} (see `uevavd plugins`)")
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
            raise AblationError(f"sweep over {key!r}: expected thre, C or a dotted key of a method's env, train, state "
                                f"or head section (perception keys would need other tables: run another ablation){hint}")
    if sweep_methods is None:  # the preset's, among the methods run (none of them: no sweep)
        sweep_methods = [m for m in abl.get("sweep_methods", [methods[-1]]) if m in methods]
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
                                                              if plan.episodes is not None else ""))
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

def method_overrides(plan: Plan, method: str, setting: dict[str, float]) -> dict[str, Any]:
    over = preset_overrides(plan.preset)
    over.update({SWEEPABLE.get(k, k): v for k, v in setting.items()})
    if plan.episodes is not None:
        over["train.episodes"] = int(plan.episodes)
    return over


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

"""The researcher's API: the pipeline in a few calls, as the README shows it.

    import uevavd

    preset = uevavd.load_preset("quick")
    recognizer = uevavd.train_classifier("data/quick", **preset["classifier"])
    table = uevavd.build_table("data/quick", "ibe_map", classifier=recognizer, preset=preset)
    run = uevavd.train("ibe_map", table, out="runs/ibe_map", preset=preset)
    run.evaluate("hard")                     # a DataFrame: the policy beside the baselines
    run.save_policy("ibe_map.safetensors")   # the network and its method, no replay buffer
    study = uevavd.ablate(out="study", methods=["ibe_map"], sweep={"perception.encoder.name": ["resnet18"]})
    study.differences()                      # each arm minus the default, paired, with 95 % intervals

Every function is a thin layer over the CLI's own code (the same caches, keys and checks);
a :class:`Run` evaluates under its own env config (its ``settings.json``), so nobody rebuilds
an :class:`~uevavd.env.config.EnvConfig` by hand.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from .policy.rundir import RunDir


def train_classifier(data: str | os.PathLike[str], out: str | os.PathLike[str] | None = None, *,
                     workers: int = 2, progress: bool = True, threads: int | None = None, **settings: Any) -> Path:
    """Train the recognizer on ``data``'s ``train_605`` crops (``settings``: the fields of
    :class:`uevavd.perception.training.classifier.ClassifierRecipe`, e.g. a preset's ``[classifier]``); reuse
    it when a file of these settings exists. Returns the ``.safetensors`` path. On the CPU it
    trains on :data:`~uevavd.perception.training.classifier.THREADS` torch threads, as
    ``uevavd ablate`` and the model zoo (its weights depend on the count); another
    ``threads`` needs an ``out`` of its own."""
    from .data.reader import read_dataset
    from .perception.classifier import classifier_cache_path, data_hash, train_records
    from .perception.training.classifier import THREADS, ClassifierRecipe
    from .perception.training.classifier import train_classifier as _train

    s = ClassifierRecipe.from_preset({}, **settings)  # checked: a misspelled key is a ValueError naming it
    threads = THREADS if threads is None else int(threads)
    if out is None and threads != THREADS:
        raise ValueError(f"threads={threads}: the cache holds recognizers trained on {THREADS} threads; "
                         "name an out file for another count")
    if out is None:  # the cache `uevavd ablate` uses too
        out = classifier_cache_path(data_hash(train_records(read_dataset(data))), s)
        if out.is_file():
            return out
    return _train(data, out, settings=s, workers=workers, progress=progress, threads=threads)


def _preset_layer(preset: Any) -> dict[str, Any] | None:
    """A preset's ``[overrides]`` from its name, its TOML path or the loaded preset (a dict)."""
    from .presets import load_preset, preset_overrides

    if preset is None:
        return None
    return preset_overrides(preset if isinstance(preset, Mapping) else load_preset(preset)) or None


def build_table(data: str | os.PathLike[str], method: Any, *, classifier: str | os.PathLike[str] | None = None,
                preset: Any = None, overrides: Mapping[str, Any] | None = None,
                out_dir: str | os.PathLike[str] | None = None, workers: int = 2, progress: bool = True):
    """The observation table of ``method`` (a name, a TOML path or a spec) over dataset ``data``,
    built or found in the cache; returns the :class:`~uevavd.table.ObservationTable`.
    ``preset`` (a name such as ``"quick"``, a TOML path or a loaded preset) and dotted
    ``overrides`` (yours, which win) resolve the method as ``uevavd ablate`` does
    (:func:`uevavd.config_layers.layer_method`)."""
    from .perception.prepare import prepare_table
    from .table import ObservationTable

    path = prepare_table(data, method, classifier_path=classifier, overrides=dict(overrides or {}) or None,
                         preset=_preset_layer(preset), out_dir=out_dir, workers=workers, progress=progress)
    return ObservationTable.load(path)


def train(method: Any, table: Any, *, out: str | os.PathLike[str], episodes: int | None = None, seed: int = 0,
          preset: Any = None, overrides: Mapping[str, Any] | None = None, device: str = "auto",
          progress: bool = True) -> Run:
    """Train ``method`` on ``table`` (an ObservationTable or its folder) into ``out``;
    resumes an unfinished run of the same settings. Returns the :class:`Run`. ``preset`` and
    ``overrides`` resolve the method as in :func:`build_table`."""
    from .config import as_method
    from .policy.trainer import train as _train
    from .table import ObservationTable

    spec = as_method(method, dict(overrides or {}) or None, preset=_preset_layer(preset))
    path = _train(spec, table, out=Path(out), episodes=episodes, seed=seed, device=device, progress=progress)
    # a table in memory has no folder to load again: the Run keeps it (run.evaluate() failed)
    return Run(path, loaded=table if isinstance(table, ObservationTable) else None)


def load_run(path: str | os.PathLike[str]) -> Run:
    """A finished (or paused) run directory."""
    from .policy.rundir import read_settings

    read_settings(path)  # a clear error when it is not a run
    return Run(Path(path))


@dataclass(frozen=True)
class Run:
    """A training run directory: its settings, its policy, its evaluation."""

    path: Path
    #: the table the run was trained on, when given in memory (no folder to load it from)
    loaded: Any = field(default=None, repr=False, compare=False)

    @cached_property
    def settings(self) -> dict[str, Any]:
        from .policy.rundir import read_settings

        return read_settings(self.path)

    @property
    def env_config(self):
        """The run's own :class:`~uevavd.env.config.EnvConfig` (its thre, C, T_max, ...)."""
        from .env.config import make_config

        return make_config(self.settings["env"])

    @property
    def finished(self) -> bool:
        return RunDir(self.path).finished

    def table(self):
        """The run's observation table: the one it was trained on, when given in memory to
        :func:`train`, else loaded from the folder it was trained on."""
        from .table import ObservationTable

        if self.loaded is not None and self.loaded.key == self.settings["table_key"]:
            return self.loaded
        if not self.settings.get("table_path"):
            raise ValueError(f"{self.path} was trained on a table in memory, which has no folder to load it from: "
                             "save the table (table.save(folder)) and train on the folder, or keep the Run "
                             "that uevavd.train returned")
        table = ObservationTable.load(self.settings["table_path"])
        if table.key != self.settings["table_key"]:
            raise ValueError(f"{self.settings['table_path']} now holds table {table.key}, but {self.path} was "
                             f"trained on {self.settings['table_key']}")
        return table

    def policy(self, device: str = "cpu", *, table: Any = None):
        """The greedy policy of the run's latest checkpoint (``act(obs)`` over batched obs), acting
        on the run's own table, or on ``table`` (another table of the run's perception config;
        one of another config is refused)."""
        from .policy.acting import load_policy

        return load_policy(self.path, device=device, table=table)

    def evaluate(self, split: str = "hard", *, baselines: bool = True, device: str = "cpu"):
        """A pandas DataFrame, one row per policy (this run's method, then random, passive,
        the visibility oracle where the table knows visible fractions, and the class-knowing
        oracle), from every context of ``split`` x all 605 starts, under the run's env config;
        ``frame.attrs["per_context"]`` holds the run's policy per context. The same shape as
        :func:`evaluate_pretrained`."""
        from .env.baselines import evaluate_beside_baselines

        name = self.settings["method"]
        frame, per_context = evaluate_beside_baselines(self.table(), split, self.policy(device), name,
                                                       self.env_config, device=device, baselines=baselines)
        frame.attrs["per_context"] = per_context
        return frame

    def curve(self):
        """The learning curve: a pandas DataFrame, one row per evaluation epoch x split
        (``episodes``, ``split``, ``return``, ``accuracy``, ``recognition``, ``path_m``, ...),
        read from the run's ``evals.jsonl`` (each line's digest checked)."""
        import pandas as pd

        from .experiments.results import metric_row
        from .policy.rundir import read_evals

        return pd.DataFrame([{"episodes": int(r["episodes"]), "split": r["split"], **metric_row(r)}
                             for r in read_evals(self.path)])

    def save_policy(self, path: str | os.PathLike[str]) -> Path:
        """The network alone (no optimizer, no replay buffer) as ``.safetensors``, with the
        method, the env config and the table key in its header: :func:`load_policy_file`
        reads it back. (A finished run has already written it as ``policy.safetensors``.)"""
        from .policy.checkpoint import ARCH_KEYS, load_checkpoint, save_policy_file

        state = load_checkpoint(RunDir(self.path).checkpoint, expect=self.settings, keys=ARCH_KEYS)
        return save_policy_file(path, state["net"], RunDir(self.path).method.read_text(encoding="utf-8"),
                                self.settings)


def evaluate_pretrained(method: str, split: str = "hard", **kwargs: Any):
    """The model zoo's ``method`` policy evaluated on ``split`` of the quick world, beside the
    baselines, as ``uevavd evaluate --pretrained`` does: the DataFrame :meth:`Run.evaluate`
    returns (a row per policy), with ``frame.attrs["per_context"]`` (the policy per context) and
    ``frame.attrs["published"]`` (the zoo's published numbers of this split). See
    :func:`uevavd.pretrained.evaluate_pretrained` for the options."""
    from .pretrained import evaluate_pretrained as _evaluate_pretrained

    frame, published, per_context = _evaluate_pretrained(method, split, **kwargs)
    frame.attrs.update(per_context=per_context, published=published)
    return frame


def load_policy_file(path: str | os.PathLike[str], *, table: Any = None, method: str | None = None,
                     device: str = "cpu"):
    """A policy saved by :meth:`Run.save_policy` (or shipped in the model zoo):
    ``(GreedyPolicy, EnvConfig)``; see :func:`uevavd.policy.acting.load_policy_file`."""
    from .policy.acting import load_policy_file as _load_policy_file

    return _load_policy_file(path, table=table, method=method, device=device)


def policy_network(method: Any, table: Any):
    """A fresh network of ``method`` for ``table``, to train with your own code (behaviour
    cloning, say); see :func:`uevavd.policy.acting.policy_network`."""
    from .policy.acting import policy_network as _policy_network

    return _policy_network(method, table)


def save_network(net: Any, path: str | os.PathLike[str], *, method: Any, table: Any) -> Path:
    """Write a :func:`policy_network` as a policy file that :func:`load_policy_file` and
    ``uevavd evaluate FILE --table TABLE`` read; see :func:`uevavd.policy.acting.save_network`."""
    from .policy.acting import save_network as _save_network

    return _save_network(net, path, method=method, table=table)


def ablate(*, out: str | os.PathLike[str], preset: str | os.PathLike[str] = "quick", methods: Any = None,
           seeds: int | None = None, recognizers: int | None = None, sweep: Mapping[str, Any] | None = None,
           sweep_methods: Any = None, cross: bool | None = None, sets: Mapping[str, Any] | None = None,
           episodes: int | None = None, data: str | os.PathLike[str] | None = None, world_seed: int | None = None,
           workers: int | None = None, backend: str = "local", device: str = "cpu", use_zoo: bool = True,
           figures: bool = True, log: Any = print) -> Ablation:
    """Run (or resume) an ablation, as ``uevavd ablate`` does, and return it as an :class:`Ablation`.

    ``methods``: registered names or method-file paths (default the preset's). ``sweep``: dotted
    key -> values, e.g. ``{"perception.encoder.name": ["efficientnet_lite0", "resnet18"]}`` (a
    value may be a whole component section, ``{"name": "resnet18", "weights": "random"}``);
    ``cross=True`` runs every combination of the swept values. ``sets``: dotted keys set for every
    method (the command line's ``--set``). A killed call resumes where it stopped, with the same
    arguments and ``out``."""
    from .experiments.plan import make_plan
    from .experiments.runner import run_ablation

    sweeps = {str(k): list(v) if isinstance(v, list | tuple) else [v] for k, v in (sweep or {}).items()}
    plan = make_plan(preset=str(preset), out=out, methods=methods, seeds=seeds, sweeps=sweeps or None,
                     sweep_methods=sweep_methods, data=data, workers=workers, backend=backend, device=device,
                     episodes=episodes, recognizers=recognizers, use_zoo=use_zoo, world_seed=world_seed,
                     figures=figures, sets=sets, cross=cross)
    run_ablation(plan, log=log)
    return Ablation(Path(plan.out))


@dataclass(frozen=True)
class Ablation:
    """A finished ablation directory (``uevavd ablate --out``): its results, its arms' paired
    differences and its report."""

    path: Path

    @property
    def results(self):
        """``results.csv`` as a pandas DataFrame (a row per method x setting x recognizer x seed x
        evaluation point x split; ``final`` marks the exhaustive final evaluation)."""
        import pandas as pd

        return pd.read_csv(self.path / "results.csv", dtype={"setting": str, "method": str, "split": str})

    def final(self):
        """One row per method x setting x run x split at the final evaluation point (the
        report's numbers); column ``seed`` is ``recognizer * 1000 + RL seed``."""
        from .experiments.report_data import final_rows, load_results

        return final_rows(load_results(self.path / "results.csv"))

    def differences(self, metrics: tuple[str, ...] = ("return", "accuracy", "recognition", "path_m")):
        """Every setting against its method's default, paired run by run, per split and terrain,
        with 95 % intervals: :func:`uevavd.experiments.arms.paired_differences`."""
        from .experiments.arms import paired_differences
        from .experiments.io import ABLATION_FILE, read_ablation_meta
        from .experiments.report_data import final_rows, load_results, recorded_roles
        from .experiments.report_stopping import read_contexts

        with recorded_roles(read_ablation_meta(self.path / ABLATION_FILE)):
            final = final_rows(load_results(self.path / "results.csv"))
            return paired_differences(final, read_contexts(self.path / "contexts.csv"), metrics)

    @property
    def components(self) -> dict[str, Any]:
        """``{method: {setting: components}}``: what every run used, as ``ablation.json`` records it."""
        from .experiments.io import ABLATION_FILE, read_ablation_meta

        return read_ablation_meta(self.path / ABLATION_FILE).get("components", {})

    @property
    def report(self) -> Path:
        """``report/report.md``."""
        return self.path / "report" / "report.md"

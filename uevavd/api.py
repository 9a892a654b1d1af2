"""The researcher's API: the pipeline in a few calls, as the README shows it.

    import uevavd

    preset = uevavd.load_preset("quick")
    recognizer = uevavd.train_classifier("data/quick", **preset["classifier"])
    table = uevavd.build_table("data/quick", "ibe_map", classifier=recognizer, overrides=preset["overrides"])
    run = uevavd.train("ibe_map", table, out="runs/ibe_map", overrides=preset["overrides"])
    run.evaluate("hard")                     # a DataFrame: the policy beside the baselines
    run.save_policy("ibe_map.safetensors")   # the network and its method, no replay buffer

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


def build_table(data: str | os.PathLike[str], method: Any, *, classifier: str | os.PathLike[str] | None = None,
                overrides: Mapping[str, Any] | None = None, out_dir: str | os.PathLike[str] | None = None,
                workers: int = 2, progress: bool = True):
    """The observation table of ``method`` (a name, a TOML path or a spec, with dotted
    ``overrides``) over dataset ``data``, built or found in the cache; returns the
    :class:`~uevavd.table.ObservationTable`."""
    from .perception.prepare import prepare_table
    from .table import ObservationTable

    path = prepare_table(data, method, classifier_path=classifier, overrides=dict(overrides or {}) or None,
                         out_dir=out_dir, workers=workers, progress=progress)
    return ObservationTable.load(path)


def train(method: Any, table: Any, *, out: str | os.PathLike[str], episodes: int | None = None, seed: int = 0,
          overrides: Mapping[str, Any] | None = None, device: str = "auto", progress: bool = True) -> Run:
    """Train ``method`` on ``table`` (an ObservationTable or its folder) into ``out``;
    resumes an unfinished run of the same settings. Returns the :class:`Run`."""
    from .config import as_method
    from .policy.trainer import train as _train
    from .table import ObservationTable

    spec = as_method(method, dict(overrides or {}) or None)
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
        oracle), from every context of ``split`` x all 605 starts, under the run's env config."""
        from .env.baselines import evaluate_beside_baselines

        name = self.settings["method"]
        return evaluate_beside_baselines(self.table(), split, self.policy(device), name, self.env_config,
                                         device=device, baselines=baselines)[0]

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
    baselines, as ``uevavd evaluate --pretrained`` does: ``(DataFrame, published numbers,
    per-context DataFrame)``. See :func:`uevavd.pretrained.evaluate_pretrained` for the options."""
    from .pretrained import evaluate_pretrained as _evaluate_pretrained

    return _evaluate_pretrained(method, split, **kwargs)


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

"""Contract checks for plugin packages and registry entries.

    from uevavd.testing import check_plugin
    import my_plugin
    check_plugin(my_plugin)   # everything `uevavd train`, `evaluate` and `ablate` will ask of it

or, from a shell, ``uevavd plugins --check my_plugin``.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ..config import load_method
from ..config_rules import ConfigError
from ..env.baselines import evaluate_beside_baselines
from ..env.config import make_config
from ..env.evaluate import evaluate_policy
from ..plugins.manager import PluginManager, manager
from ..plugins.registry import KINDS, Entry
from ..policy.acting import load_policy
from ..policy.contract import (
    RUNTIME_ARGUMENTS,
    ComponentError,
    check_estimator_rules,
    check_head_rules,
    missing_runtime_arguments,
)
from ..policy.rundir import read_settings
from ..policy.trainer import train
from ..presets import load_preset, preset_overrides
from . import perception
from .policy import small_run, toy_table

#: The state keys a state builder must take (docs/architecture.md, "A state estimator"): the
#: presets set them.
DOCUMENTED_STATE_KEYS = ("state.input_dim", "state.state_dim")
#: The shipped presets whose ``[overrides]`` every method and component is built with.
PRESETS = ("quick", "paper64", "paper")


def check_registry_entry(entry: Entry) -> None:
    """The entry's builder imports, takes keyword-only arguments and the ones its kind's host
    passes (``feature_dim`` for a state estimator, ...); a method's file is installed and loads."""
    assert entry.kind in KINDS, f"{entry.name}: unknown kind {entry.kind!r}"
    target = entry.load()
    if entry.kind == "method":
        assert Path(target).is_file(), (
            f"method {entry.name}: {entry.target} is not installed ({target} does not exist); list the file in "
            "the plugin's package data (setuptools: [tool.setuptools.package-data]) and reinstall it")
        spec = load_method(target)
        assert spec.name, f"method {entry.name}: no name"
        return
    assert callable(target), f"{entry.kind} {entry.name}: {entry.target} is not callable"
    params = inspect.signature(target).parameters.values()
    positional = [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    assert not positional, (
        f"{entry.kind} {entry.name}: builder {entry.target} takes positional parameters {positional}; "
        "make them keyword-only (def build(*, ...)) so method configs can name them"
    )
    missing = missing_runtime_arguments(entry.kind, target)
    assert not missing, (
        f"{entry.kind} {entry.name}: builder {entry.target} does not take {missing}, which uevavd passes to every "
        f"{entry.kind} builder ({', '.join(RUNTIME_ARGUMENTS[entry.kind])}); add them as keyword-only parameters"
    )


def check_plugin_module(plugin: ModuleType | Any, name: str = "plugin-under-test") -> list[Entry]:
    """Load ``plugin`` beside the built-ins in a scratch manager and check what it registers
    (builders import and take what the host passes). Returns its entries. Raises
    ``AssertionError`` (or the plugin's own error) on a problem. :func:`check_plugin` checks
    far more: every component built and run through its rules, every method trained."""
    scratch = PluginManager(autoload=False)
    scratch.ensure_loaded()
    info = scratch.register_plugin(plugin, name=name)
    assert info.status == "loaded", f"{name}: {info.error}"
    entries = [e for kind in KINDS for e in scratch.registry.entries[kind].values() if e.plugin == name]
    assert entries, f"{name}: registered nothing; implement at least one hook from uevavd.plugins.hookspecs"
    for entry in entries:
        if entry.kind != "method":  # methods may inherit configs that need the global registry
            check_registry_entry(entry)
    return entries


def check_baseline(builder: Any, *, name: str = "baseline", table: Any = None, config: Any = None) -> bool:
    """A ``baseline`` builder (:func:`uevavd.plugins.hookspecs.register_baselines`): built
    with ``table``, ``config`` and ``seed`` (a toy table by default), its policy is evaluated
    exhaustively on the hard split: only allowed actions, finite returns, the same numbers
    for the same seed. Returns False when the builder says it does not apply (None)."""
    missing = missing_runtime_arguments("baseline", builder)
    assert not missing, f"baseline {name}: its builder does not take {missing} (a baseline builder takes table, config, seed)"
    table = toy_table(n_train=2, n_hard=2, feature_dim=8) if table is None else table
    config = make_config(config)

    def run(seed: int):
        policy = builder(table=table, config=config, seed=seed)
        if policy is None:
            return None
        for method in ("reset", "act"):
            assert callable(getattr(policy, method, None)), f"baseline {name}: its policy has no {method}() method"
        try:
            return evaluate_policy(table, "hard", policy, config)
        except Exception as exc:  # noqa: BLE001 - what the policy did wrong, in one message
            raise AssertionError(f"baseline {name}: evaluating it on the hard split raised "
                                 f"{type(exc).__name__}: {exc}") from None

    first = run(0)
    if first is None:
        return False
    assert np.isfinite(first.ret).all(), f"baseline {name}: non-finite returns"
    again = run(0)
    assert again is not None and np.array_equal(first.ret, again.ret), (
        f"baseline {name}: two policies built with seed 0 gave different returns; draw from a generator seeded "
        "by the builder's seed")
    return True


@dataclasses.dataclass
class PluginReport:
    """What :func:`check_plugin` checked (``checked``, one line each) and what it skipped."""

    plugin: str
    entries: list[Entry]
    checked: list[str]
    skipped: list[str]

    def __str__(self) -> str:
        return "\n".join([f"plugin {self.plugin}: {len(self.entries)} components",
                          *(f"  ok    {c}" for c in self.checked), *(f"  skip  {s}" for s in self.skipped)])


def check_plugin(plugin: ModuleType | str, *, name: str | None = None, episodes: int = 300,
                 presets: tuple[str, ...] = PRESETS, train_methods: bool = True) -> PluginReport:
    """Everything uevavd will ask of a plugin package, before a user meets it in a run.

    ``plugin``: the module (or its import name) whose hooks register components. Every entry
    is checked as :func:`check_registry_entry` does; each state estimator and head is built
    with the arguments the trainer and each of ``presets`` pass and run through the rules
    `uevavd train` checks (shapes, causality, a zero memory at an episode start, masks,
    gradients); each baseline through :func:`check_baseline`; each encoder, segmenter and
    classifier that builds with its defaults through its check; each method file loads on
    its own and with each preset's overrides, and (``train_methods``) trains ``episodes``
    toy episodes and is evaluated beside the baselines. Raises ``AssertionError`` listing
    every problem found; returns a :class:`PluginReport`.
    """
    module = importlib.import_module(plugin) if isinstance(plugin, str) else plugin
    pname = manager.name_of(module)
    registered_here = pname is None
    if registered_here:
        pname = name or getattr(module, "__name__", "plugin-under-test")
        manager.register_plugin(module, name=pname)
    try:
        entries = [e for kind in KINDS for e in manager.registry.entries[kind].values() if e.plugin == pname]
        assert entries, f"{pname}: registered nothing; implement at least one hook from uevavd.plugins.hookspecs"
        report = PluginReport(pname, entries, [], [])
        problems: list[str] = []
        for entry in entries:
            try:
                _check_entry(entry, report, presets, episodes if train_methods else 0)
            except (AssertionError, ConfigError, ValueError, TypeError, FileNotFoundError, ImportError) as exc:
                problems.append(" ".join(str(exc).split()) if isinstance(exc, AssertionError)
                                else f"{entry.kind} {entry.name}: {type(exc).__name__}: {' '.join(str(exc).split())}")
        assert not problems, f"plugin {pname}: {len(problems)} problem(s):\n" + "\n".join(f"- {p}" for p in problems)
        return report
    finally:
        if registered_here:
            manager.unregister_plugin(pname)


def _preset_keys(preset: str, section: str) -> dict[str, Any]:
    prefix = section + "."
    return {k[len(prefix):]: v for k, v in preset_overrides(load_preset(preset)).items() if k.startswith(prefix)}


def _check_entry(entry: Entry, report: PluginReport, presets: tuple[str, ...], episodes: int) -> None:
    check_registry_entry(entry)
    what = f"{entry.kind} {entry.name}"
    builder = entry.load()
    if entry.kind in ("state", "head"):
        for preset in (None, *presets):
            keys = _preset_keys(preset, entry.kind) if preset else {}
            where = f"with preset {preset}'s {sorted(keys)}" if preset else "with its defaults"
            runtime = {"feature_dim": 16} if entry.kind == "state" else {"state_dim": 16, "n_types": 7, "n_ranges": 4}
            try:
                built = builder(**{**keys, **runtime})
            except TypeError as exc:
                raise AssertionError(f"{what}: building it {where} raised TypeError: {exc}; accept these keys "
                                     "(or refuse them by name with a ValueError)") from None
            except ValueError as exc:  # refused a preset's key by name: allowed
                report.skipped.append(f"{what} {where}: refused ({exc})")
                continue
            try:
                if entry.kind == "state":
                    check_estimator_rules(built, feature_dim=16, what=f"{what} ({where})")
                else:
                    check_head_rules(built, state_dim=16, n_types=7, n_ranges=4, what=f"{what} ({where})")
            except ComponentError as exc:
                raise AssertionError(str(exc)) from None
            report.checked.append(f"{what} {where}: the rules `uevavd train` checks")
    elif entry.kind == "baseline":
        applies = check_baseline(builder, name=entry.name)
        report.checked.append(f"{what}: evaluated on a toy table's hard split" + ("" if applies else
                                                                                  " (it said it does not apply)"))
    elif entry.kind == "method":
        _check_method(entry, report, presets, episodes)
    else:
        _check_perception(entry, builder, report)


def _check_perception(entry: Entry, builder: Any, report: PluginReport) -> None:
    what = f"{entry.kind} {entry.name}"
    try:
        built = builder()
    except Exception as exc:  # noqa: BLE001 - weights absent, a required argument: say so, go on
        report.skipped.append(f"{what}: does not build with its defaults ({type(exc).__name__}: {exc}); check it "
                              f"with uevavd.testing.check_{entry.kind}(builder(...))")
        return
    getattr(perception, f"check_{entry.kind}")(built)
    report.checked.append(f"{what}: check_{entry.kind} on its defaults")


def _check_method(entry: Entry, report: PluginReport, presets: tuple[str, ...], episodes: int) -> None:
    what = f"method {entry.name}"
    for preset in (None, *presets):
        over = preset_overrides(load_preset(preset)) if preset else {}
        spec = load_method(entry.name, preset=over or None)
        spec.train_config()
        report.checked.append(f"{what} loads" + (f" with preset {preset}'s overrides" if preset else ""))
    if not episodes:
        return
    table = toy_table(n_train=3, n_hard=2, feature_dim=8)
    state = load_method(entry.name).state
    over = {**small_run("map" if state.name == "single_view" else "memo_map"), "train.episodes": episodes}
    # a state builder is asked only for what the docs require it to take (input_dim, state_dim,
    # which the presets set) and what it names itself: the built-ins' box_dim and hidden are theirs
    params = manager.registry.signature("state", state.name).parameters
    takes_any = any(p.kind == p.VAR_KEYWORD for p in params.values())
    over = {k: v for k, v in over.items() if not k.startswith("state.") or k in DOCUMENTED_STATE_KEYS
            or takes_any or k.removeprefix("state.") in params}
    with tempfile.TemporaryDirectory(prefix="uevavd-check-") as tmp:  # as uevavd train, then evaluate, do
        run = train(load_method(entry.name, overrides=over), table, out=Path(tmp) / "run", device="cpu",
                    progress=False)
        frame, _ = evaluate_beside_baselines(table, "hard", load_policy(run), entry.name,
                                             make_config(read_settings(run)["env"]))
    assert np.isfinite(frame.loc[entry.name, "mean_return"]), f"{what}: non-finite evaluation return"
    report.checked.append(f"{what}: trained {episodes} toy episodes and evaluated beside {len(frame) - 1} baselines")

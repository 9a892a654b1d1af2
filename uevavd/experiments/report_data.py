"""Reading an ablation directory for the report: ``results.csv`` (checked), and the
selections the report and the claims share (final evaluation point, default setting,
sweeps, per-seed GenGap).

``results.csv`` is tidy: one row per method x seed x setting x evaluation point x split
(columns in :data:`REQUIRED_COLUMNS`). Baselines (random, passive, oracle) have ``episodes == -1``
and are constant reference values. A learned run has its per-epoch learning-curve rows (``final``
False; evaluated on ``train.eval_contexts`` contexts) and, once finished, one ``final`` row per
split from the exhaustive evaluation of its final policy (every context, like the baselines; the
optional ``eval_contexts`` column says how many contexts a row covers). Files of older versions
flag the last curve point ``final`` instead; both read the same way here.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..env.config import EnvConfig
from ..plugins.manager import manager
from .labels import LABELS, METHOD_ORDER
from .plan import SB3_AGENTS
from .stats import Estimate

#: The roles of an ablation's rows as its ``ablation.json`` recorded them when it ran
#: (``{"baselines": [...], "deterministic": [...]}``), set by :func:`recorded_roles` while a
#: report is written: a report never depends on which plugins are installed when it is read.
_RECORDED: ContextVar[dict[str, Any] | None] = ContextVar("uevavd_recorded_roles", default=None)


@contextmanager
def recorded_roles(meta: dict[str, Any] | None) -> Iterator[None]:
    """Within this block, :func:`baselines` and :func:`deterministic` answer from the
    ablation's own record (``meta["roles"]``, written by the runner); an ablation.json of an
    earlier version, without it, falls back to the registry."""
    roles = meta.get("roles") if isinstance(meta, dict) else None
    ok = isinstance(roles, dict) and all(isinstance(roles.get(k), list) for k in ("baselines", "deterministic"))
    token = _RECORDED.set(roles if ok else None)
    try:
        yield
    finally:
        _RECORDED.reset(token)


def baselines() -> tuple[str, ...]:
    """Reference policies, never counted among the learned methods: those the ablation
    recorded (:func:`recorded_roles`), else the registered baselines (kind ``"baseline"``,
    :func:`uevavd.plugins.hookspecs.register_baselines`) and the off-the-shelf agents of
    ``ablate --sb3`` (:data:`uevavd.experiments.plan.SB3_AGENTS`)."""
    recorded = _RECORDED.get()
    if recorded is not None:
        return tuple(recorded["baselines"])
    return (*(e.name for e in manager.registry.in_order("baseline")), *SB3_AGENTS)


def deterministic() -> tuple[str, ...]:
    """Baselines that do not depend on the seed (not tagged "seeded"): one row per
    recognizer, exact with one recognizer; as recorded by the ablation, else registered."""
    recorded = _RECORDED.get()
    if recorded is not None:
        return tuple(recorded["deterministic"])
    return tuple(e.name for e in manager.registry.in_order("baseline") if "seeded" not in e.tags)


def roles_now() -> dict[str, Any]:
    """What :func:`recorded_roles` reads back: the baselines and deterministic baselines of
    the registry now, and the display label of every registered method and baseline (the
    runner records them in ``ablation.json``)."""
    labels = {e.name: e.label for kind in ("method", "baseline") for e in manager.registry.in_order(kind) if e.label}
    return {"baselines": list(baselines()), "deterministic": list(deterministic()), "labels": {**labels, **LABELS}}


#: A run's unit id in the loaded results: ``recognizer * UNIT + seed`` in column ``seed``
#: (the RL seed alone in ``rl_seed``), so that every grouping by seed keeps the runs of
#: different recognizers apart; ``seed // UNIT`` is the recognizer.
UNIT = 1000
SPLITS: tuple[str, ...] = ("train", "simple", "hard", "validation")
#: The paper's defaults (docs/environment.md), written once in EnvConfig.
DEFAULT_THRE = EnvConfig.thre
DEFAULT_C = EnvConfig.C
METRICS: tuple[str, ...] = (
    "return", "accuracy", "recognition", "path_m", "path_steps", "stop_rate", "steps", "wall_s",
)
#: The stopping diagnosis (:meth:`uevavd.env.evaluate.EvalResult.summary`) and a learned policy's
#: return behind the stop gate (NaN for the baselines and the per-epoch rows); optional columns.
STOPPING: tuple[str, ...] = ("box_start", "moved_if_box", "box_lost", "reco_lost", "gated_return")
#: Where the room is: the mean return of the starts whose observed box is non-empty, and of the
#: others (:meth:`uevavd.env.evaluate.EvalResult.summary`); optional columns.
ROOM: tuple[str, ...] = ("box_return", "hidden_return")
REQUIRED_COLUMNS: tuple[str, ...] = (
    "method", "seed", "setting", "thre", "C", "episodes", "final", "split", *METRICS,
)
#: Sweep name -> (column, the setting-name prefix of its rows).
SWEEPS: dict[str, str] = {"thre": "thre", "C": "C"}


def md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Lines of a Markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def label(method: str) -> str:
    """Display name of a method ("ibe_map" -> "IBE-MAP"): as the ablation recorded it, else
    uevavd's own, else the one a plugin registered with it, else the name."""
    recorded = _RECORDED.get()
    if recorded is not None and isinstance(recorded.get("labels"), dict) and method in recorded["labels"]:
        return str(recorded["labels"][method])
    if method in LABELS:
        return LABELS[method]
    for kind in ("method", "baseline"):
        entry = manager.registry.entries.get(kind, {}).get(method)
        if entry is not None and entry.label:
            return entry.label
    return method


#: Baselines drawn first (the floor) and last (the ceilings); other baselines sit between the
#: learned methods and these.
#: The pose rule's privileged departure ceilings (:mod:`uevavd.env.rule_values`), one and two departures.
DEPARTURE_CEILINGS: tuple[str, ...] = ("departure_ceiling", "departure_ceiling2")
_FIRST = ("random", "passive", "box_gate", "pose_seek")
_LAST = (*DEPARTURE_CEILINGS, "visibility_oracle", "oracle")


def order_methods(methods) -> list[str]:
    """Methods in report order: random, passive and the box gate, the learned methods (uevavd's in
    :data:`METHOD_ORDER`, then others by name), the other baselines (SB3 references, a
    plugin's), then the two oracles: learned methods stay together whatever is installed."""
    ms = list(dict.fromkeys(methods))
    refs = set(baselines())

    def rank(m: str) -> tuple[int, int, str]:
        known = METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER)
        if m in _FIRST:
            return 0, _FIRST.index(m), m
        if m in _LAST:
            return 3, _LAST.index(m), m
        return (2 if m in refs else 1), known, m

    return sorted(ms, key=rank)


def learned(methods) -> list[str]:
    """The methods that are trained (not baselines), in report order."""
    refs = baselines()
    return [m for m in order_methods(methods) if m not in refs]


def _as_bool(col: pd.Series, path: Path) -> pd.Series:
    if col.dtype == bool:
        return col
    mapping = {"true": True, "1": True, "1.0": True, "false": False, "0": False, "0.0": False}
    out = col.astype(str).str.strip().str.lower().map(mapping)
    if out.isna().any():
        bad = col[out.isna()].iloc[0]
        raise ValueError(f"{path}: column 'final' holds {bad!r}; expected True/False (or 1/0)")
    return out.astype(bool)


def _check_rows(path: Path) -> None:
    """Every row has the header's number of fields: pandas fills a row cut short (a copy or a
    write that stopped mid-row) with NaN, which changed the claims without a word."""
    import csv

    with path.open(encoding="utf-8", newline="") as fh:
        rows = csv.reader(fh)
        header = next(rows, [])
        for n, row in enumerate(rows, 2):
            if row and len(row) != len(header):
                raise ValueError(f"{path}, line {n}: {len(row)} fields where the header has {len(header)} (a row cut "
                                 "short?); rerun the `uevavd ablate` that wrote it to write the table again")


def load_results(path: str | Path) -> pd.DataFrame:
    """Read and check ``results.csv``; returns a DataFrame with typed columns
    (``seed``/``episodes`` int64, ``final`` bool, metrics float64, ``setting``/``method``/
    ``split`` str). Raises ``FileNotFoundError``/``ValueError`` naming the file and what
    was expected."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} does not exist; expected the ablation's results table (run `uevavd ablate` "
            f"or `uevavd demo` first, then `uevavd report {path.parent}`)"
        )
    try:
        df = pd.read_csv(path, dtype={"setting": str, "method": str, "split": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot parse as CSV ({e})") from None
    _check_rows(path)
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}")
    if df.empty:
        raise ValueError(f"{path}: no rows; expected one row per method x seed x setting x eval point x split")
    bad_split = sorted(set(df["split"]) - set(SPLITS))
    if bad_split:
        raise ValueError(f"{path}: unknown split(s) {bad_split}; expected one of {list(SPLITS)}")
    for col in ("seed", "episodes"):
        try:
            df[col] = pd.to_numeric(df[col], errors="raise").astype(np.int64)
        except (ValueError, TypeError):
            raise ValueError(f"{path}: column {col!r} must hold integers") from None
    for col in ("thre", "C", *METRICS, *(c for c in (*STOPPING, *ROOM) if c in df.columns)):
        try:
            df[col] = pd.to_numeric(df[col], errors="raise").astype(np.float64)
        except (ValueError, TypeError):
            raise ValueError(f"{path}: column {col!r} must hold numbers") from None
    df["final"] = _as_bool(df["final"], path)
    df["setting"] = df["setting"].fillna("default").astype(str)
    if "recognizer" not in df.columns:  # files of one recognizer before the column existed
        df["recognizer"] = 0
    try:
        df["recognizer"] = pd.to_numeric(df["recognizer"], errors="raise").astype(np.int64)
    except (ValueError, TypeError):
        raise ValueError(f"{path}: column 'recognizer' must hold integers") from None
    if ((df["seed"] < 0) | (df["seed"] >= UNIT) | (df["recognizer"] < 0)).any():
        raise ValueError(f"{path}: seeds must lie in 0..{UNIT - 1} and recognizers be >= 0")
    df["rl_seed"] = df["seed"]
    df["seed"] = df["recognizer"] * UNIT + df["seed"]
    return df


def groups_of(units) -> np.ndarray:
    """The recognizer of each unit id (column ``seed`` of loaded results)."""
    return np.asarray(units, dtype=np.int64) // UNIT


def is_baseline(df: pd.DataFrame) -> pd.Series:
    """Rows of reference policies: a baseline method name or ``episodes < 0``."""
    return df["method"].isin(baselines()) | (df["episodes"] < 0)


def final_rows(df: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, seed, setting, split) at the final evaluation point.

    Learned runs use the rows flagged ``final``; a run with none flagged (interrupted)
    uses its last evaluation point. Baseline rows are averaged per key (they are
    constant). Returns the metric columns plus ``episodes``, ``thre`` and ``C``.
    """
    keys = ["method", "seed", "setting", "split"]
    base = df[is_baseline(df)]
    runs = df[~is_baseline(df)]
    parts = []
    if not runs.empty:
        flagged = runs[runs["final"]]
        have = set(map(tuple, flagged[keys].drop_duplicates().to_numpy()))
        rest = runs[[tuple(k) not in have for k in runs[keys].to_numpy()]]
        if not rest.empty:
            last = rest.groupby(keys)["episodes"].transform("max")
            rest = rest[rest["episodes"] == last]
        parts.append(pd.concat([flagged, rest]).groupby(keys, as_index=False).last())
    if not base.empty:
        parts.append(base.groupby(keys, as_index=False).agg({
            **{m: "mean" for m in (*METRICS, *(c for c in (*STOPPING, *ROOM) if c in base))}, "thre": "first", "C": "first", "episodes": "max", "final": "first"}))
    if not parts:
        return df.iloc[0:0]
    return pd.concat(parts, ignore_index=True)


def curve_rows(df: pd.DataFrame) -> pd.DataFrame:
    """The learning-curve rows of learned runs: every non-baseline row that is not a
    ``final`` row standing beside a curve point at the same (method, seed, setting, split,
    episodes) -- the exhaustive final evaluation is not a curve point (it covers other
    contexts than the per-epoch evaluations). A ``final`` row with no curve point beside it
    (files that flag the last curve point final) stays."""
    keys = ["method", "seed", "setting", "split", "episodes"]
    runs = df[~is_baseline(df)]
    plain = runs[~runs["final"]]
    have = set(map(tuple, plain[keys].drop_duplicates().to_numpy().tolist()))
    flagged = runs[runs["final"]]
    alone = flagged[[tuple(k) not in have for k in flagged[keys].to_numpy().tolist()]]
    return pd.concat([plain, alone]).sort_index()


def default_setting(df: pd.DataFrame) -> str:
    """Name of the default setting: "default" if present, else the setting at thre=0.2,
    C=0.02, else the most common setting."""
    settings = df["setting"].unique().tolist()
    if "default" in settings:
        return "default"
    at = df[np.isclose(df["thre"], DEFAULT_THRE) & np.isclose(df["C"], DEFAULT_C)]
    if not at.empty:
        return str(at["setting"].mode().iloc[0])
    return str(df["setting"].mode().iloc[0])


def sweep_rows(final: pd.DataFrame, param: str, method: str | None = None) -> pd.DataFrame:
    """Final rows of the ``param`` sweep ("thre" or "C") of learned methods: the rows whose
    setting is named ``"<param>=..."`` plus the default setting (the sweep's default
    point). Where a named setting duplicates the default value, the named one wins.
    Empty when no ``"<param>=..."`` rows exist."""
    if param not in SWEEPS:
        raise ValueError(f"unknown sweep {param!r}: expected one of {list(SWEEPS)}")
    runs = final[~is_baseline(final)]
    if method is not None:
        runs = runs[runs["method"] == method]
    named = runs[runs["setting"].str.replace(" ", "").str.startswith(f"{param}=")]
    if named.empty:
        return named
    default = runs[runs["setting"] == default_setting(final)]
    default = default[~default[param].round(9).isin(named[param].round(9))]
    return pd.concat([named, default], ignore_index=True).sort_values([param, "method", "seed"])


def sweep_methods(final: pd.DataFrame, param: str) -> list[str]:
    """Learned methods that have rows of the ``param`` sweep, IBE-MAP first."""
    runs = final[~is_baseline(final)]
    ms = runs.loc[runs["setting"].str.replace(" ", "").str.startswith(f"{param}="), "method"].unique().tolist()
    return sorted(ms, key=lambda m: (m != "ibe_map", order_methods(ms).index(m)))


def per_seed(final: pd.DataFrame, method: str, split: str, metric: str, setting: str) -> np.ndarray:
    """(n_units,) float64 values of ``metric`` at the final point, by unit (recognizer, then seed)."""
    return _per_unit(final, method, split, metric, setting)[1]


def _per_unit(final: pd.DataFrame, method: str, split: str, metric: str, setting: str):
    rows = np.flatnonzero((final["method"].to_numpy() == method) & (final["split"].to_numpy() == split)
                          & (final["setting"].to_numpy() == setting))  # numpy: pandas masks took 4 ms an estimate
    order = rows[np.argsort(final["seed"].to_numpy(dtype=np.int64)[rows], kind="quicksort")]  # sort_values' order
    return final["seed"].to_numpy(dtype=np.int64)[order], final[metric].to_numpy(dtype=np.float64)[order]


def estimate_units(units, values, deterministic: bool = False) -> Estimate:
    """The estimate of a mean over runs: the nested bootstrap when the units span several
    recognizers; else a t-interval over seeds, or exact for a deterministic baseline."""
    groups = groups_of(units)
    if np.unique(groups).size >= 2:
        return Estimate.of(values, groups=groups)
    if deterministic and np.size(values):
        return Estimate.exact(float(np.mean(values)))
    return Estimate.of(values)


def estimate(final: pd.DataFrame, method: str, split: str, metric: str, setting: str) -> Estimate:
    """Mean and 95 % interval over runs (:func:`estimate_units`); exact for a deterministic
    baseline (passive, the oracles) with one recognizer."""
    units, v = _per_unit(final, method, split, metric, setting)
    return estimate_units(units, v, method in deterministic())


def _gengap_units(final: pd.DataFrame, method: str, setting: str, test: str):
    sel = final[(final["method"] == method) & (final["setting"] == setting)]
    wide = sel.pivot_table(index="seed", columns="split", values="return", aggfunc="mean")
    if "train" not in wide or test not in wide:
        return np.zeros(0, np.int64), np.zeros(0)
    g = (wide["train"] - wide[test]).dropna()
    return g.index.to_numpy(dtype=np.int64), g.to_numpy(dtype=np.float64)


def gengap(final: pd.DataFrame, method: str, setting: str, test: str = "hard") -> np.ndarray:
    """(n,) per-run GenGap = return(train) - return(``test``), runs present in both."""
    return _gengap_units(final, method, setting, test)[1]


def gengap_estimate(final: pd.DataFrame, method: str, setting: str, test: str = "hard") -> Estimate:
    units, v = _gengap_units(final, method, setting, test)
    return estimate_units(units, v, method in deterministic())

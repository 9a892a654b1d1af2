"""Arms against the default: for every learned method and every setting it ran besides its
default (a swept encoder, segmenter, state estimator, head, reward constant, or a crossed
combination of them), the paired difference of its final-point metric against the default's,
per split and, where ``contexts.csv`` records terrains, per split and terrain.

Paired means unit by unit: the same RL seed on the same recognizer (and so the same tables'
probabilities, the same contexts and the same 605 starts); with one recognizer the interval is
Student t over the seeds' differences, with several the two-stage bootstrap over recognizers,
then seeds (:func:`uevavd.experiments.report_data.estimate_units`). A setting's runs that have
no default twin (another seed count) are left out of its difference and counted in ``n``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..atomic import atomic_write
from .report_data import (
    SPLITS,
    UNIT,
    default_setting,
    estimate_units,
    is_baseline,
    label,
    md_table,
    order_methods,
)

#: The metrics ``arms.csv`` holds (the report's section shows the return).
ARM_METRICS = ("return", "accuracy", "recognition", "path_m")
#: The columns of :func:`paired_differences`' DataFrame.
ARM_COLUMNS = ("method", "setting", "split", "terrain", "metric", "n", "default", "value", "difference", "lo", "hi")


def _units(rows: pd.DataFrame, metric: str) -> pd.Series:
    """Per-unit (column ``seed``: recognizer * UNIT + seed) mean of ``metric``."""
    return rows.groupby("seed")[metric].mean()


def paired_differences(final: pd.DataFrame, contexts: pd.DataFrame | None = None,
                       metrics: tuple[str, ...] = ("return",)) -> pd.DataFrame:
    """One row per learned method x non-default setting x split (x terrain) x metric: the
    default's and the setting's means over the paired units, their difference with its 95 %
    interval (columns :data:`ARM_COLUMNS`). ``final`` is :func:`~uevavd.experiments.report_data.final_rows`'
    frame; ``contexts`` the per-context rows (``contexts.csv``, loaded), for the terrains."""
    runs = final[~is_baseline(final)]
    if runs.empty:
        return pd.DataFrame(columns=ARM_COLUMNS)
    default = default_setting(final)
    groups: list[tuple[str, str, pd.DataFrame]] = [(s, "all", runs[runs["split"] == s]) for s in SPLITS]
    if contexts is not None and not contexts.empty and {"terrain", "recognizer"} <= set(contexts.columns):
        ctx = contexts[~contexts["method"].isin(set(final.loc[is_baseline(final), "method"]))]
        ctx = ctx.assign(terrain=ctx["terrain"].fillna("").astype(str))
        ctx = ctx[ctx["terrain"] != ""]
        per = ctx.groupby(["method", "recognizer", "seed", "setting", "split", "terrain"], as_index=False)[
            [m for m in metrics if m in ctx.columns]].mean()
        per["seed"] = per["recognizer"].astype(np.int64) * UNIT + per["seed"].astype(np.int64)
        for (split, terrain), sel in per.groupby(["split", "terrain"], sort=True):
            if per.loc[per["split"] == split, "terrain"].nunique() > 1:  # one terrain: the split's own rows
                groups.append((str(split), str(terrain), sel))
    out = []
    for method in order_methods(runs["method"].unique()):
        settings = [s for s in runs.loc[runs["method"] == method, "setting"].unique() if s != default]
        for split, terrain, rows in groups:
            rows = rows[rows["method"] == method]
            base_rows = rows[rows["setting"] == default]
            if base_rows.empty:
                continue
            for setting in settings:
                arm = rows[rows["setting"] == setting]
                for metric in metrics:
                    if arm.empty or metric not in arm:
                        continue
                    a, b = _units(arm, metric), _units(base_rows, metric)
                    both = a.index.intersection(b.index)
                    if both.empty:
                        continue
                    d = (a.loc[both] - b.loc[both]).to_numpy(dtype=np.float64)
                    e = estimate_units(both.to_numpy(dtype=np.int64), d)
                    out.append({"method": method, "setting": setting, "split": split, "terrain": terrain,
                                "metric": metric, "n": int(both.size), "default": float(b.loc[both].mean()),
                                "value": float(a.loc[both].mean()), "difference": e.mean, "lo": e.lo, "hi": e.hi})
    return pd.DataFrame(out, columns=ARM_COLUMNS)


def _verdict(lo: float, hi: float) -> str:
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "no interval"
    if lo > 0:
        return "higher"
    if hi < 0:
        return "lower"
    return "cannot tell"


def arms_section(diffs: pd.DataFrame, default: str = "default") -> list[str]:
    """The report's "Arms against the default" section (empty when no method ran a setting
    besides its default)."""
    if diffs.empty:
        return []
    out = ["## Arms against the default", "",
           f"Each setting's final-point return minus the `{default}` setting's, paired unit by unit (the same RL seed "
           "on the same recognizer, so the same contexts and starts): the mean difference and its 95 % interval "
           "(Student t over the paired seeds with one recognizer; the two-stage bootstrap over recognizers, then "
           "seeds, with several). A difference is *higher* or *lower* when its whole interval lies on that side of "
           "zero. The components each setting ran are listed under Setup (and in `ablation.json`).", ""]
    for method in dict.fromkeys(diffs["method"]):
        sel = diffs[(diffs["method"] == method) & (diffs["metric"] == "return")]
        rows = []
        for r in sel.itertuples():
            where = r.split if r.terrain == "all" else f"{r.split}, {r.terrain}"
            rows.append([f"`{r.setting}`", where, str(r.n), f"{r.default:.3f}", f"{r.value:.3f}",
                         f"{r.difference:+.3f} [{r.lo:+.3f}, {r.hi:+.3f}]" if np.isfinite(r.lo)
                         else f"{r.difference:+.3f}", _verdict(r.lo, r.hi)])
        out += [f"**{label(method)}**", ""]
        out += md_table(["setting", "split", "paired runs", "default", "setting", "difference [95 % CI]", "verdict"],
                        rows) + [""]
    out += ["All metrics: [`arms.csv`](arms.csv).", ""]
    return out


def arm_label(key: str) -> str:
    """"IBE-MAP" for "ibe_map", "IBE-MAP at `perception.encoder=resnet18`" for ``"ibe_map @ <setting>"``."""
    method, _, setting = key.partition(" @ ")
    return label(method) + (f" at `{setting}`" if setting else "")


def write_arms(final: pd.DataFrame, contexts: pd.DataFrame, out_dir: Path, default: str) -> list[str]:
    """Write ``out_dir/arms.csv`` (:func:`paired_differences` of :data:`ARM_METRICS`) and return
    the report's section; nothing when no method ran a setting besides its default."""
    diffs = paired_differences(final, contexts, ARM_METRICS)
    if not diffs.empty:
        atomic_write(out_dir / "arms.csv", diffs.to_csv(index=False, float_format="%.6g"))
    return arms_section(diffs, default)

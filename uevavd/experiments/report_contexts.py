"""The number of training contexts as an axis of the report (``uevavd ablate --sweep
env.train_per_block=4,10,20``): a table and a figure of test return, recognition, path and
GenGap against it, per method, beside passive and the oracles, with the report's intervals.

Every setting of the axis is evaluated on the same test contexts (the ablation's world holds
all of them, :func:`uevavd.experiments.plan.with_context_axis`), and each run's "train" split
is its own training contexts, so GenGap is train minus test of the same run. The x value of
a setting is the number of training contexts its learned runs were evaluated on (the
``eval_contexts`` of their final train rows), not a name parsed from the setting.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from .figures import figure_lines, plot_context_axis
from .plan import CONTEXTS_KEY
from .report_data import (
    default_setting,
    deterministic,
    estimate,
    gengap_estimate,
    is_baseline,
    label,
    md_table,
    order_methods,
)
from .stats import Estimate

#: Columns of the table: (split, metric, header, digits); split None: GenGap train - hard.
COLUMNS: tuple[tuple[str | None, str, str, int], ...] = (
    ("train", "return", "train return", 3),
    ("simple", "return", "simple return", 3),
    ("hard", "return", "hard return", 3),
    ("hard", "recognition", "hard recognition", 3),
    ("hard", "path_m", "hard path (m)", 1),
    (None, "return", "GenGap (train − hard)", 3),
)


def context_axis(final: pd.DataFrame) -> pd.DataFrame:
    """Final rows of the default setting and the ``env.train_per_block=...`` settings, with a
    column ``contexts`` (training contexts of the setting's runs); empty when the axis was
    not swept. Baselines get the count of the learned runs of their setting."""
    named = final["setting"].str.replace(" ", "").str.startswith(f"{CONTEXTS_KEY}=")
    if not named.any() or "eval_contexts" not in final:
        return final.iloc[0:0]
    sel = final[named | (final["setting"] == default_setting(final))]
    train = sel[~is_baseline(sel) & (sel["split"] == "train")]
    count = train.groupby("setting")["eval_contexts"].max()
    sel = sel.assign(contexts=sel["setting"].map(count))
    return sel[sel["contexts"].notna()].astype({"contexts": np.int64})


def _estimate(axis: pd.DataFrame, method: str, split: str | None, metric: str, setting: str) -> Estimate:
    if split is None:
        return gengap_estimate(axis, method, setting, "hard")
    return estimate(axis, method, split, metric, setting)


def _cell(e: Estimate, digits: int) -> str:
    if e.n == 0:
        return "–"
    if e.n == 1 or not math.isfinite(e.lo):
        return f"{e.mean:.{digits}f}"
    return f"{e.mean:.{digits}f} [{e.lo:.{digits}f}, {e.hi:.{digits}f}]"


def context_table(axis: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, contexts): ``n`` runs and per column of :data:`COLUMNS` its
    mean, lo and hi (the report's interval; exact for a deterministic baseline)."""
    rows = []
    settings = axis.drop_duplicates("setting").set_index("setting")["contexts"].sort_values()
    for m in order_methods(axis["method"].unique()):
        for setting, n_ctx in settings.items():
            mine = axis[(axis["method"] == m) & (axis["setting"] == setting)]
            if mine.empty:
                continue
            row = {"method": m, "contexts": int(n_ctx), "setting": setting, "n": int(mine["seed"].nunique())}
            for split, metric, header, _ in COLUMNS:
                e = _estimate(axis, m, split, metric, setting)
                row.update({header: e.mean, f"{header} lo": e.lo, f"{header} hi": e.hi})
            rows.append(row)
    return pd.DataFrame(rows)


def contexts_section(final: pd.DataFrame, out_dir: Path, *, figures: bool = True) -> list[str]:
    """The report's section on the number of training contexts (and its figure unless
    ``figures=False``), or nothing when the ablation did not sweep it."""
    axis = context_axis(final)
    if axis.empty:
        return []
    table = context_table(axis)
    fixed = set(deterministic())
    out = ["## Test return against the number of training contexts", "",
           f"`{CONTEXTS_KEY}` training contexts per target block; every setting evaluated on the same simple "
           "and hard test contexts, and on its own training contexts (GenGap is train minus hard of the same "
           "run). Mean and 95% interval as in the results tables" + (
               "; passive and the oracles are exact per recognizer" if fixed else "") + ".", ""]
    out += figure_lines(out_dir / "fig_contexts.png", "Test return against the number of training contexts",
                        lambda path: plot_context_axis(table, path), draw=figures)
    rows = []
    for _, r in table.iterrows():
        cells = []
        for _, _, header, digits in COLUMNS:
            e = Estimate(r[header], math.nan, int(r["n"]), r[f"{header} lo"], r[f"{header} hi"])
            cells.append(_cell(e, digits) if math.isfinite(e.mean) else "–")
        rows.append([label(r["method"]), str(r["contexts"]), str(r["n"]), *cells])
    out += md_table(["Policy", "training contexts", "runs", *[c[2] for c in COLUMNS]], rows) + [""]
    return out

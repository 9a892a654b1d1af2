"""The stopping diagnosis as a section of the report: where the target's box is in view at the
start, does a learned policy fly away from it, and what the same policy returns behind the stop
gate ("stop wherever the box is non-empty"), per split and, on the hard split, per terrain.

It reads the optional columns :data:`~uevavd.experiments.report_data.STOPPING` of
``results.csv`` (the runs' final evaluations) and of ``contexts.csv`` (per context, for the
terrains); ablations written before those columns existed get no section.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from .report_data import (
    SPLITS,
    STOPPING,
    baselines,
    estimate,
    is_baseline,
    label,
    learned,
    md_table,
    order_methods,
)
from .stats import Estimate

#: The rows besides the learned methods: what the gate is measured against.
REFERENCES = ("passive", "box_gate")


def _cell(e: Estimate, digits: int = 3) -> str:
    if e.n == 0 or not math.isfinite(e.mean):
        return "–"
    if e.n == 1 or not math.isfinite(e.lo):
        return f"{e.mean:.{digits}f}"
    return f"{e.mean:.{digits}f} [{e.lo:.{digits}f}, {e.hi:.{digits}f}]"


def _share(x: float) -> str:
    return "–" if not math.isfinite(x) else f"{x:.0%}"


def terrain_rows(contexts: pd.DataFrame, setting: str, split: str = "hard") -> pd.DataFrame:
    """Per (method, terrain) on ``split``: the means over runs and contexts of return,
    gated_return and path_m, box_start, box_lost, and moved_if_box weighted by each context's
    box starts (so it is the share over all box starts of the terrain)."""
    sel = contexts[(contexts["setting"] == setting) & (contexts["split"] == split)]
    if sel.empty or "terrain" not in sel or not set(STOPPING) <= set(sel.columns):
        return pd.DataFrame()
    sel = sel.assign(terrain=sel["terrain"].fillna("").astype(str),
                     moved_n=sel["box_start"] * sel["moved_if_box"].fillna(0.0))
    rows = []
    for (m, terrain), g in sel.groupby(["method", "terrain"], sort=False):
        box = float(g["box_start"].sum())
        rows.append({"method": m, "terrain": terrain or "(unrecorded)", "contexts": int(g["context"].nunique()),
                     "return": float(g["return"].mean()), "gated_return": float(g["gated_return"].mean()),
                     "path_m": float(g["path_m"].mean()), "box_start": float(g["box_start"].mean()),
                     "moved_if_box": float(g["moved_n"].sum()) / box if box > 0 else math.nan,
                     "box_lost": float(g["box_lost"].mean())})
    return pd.DataFrame(rows)


def stopping_section(final: pd.DataFrame, setting: str, ablation_dir: Path) -> list[str]:
    """The report's section on stopping, or nothing for results without the diagnosis."""
    if not set(STOPPING) <= set(final.columns):
        return []
    runs = final[~is_baseline(final) & (final["setting"] == setting)]
    methods = learned(runs["method"].unique())
    if not methods or runs["box_start"].isna().all():
        return []
    present = set(final.loc[final["setting"] == setting, "split"])
    splits = [s for s in SPLITS if s in present]
    refs = [m for m in REFERENCES if m in set(final["method"])]
    out = ["## Stopping: does the policy fly away from a view where the target is in view?", "",
           "From every start view of every context: *box starts*, the share of starts whose observed target box "
           "is non-empty; *moves*, of those, the share where the policy's first decision is a move; *lost*, the "
           "share of all episodes that start with the box in view, move, and end unrecognised; *gated*, the same "
           "policy behind the stop gate (stop wherever the observed box is non-empty, else its own action). "
           "Return and gated return: mean and 95 % interval over runs; the gated minus ungated difference is "
           "paired by run.", ""]
    rows = []
    for split in splits:
        for m in [*refs, *methods]:
            ret = estimate(final, m, split, "return", setting)
            if ret.n == 0:
                continue
            box = estimate(final, m, split, "box_start", setting).mean
            moves = estimate(final, m, split, "moved_if_box", setting).mean
            lost = estimate(final, m, split, "box_lost", setting).mean
            if m in baselines():
                rows.append([split, label(m), _share(box), _share(moves), _share(lost), _cell(ret), "", ""])
                continue
            gated = estimate(final, m, split, "gated_return", setting)
            rows.append([split, label(m), _share(box), _share(moves), _share(lost), _cell(ret), _cell(gated),
                         _cell(_paired(final, m, split, setting))])
    out += md_table(["split", "policy", "box starts", "moves", "lost", "return", "gated return",
                     "gated minus return"], rows) + [""]
    ctx_path = ablation_dir / "contexts.csv"
    if ctx_path.is_file():
        try:
            contexts = pd.read_csv(ctx_path, dtype={"setting": str, "method": str, "split": str})
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, OSError):
            contexts = pd.DataFrame()
        terr = terrain_rows(contexts, setting) if not contexts.empty else pd.DataFrame()
        if not terr.empty:
            out += ["Hard split per terrain (means over runs and contexts):", ""]
            rank = {m: i for i, m in enumerate(order_methods(terr["method"].unique()))}
            terr = terr[terr["method"].isin([*refs, *methods])]
            trows = []
            for _, r in terr.sort_values(["terrain", "method"], key=lambda c: c.map(rank) if c.name == "method"
                                         else c).iterrows():
                gated = "" if r["method"] in baselines() else f"{r['gated_return']:.3f}"
                trows.append([r["terrain"], label(r["method"]), str(r["contexts"]), _share(r["box_start"]),
                              _share(r["moved_if_box"]), _share(r["box_lost"]), f"{r['return']:.3f}", gated,
                              f"{r['path_m']:.1f}"])
            out += md_table(["terrain", "policy", "contexts", "box starts", "moves", "lost", "return",
                             "gated return", "path (m)"], trows) + [""]
    return out


def _paired(final: pd.DataFrame, method: str, split: str, setting: str) -> Estimate:
    """Gated minus ungated return of ``method``, paired by run: the interval of the per-run
    differences (the report's estimate over units)."""
    sel = final[(final["method"] == method) & (final["split"] == split) & (final["setting"] == setting)]
    diff = sel.assign(d=sel["gated_return"] - sel["return"])
    diff = diff.assign(method="__paired__", **{"return": diff["d"]})
    return estimate(diff, "__paired__", split, "return", setting)


__all__ = ["stopping_section", "terrain_rows"]

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

import numpy as np
import pandas as pd

from .report_data import (
    SPLITS,
    STOPPING,
    UNIT,
    baselines,
    estimate,
    estimate_units,
    is_baseline,
    label,
    learned,
    md_table,
    order_methods,
)
from .stats import Estimate, difference

#: The rows besides the learned methods: what the gate is measured against.
REFERENCES = ("passive", "box_gate", "pose_seek")


def _cell(e: Estimate, digits: int = 3) -> str:
    if e.n == 0 or not math.isfinite(e.mean):
        return "–"
    if e.n == 1 or not math.isfinite(e.lo):
        return f"{e.mean:.{digits}f}"
    return f"{e.mean:.{digits}f} [{e.lo:.{digits}f}, {e.hi:.{digits}f}]"


def _diff_cell(d: Estimate, digits: int = 3) -> str:
    """A difference with its sign, and its interval where one exists."""
    if d.n == 0 or not math.isfinite(d.mean):
        return "–"
    if not (math.isfinite(d.lo) and math.isfinite(d.hi)):
        return f"{d.mean:+.{digits}f}"
    return f"{d.mean:+.{digits}f} [{d.lo:+.{digits}f}, {d.hi:+.{digits}f}]"


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
    """The report's section on stopping, or one line saying why it is not there."""
    title = "## Stopping: does the policy fly away from a view where the target is in view?"
    missing = [c for c in STOPPING if c not in final.columns]
    if missing:
        return [title, "", f"Not written: results.csv has no column(s) {missing} (results of an earlier version; "
                           "rerun its `uevavd ablate` to evaluate them).", ""]
    runs = final[~is_baseline(final) & (final["setting"] == setting)]
    methods = learned(runs["method"].unique())
    if not methods:
        return []
    if runs["box_start"].isna().all():
        return [title, "", "Not written: the learned runs' box_start is empty in results.csv (results of an earlier "
                           "version; rerun its `uevavd ablate` to evaluate them).", ""]
    present = set(final.loc[final["setting"] == setting, "split"])
    splits = [s for s in SPLITS if s in present]
    refs = [m for m in REFERENCES if m in set(final["method"])]
    out = [title, "",
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
                         _diff_cell(_paired(final, m, split, setting))])
    out += md_table(["split", "policy", "box starts", "moves", "lost", "return", "gated return",
                     "gated minus return"], rows) + [""]
    contexts = read_contexts(ablation_dir / "contexts.csv")
    by_terrain = terrain_final(contexts, setting)
    out += _against_section(final, by_terrain, setting, methods, splits)
    if not contexts.empty:
        terr = terrain_rows(contexts, setting)
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


#: What each learned method is compared with, paired as the report pairs runs.
AGAINST = (("ibe_map", "IBE-MAP"), ("passive", "passive"), ("box_gate", "box gate"), ("pose_seek", "pose rule"))


def read_contexts(path: Path) -> pd.DataFrame:
    if not path.is_file():
        return pd.DataFrame()
    try:
        return pd.read_csv(path, dtype={"setting": str, "method": str, "split": str, "terrain": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, OSError):
        return pd.DataFrame()


def terrain_final(contexts: pd.DataFrame, setting: str, split: str = "hard") -> pd.DataFrame:
    """Final rows per terrain, as :func:`~uevavd.experiments.report_data.final_rows` has them per
    split: one row per (method, run, terrain) of ``split`` with the mean return over the
    terrain's contexts, the terrain in column ``split`` (so the report's estimates apply)."""
    need = {"method", "recognizer", "seed", "setting", "split", "terrain", "return"}
    if contexts.empty or not need <= set(contexts.columns):
        return pd.DataFrame()
    sel = contexts[(contexts["setting"] == setting) & (contexts["split"] == split)]
    sel = sel.assign(terrain=sel["terrain"].fillna("").astype(str).replace("", "(unrecorded)"))
    rows = sel.groupby(["method", "recognizer", "seed", "terrain"], as_index=False)["return"].mean()
    rows["seed"] = rows["recognizer"].astype(np.int64) * UNIT + rows["seed"].astype(np.int64)
    return rows.rename(columns={"terrain": "split"}).assign(setting=setting)


def _against_section(final: pd.DataFrame, by_terrain: pd.DataFrame, setting: str, methods: list[str],
                     splits: list[str]) -> list[str]:
    """Each learned method's return minus IBE-MAP's, passive's and the box gate's, per split and,
    on the hard split, per terrain: the report's intervals, paired by recognizer draws."""
    refs = [(r, name) for r, name in AGAINST if r in set(final["method"])]
    groups = [(split, final) for split in splits]
    if not by_terrain.empty:
        groups += [(f"hard, {t}", by_terrain.replace({"split": {t: f"hard, {t}"}}))
                   for t in sorted(by_terrain["split"].unique())]
    rows = []
    for where, frame in groups:
        for m in methods:
            e = estimate(frame, m, where, "return", setting)
            if e.n == 0:
                continue
            cells = [_diff_cell(difference(e, estimate(frame, r, where, "return", setting)))
                     if r != m and estimate(frame, r, where, "return", setting).n else "" for r, _ in refs]
            rows.append([where, label(m), _cell(e), *cells])
    if not rows or not refs:
        return []
    return ["Each learned method's return minus each reference's (95 % interval of the difference as the "
            "report computes it: with several recognizers the two-stage bootstrap, paired by its draws; with one, "
            "Welch's t; per terrain from the runs' means over the terrain's hard contexts):", "",
            *md_table(["split", "policy", "return", *[f"minus {name}" for _, name in refs]], rows), ""]


def _paired(final: pd.DataFrame, method: str, split: str, setting: str) -> Estimate:
    """Gated minus ungated return of ``method``, paired by run: the report's estimate over the
    runs' differences."""
    sel = final[(final["method"] == method) & (final["split"] == split) & (final["setting"] == setting)]
    sel = sel.sort_values("seed")
    return estimate_units(sel["seed"].to_numpy(), (sel["gated_return"] - sel["return"]).to_numpy(dtype=float))


__all__ = ["read_contexts", "stopping_section", "terrain_rows"]

"""The report's room table: where the visibility oracle's gain over passive lies (starts with the
target's box in view, and starts without), and the share of it each policy takes.

It reads the optional columns :data:`~uevavd.experiments.report_data.ROOM` (and ``box_start``)
of ``results.csv`` and, for the hard split per terrain, ``contexts.csv``; results without them
get no section.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from .report_data import DEPARTURE_CEILINGS, ROOM, SPLITS, estimate, is_baseline, label, learned, md_table
from .report_stopping import read_contexts

#: The two references the room lies between, and the scripted rules shown beside the learned methods
#: (the rule's departure ceilings, where evaluated, stand beside the visibility oracle).
FLOOR, CEILING = "passive", "visibility_oracle"
SCRIPTED = ("box_gate", "pose_seek")
KINDS = (("box_return", "box in view"), ("hidden_return", "box hidden"))


def _share(value: float, floor: float, ceiling: float) -> str:
    room = ceiling - floor
    if not all(math.isfinite(x) for x in (value, floor, ceiling)) or abs(room) < 1e-9:
        return "–"
    return f"{(value - floor) / room:+.0%}"


def terrain_room(contexts: pd.DataFrame, setting: str, split: str = "hard") -> pd.DataFrame:
    """Per (method, terrain) of ``split``: the share of starts with the box in view and the mean
    return of each kind of start, over runs and contexts, each context weighted by its starts of
    that kind (so it is the mean over the terrain's starts of that kind)."""
    need = {"method", "setting", "split", "terrain", "box_start", *ROOM}
    if contexts.empty or not need <= set(contexts.columns):
        return pd.DataFrame()
    sel = contexts[(contexts["setting"] == setting) & (contexts["split"] == split)]
    sel = sel.assign(terrain=sel["terrain"].fillna("").astype(str).replace("", "(unrecorded)"))
    rows = []
    for (m, terrain), g in sel.groupby(["method", "terrain"], sort=False):
        w_box, w_hidden = g["box_start"].to_numpy(float), 1.0 - g["box_start"].to_numpy(float)
        row = {"method": m, "where": f"hard, {terrain}", "box_start": float(np.mean(w_box))}
        for col, w in (("box_return", w_box), ("hidden_return", w_hidden)):
            v = g[col].to_numpy(float)
            ok = np.isfinite(v) & (w > 0)
            row[col] = float(np.sum(v[ok] * w[ok]) / np.sum(w[ok])) if ok.any() else math.nan
        rows.append(row)
    return pd.DataFrame(rows)


def room_section(final: pd.DataFrame, setting: str, ablation_dir: Path) -> list[str]:
    """The report's room table, or nothing for results without the columns or the two references."""
    if not {*ROOM, "box_start"} <= set(final.columns):
        return []
    present = set(final.loc[final["setting"] == setting, "method"])
    if not {FLOOR, CEILING} <= present or final.loc[final["method"] == CEILING, "hidden_return"].isna().all():
        return []
    beside = [m for m in DEPARTURE_CEILINGS if m in present]
    methods = [*(m for m in SCRIPTED if m in present),
               *learned(final.loc[~is_baseline(final) & (final["setting"] == setting), "method"].unique())]
    means = []
    for split in [s for s in SPLITS if s in set(final.loc[final["setting"] == setting, "split"])]:
        for m in (FLOOR, CEILING, *beside, *methods):
            if estimate(final, m, split, "return", setting).n:
                means.append({"method": m, "where": split, **{c: estimate(final, m, split, c, setting).mean
                                                             for c in ("box_start", *ROOM)}})
    frame = pd.concat([pd.DataFrame(means), terrain_room(read_contexts(ablation_dir / "contexts.csv"), setting)],
                      ignore_index=True)
    rows = []
    for where, g in frame.groupby("where", sort=False):
        by = g.set_index("method")
        if FLOOR not in by.index or CEILING not in by.index:
            continue
        share_box = float(by.loc[FLOOR, "box_start"])
        for col, kind in KINDS:
            floor, ceiling = float(by.loc[FLOOR, col]), float(by.loc[CEILING, col])
            if not (math.isfinite(floor) and math.isfinite(ceiling)):
                continue
            starts = share_box if col == "box_return" else 1.0 - share_box
            cells = [f"{float(by.loc[m, col]):.3f} ({_share(float(by.loc[m, col]), floor, ceiling)})"
                     if m in by.index and math.isfinite(float(by.loc[m, col])) else "–" for m in (*beside, *methods)]
            rows.append([where, kind, f"{starts:.0%}", f"{floor:.3f}", f"{ceiling:.3f}", f"{ceiling - floor:+.3f}",
                         *cells])
    if not rows:
        return []
    return ["## Where the room is: starts with the target's box in view, and without", "",
            "Per split and, on the hard split, per terrain: the share of starts of each kind, passive's and the "
            "visibility oracle's mean return there, the oracle's gain over passive (the room), and each policy's "
            "mean return with the share of the room it takes ((return - passive) / room; means over runs and "
            "contexts)." + (" Beside the room, the privileged ceilings of a method anchored to the pose rule: the "
                            "rule departed from at most once or twice with each context's exact values (a "
                            "share above 100 % is room the visibility oracle does not see)." if beside else ""), "",
            *md_table(["where", "starts", "share", "passive", "visibility oracle", "room",
                       *[label(m) for m in (*beside, *methods)]], rows), ""]


__all__ = ["room_section", "terrain_room"]

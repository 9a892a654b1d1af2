"""Visibility statistics of a world, per split and terrain: what ``uevavd synth`` prints and
``benchmarks/synthetic_quality.py`` reports.

A context's statistics come from the visible fraction of each of its 605 views (target
pixels seen / target pixels with every occluder removed), read from ``scene.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..layout import SCENE_META
from ..splits import SPLITS, split_of
from .world import VALIDITY, terrain_of


def view_stats(visible: np.ndarray) -> dict[str, float]:
    """mean visible fraction and the shares of views with visible >= 0.9 (clear), < 0.5
    (mostly hidden) and == 0 (fully occluded) of an array of visible fractions."""
    v = np.asarray(visible, np.float64)
    return {"mean": float(v.mean()), "clear": float(np.mean(v >= VALIDITY.clear_at)),
            "hidden": float(np.mean(v < 0.5)), "occluded": float(np.mean(v == 0))}


def read_visible(root: str | Path) -> dict[int, np.ndarray]:
    """``{context id: (605,) float64 visible fractions}`` of every context folder of a
    synthetic world (from its ``scene.json``)."""
    out = {}
    for meta_path in sorted(Path(root).glob(f"[0-9][0-9][0-9]/{SCENE_META}")):
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        if meta.get("context") is not None:
            out[int(meta["context"])] = np.array(list(meta["visible"].values()), np.float64)
    return out


def split_rows(visible: Mapping[int, np.ndarray]) -> list[dict]:
    """One row per (split, terrain, placement) present, then one per split: contexts, views,
    the :func:`view_stats`, the lowest per-context clear share and how many contexts pass
    the validity rule."""
    rows = []
    for split in SPLITS:
        cs = sorted(c for c in visible if split_of(c) == split)
        groups = sorted({terrain_of(c) for c in cs})
        keys = [(g, [c for c in cs if terrain_of(c) == g]) for g in groups] if len(groups) > 1 else []
        keys.append((("all", ""), cs))
        for (terrain, placement), members in keys:
            if not members:
                continue
            v = np.concatenate([visible[c] for c in members])
            clear = [view_stats(visible[c])["clear"] for c in members]  # the same comparison as the rows
            rows.append({"split": split, "terrain": terrain if terrain == "all" else f"{terrain} ({placement})",
                         "contexts": len(members), "views": len(v), **view_stats(v),
                         "min_clear": min(clear), "valid": sum(VALIDITY.passes(visible[c]) for c in members)})
    return rows


def format_rows(rows: list[dict]) -> str:
    """The rows of :func:`split_rows` as a Markdown table."""
    lines = ["| split | terrain | contexts | mean visible | visible >= 0.9 | < 0.5 | = 0 | lowest context >= 0.9 "
             "| pass the rule |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['split']} | {r['terrain']} | {r['contexts']} | {r['mean']:.3f} | {r['clear']:.1%} | "
                     f"{r['hidden']:.1%} | {r['occluded']:.1%} | {r['min_clear']:.1%} | "
                     f"{r['valid']}/{r['contexts']} |")
    return "\n".join(lines)

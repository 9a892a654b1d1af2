"""The recognizer audit: how well each recognizer sees the target before any policy moves.

From an observation table alone (its classifier probabilities on the raw views, the true
targets and the visible fractions): per split and per context, the accuracy (argmax == true
class) on clear views (visible >= 0.9), and per split the accuracy in bins of the visible
fraction. Written by the ablation as ``recognizer_audit.json`` and shown by the report before
any RL result: a policy cannot recognise what the recognizer cannot, so a split where the
recognizer fails on clear views says nothing about active viewing.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..perception.classifier import read_classifier_file
from ..table import load_table
from .report_data import md_table as _table

#: Visible fraction at or above which a view counts as clear (the world's validity rule's).
CLEAR_AT = 0.9
BINS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0001)


def audit_table(table, terrains: Mapping[int, str] | None = None) -> dict[str, Any]:
    """``{split: {"clear_views", "clear_accuracy", "accuracy", "contexts": [...],
    "by_visible": [...]}}`` of an :class:`~uevavd.table.ObservationTable`
    (or its folder). Splits without visible fractions report accuracy only."""
    tbl = load_table(table)
    pred = tbl.probs.argmax(-1)  # (S, V)
    correct = pred == np.asarray(tbl.targets)[:, None]
    vis = np.asarray(tbl.visible, np.float64)
    out: dict[str, Any] = {}
    for split in ("train", "simple", "hard"):
        idx = tbl.scene_indices(split)
        if not len(idx):
            continue
        c, v = correct[idx], vis[idx]
        clear = v >= CLEAR_AT
        contexts = []
        for k, s in enumerate(idx):
            n = int(clear[k].sum())
            contexts.append({"context": int(tbl.contexts[s]), "terrain": (terrains or {}).get(int(tbl.contexts[s]), ""),
                             "clear_views": n, "clear_accuracy": float(c[k][clear[k]].mean()) if n else None,
                             "accuracy": float(c[k].mean())})
        bins = []
        for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
            m = (v >= lo) & (v < hi)
            bins.append({"lo": lo, "hi": min(hi, 1.0), "views": int(m.sum()),
                         "accuracy": float(c[m].mean()) if m.any() else None})
        out[split] = {"clear_views": int(clear.sum()), "accuracy": float(c.mean()),
                      "clear_accuracy": float(c[clear].mean()) if clear.any() else None,
                      "contexts": contexts, "by_visible": bins}
    return out


def classifier_summary(path: str | Path) -> dict[str, Any]:
    """Architecture, initialisation, epochs and held-out (train_605 viewpoints) accuracy of a
    classifier file."""
    _, meta = read_classifier_file(path)
    train = meta.get("train", {})
    settings = train.get("settings", {})
    return {"file": str(path), "arch": meta.get("arch"), "init": train.get("init"),
            "epochs": settings.get("epochs"), "seed": settings.get("seed"),
            "input_size": meta.get("input_size"), "val_accuracy": train.get("val_accuracy")}


def _pct(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def audit_markdown(audit: Mapping[str, Any]) -> list[str]:
    """Report lines for ``recognizer_audit.json`` (one entry per recognizer)."""
    out = ["## Recognizer audit", "",
           "Before any policy moves: each recognizer's accuracy (argmax == true class) on the raw views of the "
           f"table, on clear views (visible fraction >= {CLEAR_AT}) per split and per context, and against the "
           "visible fraction. The recognizers are trained on `train_605` only, so every context view is held out; "
           "the training contexts' clear views are the data the quick preset's recipe was chosen on.", ""]
    recs = sorted(audit, key=int)
    rows = []
    for r in recs:
        a = audit[r]
        clf = a.get("classifier", {})
        cells = [str(r), f"{clf.get('arch')} ({clf.get('init')}, {clf.get('epochs')} epochs)",
                 _pct(clf.get("val_accuracy"))]
        for split in ("train", "simple", "hard"):
            s = a["splits"].get(split)
            cells.append("-" if s is None else f"{_pct(s['clear_accuracy'])} ({s['clear_views']})")
        rows.append(cells)
    out += _table(["recognizer", "network", "held-out train_605", "train: clear acc. (views)", "simple", "hard"], rows)
    out += ["", "Per context, clear-view accuracy (clear views):", ""]
    first = audit[recs[0]]["splits"]
    header = ["split", "context", "terrain", *[f"recognizer {r}" for r in recs]]
    rows = []
    for split, s in first.items():
        for k, ctx in enumerate(s["contexts"]):
            cells = [split, f"{ctx['context']:03d}", ctx.get("terrain") or ""]
            for r in recs:
                c = audit[r]["splits"][split]["contexts"][k]
                cells.append(f"{_pct(c['clear_accuracy'])} ({c['clear_views']})")
            rows.append(cells)
    out += _table(header, rows)
    out += ["", "Accuracy against the visible fraction (all views of the split; recognizer "
            f"{recs[0]}):", ""]
    rows = []
    for split, s in first.items():
        rows.append([split] + [f"{_pct(b['accuracy'])} ({b['views']})" for b in s["by_visible"]])
    out += _table(["split", *[f"{b['lo']:.1f}-{b['hi']:.1f}" for b in first[next(iter(first))]["by_visible"]]], rows)
    out.append("")
    return out



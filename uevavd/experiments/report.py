"""The ablation report: ``DIR/report/report.md`` (+ PNGs and ``summary.csv``) written
from the files of an ablation directory alone, so it can be regenerated any time
(``uevavd report DIR``).

Inputs (written by the ablation runner):

* ``DIR/results.csv``: one row per method x seed x setting x evaluation point x split
  (:data:`uevavd.experiments.report_data.REQUIRED_COLUMNS`); required.
* ``DIR/trajectories.json``: greedy episodes of the final policies from one start in a
  hard-test context (Fig. 8); optional.
* ``DIR/ablation.json``: preset, methods, seeds, sweeps, data_root, stage timings;
  optional (the setup section says what is missing).

Outputs in ``DIR/report/``: ``report.md`` (GitHub-readable, relative image links),
``fig9_curves.png``, ``fig8_strips.png``, ``summary.csv``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from ..atomic import atomic_write, folder_lock, remove_temporaries
from .arms import arm_label, write_arms
from .audit import audit_markdown
from .claims import Claim, check_claims, diagnose
from .figures import figure_lines, plot_curves, plot_strips
from .io import ABLATION_FILE, ablation_folder, check_outputs, read_ablation_meta
from .report_contexts import contexts_section
from .report_data import (
    DEFAULT_C,
    DEFAULT_THRE,
    METRICS,
    SPLITS,
    baselines,
    curve_rows,
    default_setting,
    deterministic,
    estimate,
    estimate_units,
    final_rows,
    gengap_estimate,
    is_baseline,
    label,
    learned,
    load_results,
    md_table,
    order_methods,
    recorded_roles,
    sweep_methods,
    sweep_rows,
)
from .report_rliable import rliable_section
from .report_room import room_section
from .report_stopping import read_contexts, stopping_section
from .stats import Estimate
from .strips import load_trajectories, strip_images

__all__ = ["Claim", "check_claims", "write_report", "summary_table"]

REPORT_DIR = "report"
#: Metrics of the results table: (column, header, digits).
TABLE_METRICS: tuple[tuple[str, str, int], ...] = (
    ("return", "Return", 3),
    ("accuracy", "Accuracy", 3),
    ("recognition", "Recognition", 3),
    ("path_m", "Path (m)", 1),
    ("path_steps", "Path (steps)", 2),
    ("steps", "Decisions", 2),
)


def _read_json(path: Path, notes: list[str]):
    if not path.is_file():
        notes.append(f"`{path.name}` not found in the ablation directory.")
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except ValueError as e:
        raise ValueError(f"{path}: not valid JSON ({e}); expected the file the ablation runner writes") from None


def _cell(e: Estimate, digits: int) -> str:
    if e.n == 0:
        return "–"
    if not math.isfinite(e.std):
        return f"{e.mean:.{digits}f} (n=1)"
    if e.n == 1:  # an exact (deterministic) value
        return f"{e.mean:.{digits}f}"
    return f"{e.mean:.{digits}f} ± {e.std:.{digits}f}<br>[{e.lo:.{digits}f}, {e.hi:.{digits}f}]"


def summary_table(final: pd.DataFrame) -> pd.DataFrame:
    """The final-point table of every method x setting x split: ``n`` seeds, and per
    metric ``<m>_mean``, ``<m>_std``, ``<m>_ci_lo``, ``<m>_ci_hi`` (95% t-interval;
    exact for deterministic baselines), plus ``episodes`` (max over seeds)."""
    default = default_setting(final)
    rank = {m: i for i, m in enumerate(order_methods(final["method"].unique()))}
    rows, fixed = [], deterministic()
    for (setting, m, split), sel in final.groupby(["setting", "method", "split"], sort=False):
        row = {"setting": setting, "method": m, "split": split, "thre": float(sel["thre"].iloc[0]),
               "C": float(sel["C"].iloc[0]), "n": int(sel["seed"].nunique()), "episodes": int(sel["episodes"].max())}
        for metric in METRICS:
            sel = sel.sort_values("seed")
            e = estimate_units(sel["seed"].to_numpy(), sel[metric].to_numpy(dtype=np.float64), m in fixed)
            row.update({f"{metric}_mean": e.mean, f"{metric}_std": e.std,
                        f"{metric}_ci_lo": e.lo, f"{metric}_ci_hi": e.hi})
        rows.append(row)
    out = pd.DataFrame(rows)
    if out.empty:
        return out
    key = [(s != default, s, rank[m], SPLITS.index(sp)) for s, m, sp in out[["setting", "method", "split"]].to_numpy()]
    return out.iloc[sorted(range(len(out)), key=key.__getitem__)].reset_index(drop=True)


def _setup_section(meta: dict | None, results: pd.DataFrame, final: pd.DataFrame, notes: list[str]) -> list[str]:
    out = ["## Setup", ""]
    meta = meta or {}
    methods = learned(results["method"].unique())
    absent = [m for m in (meta.get("methods") or []) if m not in methods]
    if absent:
        notes.append(f"ablation.json lists {', '.join(label(m) for m in absent)} but results.csv has no rows for "
                     "them (the run was interrupted or is still going).")
    # ablation.json may list the seeds or give their number; the results say which ran
    runs_all = results.loc[~is_baseline(results)]
    seeds = sorted(runs_all["rl_seed"].unique().tolist())
    if isinstance(meta.get("seeds"), list) and meta["seeds"]:
        seeds = list(meta["seeds"])
    recognizers = sorted(results["recognizer"].unique().tolist())
    runs = final[~is_baseline(final)]
    episodes = sorted(runs["episodes"].unique().tolist())
    out += [
        f"- Preset: `{meta.get('preset', 'unknown')}`",
        f"- Methods: {', '.join(label(m) for m in methods)}; references: "
        f"{', '.join(label(m) for m in baselines() if m in set(results['method']))}",
        f"- Seeds: {', '.join(str(s) for s in seeds)} ({len(seeds)}) on each of {len(recognizers)} recognizer(s) "
        f"({', '.join(str(r) for r in recognizers)}): {len(seeds) * len(recognizers)} runs per method and setting",
        *[f"- Perception of {arm_label(m)}: {v}" if m.split(" @ ")[0] in set(methods) else f"- {m.capitalize()}: {v}"
          for m, v in (meta.get("perception") or {}).items()],
        f"- Sweeps: {json.dumps(meta.get('sweeps', {}))}; default thre = {DEFAULT_THRE}, C = {DEFAULT_C}",
        f"- Training episodes at the final evaluation point: {', '.join(str(e) for e in episodes) or 'n/a'}"
        " (the paper trains 300,000)",
        f"- Data: `{meta.get('data_root', 'unknown')}`",
        f"- Evaluation: {_evaluation_text(results)}",
    ]
    for n in notes:
        out.append(f"- Note: {n}")
    stages = meta.get("stages") or {}
    if stages:
        out += ["", "Stage timings (of the last call: a resumed ablation times what it did after resuming):", ""]
        rows = [[str(k), f"{float(v):.1f}"] for k, v in stages.items()]
        rows.append(["**total**", f"**{sum(float(v) for v in stages.values()):.1f}**"])
        out += md_table(["stage", "wall (s)"], rows)
    out.append("")
    return out


def _contexts_text(rows: pd.DataFrame) -> str:
    """"train 20, hard 5" from the ``eval_contexts`` column (empty if unknown)."""
    if "eval_contexts" not in rows or rows.empty:
        return ""
    parts = []
    for split in SPLITS:
        n = pd.to_numeric(rows.loc[rows["split"] == split, "eval_contexts"], errors="coerce").dropna()
        n = n[n > 0]
        if len(n):
            lo, hi = int(n.min()), int(n.max())
            parts.append(f"{split} {lo}" if lo == hi else f"{split} {lo}-{hi}")
    return ", ".join(parts)


def _evaluation_text(results: pd.DataFrame) -> str:
    """Which rows are exhaustive: the final rows of learned runs and the baselines cover
    every context; the learning-curve points only ``train.eval_contexts`` of them."""
    runs = results[~is_baseline(results)]
    final = runs[runs["final"]]
    curve = runs[~runs["final"]]
    keys = ["method", "seed", "setting", "split", "episodes"]
    twins = final.merge(curve[keys].drop_duplicates(), on=keys, how="inner")
    if not final.empty and twins.empty:  # an older results file: the last curve point is the final row
        return ("this results file flags each run's last per-epoch evaluation as its final point "
                "(`train.eval_contexts` contexts per split, evenly spaced, x 605 start views); the baselines cover "
                "every context. Rerun `uevavd ablate` on the directory to add the exhaustive final evaluations.")
    exhaustive = _contexts_text(pd.concat([final, results[is_baseline(results)]]))
    sampled = _contexts_text(curve)
    return ("final-point numbers (results tables, GenGap, sweeps, claims, the reference lines of Fig. 9) are "
            "exhaustive: every context of each split x all 605 start views, greedy, for the learned policies' "
            "final checkpoints and the baselines alike"
            + (f" (contexts per split: {exhaustive})" if exhaustive else "")
            + ". The learning-curve points of Fig. 9 are the per-epoch evaluations during training, on "
            "`train.eval_contexts` evenly spaced contexts per split"
            + (f" ({sampled})" if sampled else "") + " x 605 start views.")


def _results_section(final: pd.DataFrame, setting: str) -> list[str]:
    out = ["## Results at the final evaluation point", "",
           f"Setting `{setting}`. Cells: mean ± std over runs, and the 95% confidence interval below it: "
           "with one recognizer a Student-t interval over seeds (the deterministic baselines exact); with several, "
           "a two-stage bootstrap (recognizers with replacement, then seeds within each; the baselines vary "
           "with the recognizer) whose std is the bootstrap standard error. "
           "Learned methods: their final policies evaluated on every context of the split x 605 start views, "
           "like the baselines (see Setup). "
           "All values per episode: return is discounted (gamma = 0.9), accuracy is argmax == true "
           "class at the final view, recognition is the rate of reco = 1 at the end.", ""]
    for split in SPLITS:
        sel = final[(final["split"] == split) & (final["setting"] == setting)]
        if sel.empty:
            continue
        out += [f"**{split} contexts**", ""]
        rows = []
        for m in order_methods(sel["method"].unique()):
            n = int(sel.loc[sel["method"] == m, "seed"].nunique())
            rows.append([label(m), str(n)] + [_cell(estimate(final, m, split, c, setting), d)
                                              for c, _, d in TABLE_METRICS])
        out += md_table(["Policy", "runs", *[h for _, h, _ in TABLE_METRICS]], rows) + [""]
    out += ["All settings, splits and metrics with their intervals: [`summary.csv`](summary.csv).", ""]
    return out


def _gengap_section(final: pd.DataFrame, setting: str) -> list[str]:
    out = ["## Generalisation gap", "",
           "GenGap = return on training contexts minus return on test contexts, per run (same run), "
           "then mean ± std and the 95% interval of the results tables (Student t over seeds with one "
           "recognizer; the two-stage bootstrap over recognizers, then seeds, with several). Smaller is better.",
           ""]
    rows = []
    for m in order_methods(final.loc[final["setting"] == setting, "method"].unique()):
        tr = estimate(final, m, "train", "return", setting)
        hd = estimate(final, m, "hard", "return", setting)
        rows.append([label(m), _cell(tr, 3), _cell(hd, 3), _cell(gengap_estimate(final, m, setting, "hard"), 3),
                     _cell(gengap_estimate(final, m, setting, "simple"), 3)])
    out += md_table(["Policy", "train return", "hard-test return", "GenGap (train − hard)",
                   "GenGap (train − simple)"], rows) + [""]
    return out


def _curves_section(results: pd.DataFrame, final: pd.DataFrame, setting: str, out_dir: Path,
                    window: int | None, figures: bool) -> list[str]:
    curves = curve_rows(results)
    curves = curves[(curves["setting"] == setting) & (curves["episodes"] >= 0)]
    out = ["## Learning curves (Fig. 9)", ""]
    if curves.empty:
        return out + ["No learning-curve rows in the default setting.", ""]
    points = int(curves.groupby(["method", "seed", "split"])["episodes"].nunique().min())
    w = int(window) if window is not None else max(1, min(5, points // 3))
    base = final[is_baseline(final) & (final["setting"] == setting)]
    smoothing = (f"smoothed with a {w}-point trailing sliding-window mean (the point at k averages points "
                 f"k-{w - 1}..k, so a smoothed curve lags the raw one by about {(w - 1) / 2:g} evaluation points)"
                 if w > 1 else "not smoothed (window 1)")
    out += [f"Return, recognition rate and movement distance against training episodes on the training and "
            f"hard-test contexts ({setting} setting). Each seed's curve ({points}+ evaluation points) is "
            f"{smoothing}; the line is the mean over runs and the band "
            + ("the tables' 95% two-stage bootstrap interval (recognizers, then seeds)"
               if results["recognizer"].nunique() > 1 else
               "the 95% Student-t interval over seeds (mean ± t(0.975, n-1) · sd / √n, the same interval as the "
               "tables; no band with one seed)")
            + " at each evaluation point, clipped to the metric's range. Curve points are the per-epoch evaluations "
            "(`train.eval_contexts` contexts per split); dashed lines: the baselines, evaluated on every context.",
            ""]
    return out + figure_lines(out_dir / "fig9_curves.png", "Fig. 9: learning curves",
                              lambda path: plot_curves(curves, base, path, window=w), draw=figures)


def _sweep_section(final: pd.DataFrame, param: str, table_no: int, ablation_dir: Path) -> list[str]:
    title = {"thre": "classification threshold thre", "C": "movement-cost bound C"}[param]
    out = [f"## Table {table_no}: policy performance versus the {title}", ""]
    methods = sweep_methods(final, param)
    if not methods:
        return out + [f"The {param} sweep was not run (results.csv has no `{param}=...` setting). "
                      f"Run it with `uevavd ablate --sweep {param}` (the values go to `ablation.json` "
                      f"`sweeps.{param}`), then `uevavd report {ablation_dir}`.", ""]
    rows_spec = (("return", "Return", 3, max), ("accuracy", "Accuracy", 3, max),
                 ("recognition", "Recognition", 3, max), ("path_m", "Path (m)", 1, min),
                 ("path_steps", "Path (steps)", 2, min))
    for m in methods:
        rows = sweep_rows(final, param, m)
        rows = rows[rows["split"] == "hard"]
        values = sorted(rows[param].unique())
        if not values:
            out += [f"{label(m)}: the {param} sweep has no hard-split rows.", ""]
            continue
        out += [f"{label(m)} on the hard-test contexts, mean ± std over seeds (best in bold).", ""]
        table = []
        for col, name, d, best in rows_spec:
            ests = [estimate_units(rows.loc[np.isclose(rows[param], v), "seed"].to_numpy(),
                                   rows.loc[np.isclose(rows[param], v), col].to_numpy(dtype=np.float64))
                    for v in values]
            top = best(e.mean for e in ests)
            cells = []
            for e in ests:
                s = f"{e.mean:.{d}f} ± {e.std:.{d}f}" if math.isfinite(e.std) else f"{e.mean:.{d}f} (n=1)"
                cells.append(f"**{s}**" if e.mean == top else s)
            table.append([name, *cells])
        seeds = [str(rows.loc[np.isclose(rows[param], v), "seed"].nunique()) for v in values]
        table.append(["seeds", *seeds])
        out += md_table(["", *[f"{param}={v:g}" for v in values]], table) + [""]
    return out


def _strips_section(ablation_dir: Path, meta: dict | None, out_dir: Path, figures: bool) -> list[str]:
    out = ["## Observation sequences (Fig. 8)", ""]
    trajs, note = load_trajectories(ablation_dir / "trajectories.json")
    if not trajs:
        return out + [note, ""]
    lookup = strip_images(trajs, (meta or {}).get("data_root"))
    t_max = int((meta or {}).get("t_max", 5))
    t0 = trajs[0]
    out += [f"Greedy episode of each final policy from the same start (view {t0.get('start_view')}) in hard-test "
            f"context {t0.get('context')} (scene `{t0.get('scene')}`). Left: the viewpoint grid seen from "
            "above (target at the red square), the path with the start as a red star, altitude as marker colour "
            "and size; right: the crops observed along the path with the action taken at each.", ""]
    out += figure_lines(out_dir / "fig8_strips.png", "Fig. 8: observation sequences",
                        lambda path: plot_strips(trajs, lookup, path, t_max=t_max), draw=figures)
    if note:
        out += [note, ""]
    out.append(f"Images read from {lookup.source}.")
    if lookup.missing:
        out.append(f"{lookup.missing} crop(s) could not be found under the dataset root and are drawn as gray panels.")
    out.append("")
    rows = [[label(t["method"]), str(t.get("seed", 0)), str(len(t["views"]) - 1),
             "yes" if t.get("recognized") else "no", "yes" if t.get("correct") else "no",
             f"{float(t.get('return', float('nan'))):.3f}"] for t in trajs]
    out += md_table(["Policy", "seed", "moves", "recognised", "correct", "return"], rows) + [""]
    return out


def _claims_section(claims: list[Claim], notes: list[str]) -> list[str]:
    out = ["## Claims checked", "",
           "Each claim of the paper against our final-point numbers. A comparison agrees when its whole 95% "
           "interval lies on the claimed side of zero, disagrees when it lies wholly on the other side, and "
           "cannot tell otherwise. Intervals: with one recognizer, Student t over seeds (Welch for differences "
           "between methods, exact for the deterministic passive baseline); with several, the two-stage bootstrap "
           "(recognizers with replacement, then seeds within each; differences paired by recognizer); for sweeps, "
           "a least-squares slope with its t-interval over (setting, run) points.", ""]
    for c in claims:
        out.append(f"- **({c.id}) {c.text}** — **{c.verdict}**. {c.evidence}")
    out += ["", "### What could explain a claim that does not agree", ""]
    out += [f"- {n}" for n in notes] if notes else ["- Every claim agrees."]
    out.append("")
    return out


def write_report(dir: Path, *, window: int | None = None, figures: bool = True) -> Path:  # noqa: A002
    """Write ``dir/report/report.md`` (+ ``fig9_curves.png``, ``fig8_strips.png``,
    ``summary.csv``) from ``dir/results.csv``, ``dir/trajectories.json`` and
    ``dir/ablation.json``; return the path of ``report.md``.

    ``window``: sliding-window length (evaluation points) of the curve smoothing;
    default ``min(5, points // 3)`` (at least 1). ``figures=False``: the text and tables
    only, the same but for the figures (drawing them is most of a report's time).
    """
    ablation_dir = ablation_folder(dir)
    results = load_results(ablation_dir / "results.csv")
    notes: list[str] = []
    meta_path = ablation_dir / ABLATION_FILE
    meta = (check_outputs(ablation_dir, read_ablation_meta(meta_path)) if meta_path.is_file()
            else _read_json(meta_path, notes))
    # two reports of one folder take turns; the temporaries a killed one left are removed
    with recorded_roles(meta), folder_lock(ablation_dir / REPORT_DIR, RuntimeError, wait=lambda lock: None):
        remove_temporaries(ablation_dir / REPORT_DIR)
        return _write_report(ablation_dir, results, meta, notes, window, figures)


def _write_report(ablation_dir: Path, results: pd.DataFrame, meta: dict | None, notes: list[str],
                  window: int | None, figures: bool) -> Path:
    out_dir = ablation_dir / REPORT_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    final = final_rows(results)
    setting = default_setting(final)
    summary = summary_table(final)
    atomic_write(out_dir / "summary.csv", summary.to_csv(index=False, float_format="%.6g"))
    claims = check_claims(results, (meta or {}).get("lineage"))
    title = f"# Ablation report: preset `{(meta or {}).get('preset', 'unknown')}`"
    lines = [title, "", f"Generated by `uevavd report {ablation_dir}` from the files in that directory.", ""]
    lines += _setup_section(meta, results, final, notes)
    audit = _read_json(ablation_dir / "recognizer_audit.json", notes) if (
        ablation_dir / "recognizer_audit.json").is_file() else None
    if audit:
        lines += audit_markdown(audit)
    lines += _results_section(final, setting)
    lines += _gengap_section(final, setting)
    lines += _curves_section(results, final, setting, out_dir, window, figures)
    lines += _sweep_section(final, "thre", 2, ablation_dir)
    lines += _sweep_section(final, "C", 3, ablation_dir)
    lines += contexts_section(final, out_dir, figures=figures)
    lines += stopping_section(final, setting, ablation_dir)
    lines += room_section(final, setting, ablation_dir)
    contexts = read_contexts(ablation_dir / "contexts.csv")
    lines += write_arms(final, contexts, out_dir, setting)
    lines += rliable_section(contexts, setting, out_dir, figures=figures)
    lines += _strips_section(ablation_dir, meta, out_dir, figures)
    lines += _claims_section(claims, diagnose(results, claims))
    path = out_dir / "report.md"
    atomic_write(path, "\n".join(lines))
    return path


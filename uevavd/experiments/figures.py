"""Figures of the ablation report (headless matplotlib, Agg): the Fig. 9-style
learning curves and the Fig. 8-style observation strips.

Both functions write a PNG atomically (temp file in the same folder, then
``os.replace``) and return its path.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import seaborn as sns  # noqa: E402

from ..atomic import atomic_save  # noqa: E402
from ..data.grid import ACTION_TYPES, STOP, XS, YS, ZS, view_coords  # noqa: E402
from .report_data import baselines as reference_names  # noqa: E402
from .report_data import estimate_units, label, order_methods  # noqa: E402
from .stats import smooth  # noqa: E402

#: Fig. 9 panels: (column, y-axis label).
CURVE_METRICS: tuple[tuple[str, str], ...] = (
    ("return", "return"),
    ("recognition", "recognition rate"),
    ("path_m", "movement distance (m)"),
)
CURVE_SPLITS: tuple[tuple[str, str], ...] = (("train", "training contexts"), ("hard", "hard-test contexts"))
_BASELINE_COLOURS = {"random": "0.45", "passive": "tab:brown", "visibility_oracle": "tab:purple",
                     "departure_ceiling": "mediumorchid", "departure_ceiling2": "plum",
                     "oracle": "black", "sb3_dqn": "tab:olive", "sb3_ppo": "tab:cyan"}
#: Colours of other baselines (a plugin's), in order of their names: each its own.
_MORE_COLOURS = ("tab:pink", "tab:gray", "darkgoldenrod", "teal", "indigo", "firebrick")


def baseline_colour(method: str, others: list[str] | None = None) -> str:
    """A baseline's line colour: uevavd's own, else one of :data:`_MORE_COLOURS` by its
    place among ``others`` (the figure's other baselines, sorted), so no two share one."""
    if method in _BASELINE_COLOURS:
        return _BASELINE_COLOURS[method]
    rest = sorted(m for m in (others or [method]) if m not in _BASELINE_COLOURS)
    i = rest.index(method) if method in rest else 0
    return _MORE_COLOURS[i % len(_MORE_COLOURS)]


#: Resolution of the PNG copy of a figure (the PDF beside it is vector).
PNG_DPI = 160


def save_figure(fig, path: Path) -> Path:
    """``path`` (PNG, for the Markdown report) and the same figure as a PDF beside it (for papers)."""
    try:
        atomic_save(path.with_suffix(".pdf"), lambda tmp: fig.savefig(tmp, format="pdf", bbox_inches="tight"))
        return atomic_save(path, lambda tmp: fig.savefig(tmp, format="png", dpi=PNG_DPI, bbox_inches="tight"))
    finally:
        plt.close(fig)


def figure_lines(path: Path, caption: str, plot: Callable[[Path], object], *, draw: bool = True) -> list[str]:
    """A report figure's Markdown: ``plot(path)`` draws it and its image link is returned.
    With ``draw=False`` (``--no-figures``) nothing is drawn, an earlier drawing of it (PNG and
    PDF) is removed, so the folder never shows a figure of other data, and a line says so."""
    if draw:
        plot(path)
        return [f"![{caption}]({path.name})", ""]
    for old in (path, path.with_suffix(".pdf")):
        old.unlink(missing_ok=True)
    return [f"({caption}: not drawn, the report was written with `--no-figures`.)", ""]


def smoothed_curves(curves: pd.DataFrame, window: int) -> pd.DataFrame:
    """Each (method, seed, split) curve sorted by episodes with every metric of
    :data:`CURVE_METRICS` replaced by its trailing ``window``-point sliding mean; the
    k-th evaluation point of each seed is placed at the mean episode count of the k-th
    points over seeds (``eval_point`` = k, ``episodes_raw`` = the seed's own count)."""
    out = []
    for _, g in curves.groupby(["method", "seed", "split"], sort=False):
        g = g.sort_values("episodes").copy()
        g["eval_point"] = np.arange(len(g))
        for col, _ in CURVE_METRICS:
            g[col] = smooth(g[col].to_numpy(), window)
        out.append(g)
    if not out:
        return curves.iloc[0:0]
    data = pd.concat(out, ignore_index=True)
    # Seeds evaluate at slightly different episode counts (episodes finish in batches), and
    # seaborn aggregates over seeds only at equal x: put the k-th evaluation point of every
    # seed at the mean episode count of the k-th points.
    data["episodes_raw"] = data["episodes"]
    data["episodes"] = data.groupby(["method", "split", "eval_point"])["episodes_raw"].transform("mean")
    return data


#: The range a metric can take; a band is clipped to it (a t-interval over few seeds can
#: otherwise claim a recognition rate of 1.5 or a negative distance).
METRIC_RANGE: dict[str, tuple[float, float]] = {
    "accuracy": (0.0, 1.0), "recognition": (0.0, 1.0), "stop_rate": (0.0, 1.0),
    "path_m": (0.0, np.inf), "path_steps": (0.0, np.inf), "steps": (0.0, np.inf),
}


def curve_bands(data: pd.DataFrame, col: str) -> pd.DataFrame:
    """Mean and 95% band over runs of the smoothed curves (:func:`smoothed_curves`) at
    each evaluation point: one row per (method, split, eval_point) with ``episodes``,
    ``mean``, ``lo``, ``hi`` and ``n`` (runs). The band is the tables' interval
    (:func:`uevavd.experiments.report_data.estimate_units`): with one recognizer the Student-t
    interval over seeds (mean ± t(0.975, n-1) · sd / √n; NaN, no band, with fewer than two
    seeds), with several the nested bootstrap; clipped to :data:`METRIC_RANGE`."""
    lo_b, hi_b = METRIC_RANGE.get(col, (-np.inf, np.inf))
    rows = []
    for (m, split, k), g in data.groupby(["method", "split", "eval_point"], sort=True):
        e = estimate_units(g["seed"].to_numpy(), g[col].to_numpy(dtype=np.float64))
        rows.append({"method": m, "split": split, "eval_point": int(k), "episodes": float(g["episodes"].mean()),
                     "mean": e.mean, "lo": float(np.clip(e.lo, lo_b, hi_b)), "hi": float(np.clip(e.hi, lo_b, hi_b)),
                     "n": e.n})
    return pd.DataFrame(rows, columns=["method", "split", "eval_point", "episodes", "mean", "lo", "hi", "n"])


def plot_curves(curves: pd.DataFrame, baselines: pd.DataFrame, path: Path, *, window: int) -> Path:
    """Fig. 9: 3 metrics (rows) x {train, hard} (columns) against training episodes.

    ``curves``: learned-method learning-curve rows of one setting (``episodes >= 0``);
    each seed's curve is smoothed with a ``window``-point trailing sliding mean, then the
    mean over seeds is drawn (seaborn) with the 95% Student-t band over seeds of
    :func:`curve_bands` (matplotlib ``fill_between``; none with one seed).
    ``baselines``: final baseline rows of the same setting, drawn as dashed lines at
    their mean over seeds.
    """
    data = smoothed_curves(curves, window)
    data = data.assign(policy=data["method"].map(label))
    hue_order = [label(m) for m in order_methods(data["method"].unique())]
    palette = dict(zip(hue_order, sns.color_palette("tab10", len(hue_order)), strict=True))
    fig, axes = plt.subplots(len(CURVE_METRICS), len(CURVE_SPLITS), figsize=(11, 10), squeeze=False)
    for i, (col, ylabel) in enumerate(CURVE_METRICS):
        for j, (split, title) in enumerate(CURVE_SPLITS):
            ax = axes[i, j]
            sub = data[data["split"] == split]
            if sub.empty:
                ax.text(0.5, 0.5, f"no {split} rows", ha="center", va="center", transform=ax.transAxes)
            else:
                band = curve_bands(sub, col)
                band = band.assign(policy=band["method"].map(label))
                sns.lineplot(data=band, x="episodes", y="mean", hue="policy", hue_order=hue_order, palette=palette,
                             errorbar=None, ax=ax, legend=False)
                for policy, g in band.groupby("policy", sort=False):
                    ok = np.isfinite(g["lo"].to_numpy()) & np.isfinite(g["hi"].to_numpy())
                    if ok.any():
                        ax.fill_between(g["episodes"].to_numpy(), g["lo"].to_numpy(), g["hi"].to_numpy(),
                                        where=ok, color=palette[policy], alpha=0.2, linewidth=0)
            base = baselines[baselines["split"] == split]
            for m in reference_names():
                vals = base.loc[base["method"] == m, col]
                if len(vals):
                    ax.axhline(float(vals.mean()), ls="--", lw=1.2, color=baseline_colour(m, reference_names()))
            ax.set_xlabel("training episodes")
            ax.set_ylabel(ylabel)
            ax.set_title(f"({'abc'[i]}) {ylabel}, {title}", fontsize=10)
            ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], color=palette[h], lw=2, label=h) for h in hue_order]
    present = set(baselines["method"])
    handles += [plt.Line2D([], [], color=baseline_colour(m, reference_names()), ls="--", label=label(m))
                for m in reference_names() if m in present]
    fig.legend(handles=handles, loc="lower center", ncol=max(1, len(handles)), frameon=False,
               bbox_to_anchor=(0.5, -0.01))
    nested = curves["seed"].nunique() > 0 and (curves["seed"] // 1000).nunique() > 1  # several recognizers
    how = ("the two-stage bootstrap over recognizers, then seeds" if nested else "Student t over seeds")
    fig.suptitle(f"Mean over runs and 95% interval ({how}) after a {window}-point trailing sliding-window mean",
                 fontsize=11)
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    return save_figure(fig, path)


#: Panels of the training-contexts figure: (column of ``context_table``, y-axis label).
CONTEXT_PANELS: tuple[tuple[str, str], ...] = (
    ("hard return", "return, hard-test contexts"),
    ("simple return", "return, simple-test contexts"),
    ("GenGap (train − hard)", "GenGap (train − hard)"),
    ("hard recognition", "recognition rate, hard-test contexts"),
    ("hard path (m)", "movement distance (m), hard-test contexts"),
    ("train return", "return, own training contexts"),
)


def plot_context_axis(table: pd.DataFrame, path: Path) -> Path:
    """Test return, recognition, path and GenGap against the number of training contexts.

    ``table``: :func:`uevavd.experiments.report_contexts.context_table` (one row per method and
    count, each panel's column with ``lo`` / ``hi``). Learned methods: line and 95% band (the
    tables' interval); baselines: dashed lines in their colours, their own value at each count
    (passive and the oracles are evaluated on each setting's training contexts too). Random is
    left to the table: its returns (about -0.3) would squeeze every other line flat."""
    refs = set(reference_names())
    methods = [m for m in order_methods(table["method"].unique()) if m != "random"]
    learned = [m for m in methods if m not in refs]
    palette = dict(zip(learned, sns.color_palette("tab10", len(learned)), strict=True))
    fig, axes = plt.subplots(2, 3, figsize=(14, 8), squeeze=False)
    for ax, (col, ylabel) in zip(axes.ravel(), CONTEXT_PANELS, strict=True):
        for m in methods:
            g = table[table["method"] == m].sort_values("contexts")
            x, y = g["contexts"].to_numpy(), g[col].to_numpy(dtype=np.float64)
            if m in palette:
                ax.plot(x, y, "o-", color=palette[m], lw=2, label=label(m))
                lo, hi = g[f"{col} lo"].to_numpy(dtype=np.float64), g[f"{col} hi"].to_numpy(dtype=np.float64)
                ok = np.isfinite(lo) & np.isfinite(hi)
                if ok.any():
                    ax.fill_between(x, lo, hi, where=ok, color=palette[m], alpha=0.2, linewidth=0)
            else:
                ax.plot(x, y, "--", color=baseline_colour(m, sorted(refs)), lw=1.2, label=label(m))
        ax.set_xlabel("training contexts")
        ax.set_ylabel(ylabel)
        ax.set_xticks(sorted(table["contexts"].unique()))
        ax.grid(alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=max(1, len(labels)), frameon=False,
               bbox_to_anchor=(0.5, -0.01))
    fig.suptitle("Against the number of training contexts: mean over runs and 95% interval; dashed: baselines",
                 fontsize=11)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    return save_figure(fig, path)


def _move_text(a: int, b: int, last: bool, stopped: bool) -> str:
    """The move from view ``a`` to ``b`` inferred from the grid (when the episode has no
    recorded actions): the axis and metres flown, "no move" (a clamped move), or at the
    last view "stop" / "(end)"."""
    if last:
        return "stop" if stopped else "(end)"
    d = view_coords(b) - view_coords(a)
    if not d.any():
        return "no move (edge)"
    axis = int(np.flatnonzero(d)[0])
    name = {(0, 1): "right", (0, -1): "left", (1, 1): "forward", (1, -1): "backward", (2, 1): "up",
            (2, -1): "down"}[(axis, int(np.sign(d[axis])))]
    return f"{name} {abs(d[axis]):.0f} m"


def _action_text(action: Sequence[int] | None) -> str:
    if action is None:
        return "(end)"
    a_type, a_range = int(action[0]), int(action[1])
    if a_type == STOP:
        return "stop"
    name = ACTION_TYPES[a_type] if 0 <= a_type < len(ACTION_TYPES) else f"type {a_type}"
    return f"{name} x{a_range + 1}"


def _grid_axes(ax, views: Sequence[int]):
    gx, gy = np.meshgrid(XS, YS, indexing="ij")
    ax.scatter(gx.ravel(), gy.ravel(), s=4, color="0.8", zorder=1)
    ax.scatter([0], [0], marker="s", s=40, color="tab:red", zorder=2)
    xyz = view_coords(np.asarray(views, dtype=np.int64)).reshape(-1, 3)
    ax.plot(xyz[:, 0], xyz[:, 1], "-", color="0.3", lw=1.2, zorder=3)
    size = 20 + (xyz[:, 2] - ZS[0]) * 2.0
    sc = ax.scatter(xyz[:, 0], xyz[:, 1], c=xyz[:, 2], s=size, cmap="viridis", vmin=ZS[0], vmax=ZS[-1],
                    edgecolors="black", linewidths=0.5, zorder=4)
    ax.scatter(xyz[:1, 0], xyz[:1, 1], marker="*", s=220, facecolors="none", edgecolors="tab:red",
               linewidths=1.5, zorder=5)
    for k, (x, y) in enumerate(xyz[:, :2]):
        ax.annotate(str(k), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7, zorder=6)
    ax.set_xlim(XS[0] - 8, XS[-1] + 8)
    ax.set_ylim(YS[0] - 8, YS[-1] + 8)
    ax.set_aspect("equal")
    ax.set_xticks([XS[0], 0, XS[-1]])
    ax.set_yticks([YS[0], 0, YS[-1]])
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    return sc


def plot_strips(trajectories: Sequence[dict], image_for: Callable[[dict, int], np.ndarray | None],
                path: Path, *, t_max: int = 5) -> Path:
    """Fig. 8: one row per policy; the first panel is the top-down viewpoint grid (x-y,
    target at the origin as a red square) with the path drawn, altitude as marker colour
    and size, the start as a red star; then the observed crops along the path, each
    captioned with its step, altitude and the action taken there.

    ``trajectories``: dicts as in ``trajectories.json`` (keys method, seed, views,
    actions, recognized, correct, return). ``image_for(traj, view)`` returns an
    (H, W, 3) uint8 RGB crop or None when the image cannot be found (drawn as a gray
    "missing" panel). Without recorded ``actions`` the moves are read off the views, and
    an episode with fewer than ``t_max`` moves ended with stop.
    """
    n_rows = max(1, len(trajectories))
    n_cols = 1 + max((len(t["views"]) for t in trajectories), default=1)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.1 * n_cols + 0.8, 2.6 * n_rows + 0.4), squeeze=False,
                             gridspec_kw={"width_ratios": [1.4] + [1.0] * (n_cols - 1)})
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.55 / (2.6 * n_rows + 0.4) + 0.04, top=0.95,
                        wspace=0.12, hspace=0.55)
    sc = None
    for r, traj in enumerate(trajectories):
        views = [int(v) for v in traj["views"]]
        actions = list(traj.get("actions") or [])
        sc = _grid_axes(axes[r, 0], views)
        reco = "recognised" if traj.get("recognized") else "not recognised"
        corr = "correct" if traj.get("correct") else "wrong"
        axes[r, 0].set_title(f"{label(traj['method'])} (seed {traj.get('seed', 0)})\n{reco}, {corr}, "
                             f"R={float(traj.get('return', float('nan'))):.2f}", fontsize=7)
        for k in range(1, n_cols):
            ax = axes[r, k]
            ax.set_xticks([])
            ax.set_yticks([])
            if k - 1 >= len(views):
                ax.axis("off")
                continue
            view = views[k - 1]
            img = image_for(traj, view)
            if img is None:
                ax.imshow(np.full((8, 8, 3), 200, np.uint8))
                ax.text(0.5, 0.5, "missing", ha="center", va="center", transform=ax.transAxes, fontsize=8)
            else:
                ax.imshow(img)
            x, y, z = view_coords(view)
            ax.set_title(f"t={k - 1}  ({x:+.0f}, {y:+.0f}, {z:.0f})", fontsize=7)
            if actions:
                text = _action_text(actions[k - 1] if k - 1 < len(actions) else None)
            else:
                last = k == len(views)
                text = _move_text(view, views[k] if not last else view, last, len(views) - 1 < t_max)
            ax.set_xlabel(text, fontsize=7)
    if not trajectories:
        axes[0, 0].text(0.5, 0.5, "no trajectories", ha="center", va="center")
        axes[0, 0].axis("off")
    elif sc is not None:
        cax = fig.add_axes((0.05, 0.012, 0.16, 0.012))
        bar = fig.colorbar(sc, cax=cax, orientation="horizontal")
        bar.set_label("altitude z (m): marker colour and size", fontsize=7)
        bar.ax.tick_params(labelsize=6)
    return save_figure(fig, path)

"""The report's aggregate statistics as the RL community reads them (Agarwal et al., "Deep RL at
the edge of the statistical precipice", NeurIPS 2021), computed with ``rliable``: the
interquartile mean, the optimality gap, the probability of improvement and performance profiles,
over runs and contexts per split.

The tasks are a split's contexts; a run is one (recognizer, seed). Each context's return is
normalised between passive (0) and the oracle (1) of the same recognizer's table, so a score is
the share of the room above stopping at once that a policy takes there (contexts where the oracle
is no better than passive carry no room and are left out). A baseline is deterministic given its
recognizer's table, so it scores each of that recognizer's seeds alike. Intervals are rliable's
stratified bootstrap over runs (95 %, percentile; 1,000 resamples for the tables, 500 for the
profiles' bands), from a fixed random state.

``rliable`` is an optional extra (``pip install -e ".[rliable]"``); without it the section says
how to get it.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .figures import figure_lines, save_figure  # sets matplotlib's non-interactive backend first
from .report_data import SPLITS, label, learned, md_table

#: The two references a context's return is normalised between: 0 and 1.
FLOOR, CEILING = "passive", "oracle"
#: The scripted rules every learned method is compared with, beside passive.
REFERENCES = ("passive", "box_gate", "pose_seek")
REPS = 1000  #: bootstrap resamples per estimate of the tables
PROFILE_REPS = 500  #: bootstrap resamples of the performance profiles' bands
SEED = 0  #: the bootstrap's random state, so a report is written the same twice
TAUS = np.linspace(-0.5, 1.0, 31)  #: the performance profiles' thresholds (normalised score)


def rliable_available() -> bool:
    """Whether rliable runs here: it imports (its ``arch`` 7 fails at import under pandas 3) and
    its bootstrap runs (``arch`` 8, which rliable 1.2 does not take, refuses its random state)."""
    try:
        from rliable import library, metrics

        with _seeded() as state:
            library.get_interval_estimates({"x": np.zeros((2, 2))}, metrics.aggregate_mean, reps=2,
                                           random_state=state)
    except Exception:  # noqa: BLE001 - an ImportError, or arch's TypeError under pandas 3 or arch 8
        return False
    return True


@contextmanager
def _seeded() -> Iterator[np.random.RandomState]:
    """A fixed random state for rliable's bootstrap, without arch's notice that its RandomState
    argument is deprecated (rliable 1.2 passes it that way)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, module="arch")
        yield np.random.RandomState(SEED)


def score_matrices(contexts: pd.DataFrame, setting: str, split: str) -> dict[str, np.ndarray]:
    """Per method of ``split``: (runs, contexts) float64 normalised scores, the runs in
    (recognizer, seed) order and the contexts those with room, alike for every method.
    Empty where the contexts have no passive or oracle rows."""
    need = {"method", "recognizer", "seed", "setting", "split", "context", "return"}
    if contexts.empty or not need <= set(contexts.columns):
        return {}
    sel = contexts[(contexts["setting"] == setting) & (contexts["split"] == split)]
    table = sel.pivot_table(index=["method", "recognizer", "seed"], columns="context", values="return",
                            aggfunc="mean")
    methods = list(table.index.get_level_values("method").unique())
    if FLOOR not in methods or CEILING not in methods:
        return {}
    floor = table.loc[FLOOR].groupby(level="recognizer").mean()  # (recognizers, contexts)
    room = table.loc[CEILING].groupby(level="recognizer").mean() - floor
    keep = (room > 1e-9).all(axis=0)
    learners = learned(m for m in methods if m not in (FLOOR, CEILING))
    runs = sorted({(r, s) for m in learners for r, s in table.loc[m].index if m not in REFERENCES})
    if not runs or not keep.any():
        return {}
    out = {}
    for m in [*learners, *(r for r in REFERENCES if r in methods and r not in learners)]:
        rows = table.loc[m]
        got = []
        for rec, seed in runs:
            if (rec, seed) in rows.index:
                ret = rows.loc[(rec, seed)]
            elif rec in rows.index.get_level_values("recognizer"):  # a baseline: one row per recognizer
                ret = rows.xs(rec, level="recognizer").iloc[0]
            else:
                break
            got.append(((ret - floor.loc[rec]) / room.loc[rec])[keep].to_numpy(np.float64))
        if len(got) == len(runs) and np.isfinite(got).all():
            out[m] = np.stack(got)
    return out


def _interval(point: float, ci: np.ndarray) -> str:
    return f"{point:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"


def aggregates(scores: dict[str, np.ndarray], *, reps: int = REPS) -> dict[str, dict[str, Any]]:
    """Per method: the IQM, the optimality gap (gamma = 1: the oracle) and the mean, each
    (point, (low, high)) over rliable's stratified bootstrap."""
    from rliable import library as rly
    from rliable import metrics

    def func(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_optimality_gap(x, 1.0),
                         metrics.aggregate_mean(x)])

    with _seeded() as state:
        point, ci = rly.get_interval_estimates(scores, func, reps=reps, random_state=state)
    return {m: {k: (float(point[m][i]), ci[m][:, i]) for i, k in enumerate(("iqm", "gap", "mean"))}
            for m in scores}


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """rliable's ``metrics.probability_of_improvement`` (per context Mann-Whitney's U / (n m):
    P(a run of x beats a run of y) + half the ties, averaged over contexts), computed for all
    contexts at once instead of one scipy call each (a thousand times faster, the same number)."""
    gt = (x[:, None, :] > y[None, :, :]).mean(axis=(0, 1))
    eq = (x[:, None, :] == y[None, :, :]).mean(axis=(0, 1))
    return float(np.mean(gt + 0.5 * eq))


def improvement(scores: dict[str, np.ndarray], pairs: list[tuple[str, str]], *, reps: int = REPS
                ) -> dict[tuple[str, str], tuple[float, np.ndarray]]:
    """P(X > Y) for each pair: the probability that a run of X beats a run of Y on a context
    drawn at random, with its interval (rliable's stratified bootstrap over runs)."""
    from rliable import library as rly

    keyed = {f"{x},{y}": (scores[x], scores[y]) for x, y in pairs}
    with _seeded() as state:
        point, ci = rly.get_interval_estimates(keyed, probability_of_improvement, reps=reps, random_state=state)
    return {(x, y): (float(point[f"{x},{y}"]), ci[f"{x},{y}"].ravel()) for x, y in pairs}


def profiles_figure(by_split: dict[str, dict[str, np.ndarray]], path: Path, *, reps: int = PROFILE_REPS) -> None:
    """One panel per split: the fraction of (run, context) scores above each threshold tau, with
    its 95 % band, per method (rliable's performance profiles)."""
    import matplotlib.pyplot as plt
    from rliable import library as rly

    fig, axes = plt.subplots(1, len(by_split), figsize=(4.2 * len(by_split), 3.4), squeeze=False)
    for ax, (split, scores) in zip(axes[0], by_split.items(), strict=True):
        np.random.seed(SEED)  # create_performance_profile's bootstrap takes no random state
        with _seeded():
            prof, cis = rly.create_performance_profile(scores, TAUS, reps=reps)
        for m in scores:
            ax.plot(TAUS, prof[m], label=label(m), lw=1.5)
            ax.fill_between(TAUS, cis[m][0], cis[m][1], alpha=0.2)
        ax.set(title=split, xlabel="normalised score tau (passive 0, oracle 1)", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("fraction of runs x contexts with score > tau")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    save_figure(fig, path)


def rliable_section(contexts: pd.DataFrame, setting: str, out_dir: Path, *, reps: int = REPS,
                    profile_reps: int = PROFILE_REPS, figures: bool = True) -> list[str]:
    """The report's aggregate statistics (and their figure unless ``figures=False``), or a
    line saying how to get them."""
    if contexts.empty:
        return []
    by_split = {s: m for s in SPLITS if (m := score_matrices(contexts, setting, s))}
    if not by_split:
        return []
    head = ["## Aggregate statistics (rliable)", ""]
    if not rliable_available():
        return [*head, "Not computed: rliable is not installed here, or does not run with the arch and pandas "
                "installed. `pip install -e \".[rliable]\"` brings it with the versions under which it runs; then "
                "`uevavd report DIR` writes this section.", ""]
    lines = [*head,
             "The interquartile mean (IQM), the optimality gap and the mean of the normalised score, over runs "
             "(recognizer x seed) and contexts per split, with 95 % stratified-bootstrap intervals over runs "
             "(Agarwal et al. 2021, computed with rliable). A context's score is its return normalised between "
             "passive (0) and the oracle (1) of the same recognizer's table; contexts where the oracle is no "
             "better than passive are left out. The gap is the mean shortfall below the oracle (lower is "
             "better).", ""]
    rows = []
    for split, scores in by_split.items():
        agg = aggregates(scores, reps=reps)
        n_runs, n_tasks = next(iter(scores.values())).shape
        for m in scores:
            rows.append([split, label(m), f"{n_runs} x {n_tasks}", _interval(*agg[m]["iqm"]),
                         _interval(*agg[m]["gap"]), _interval(*agg[m]["mean"])])
    lines += md_table(["split", "method", "runs x contexts", "IQM", "optimality gap", "mean"], rows)
    pair_rows = []
    for split, scores in by_split.items():
        ours = [m for m in scores if m not in REFERENCES]
        pairs = [(x, y) for i, x in enumerate(ours) for y in ours[i + 1:]]
        pairs += [(x, r) for x in ours for r in REFERENCES if r in scores]
        if pairs:
            for (x, y), (p, ci) in improvement(scores, pairs, reps=reps).items():
                pair_rows.append([split, label(x), label(y), _interval(p, ci)])
    if pair_rows:
        lines += ["", "<details><summary>Probability of improvement P(X > Y): that a run of X scores above a run "
                  "of Y on a context drawn at random (0.5: neither; an interval above 0.5 favours X); each learned "
                  "method against the others, passive and the scripted rules</summary>", "",
                  *md_table(["split", "X", "Y", "P(X > Y) [95 %]"], pair_rows), "", "</details>"]
    return [*lines, "", *figure_lines(out_dir / "performance_profiles.png", "Performance profiles",
                                      lambda path: profiles_figure(by_split, path, reps=profile_reps), draw=figures)]


__all__ = ["aggregates", "improvement", "rliable_available", "rliable_section", "score_matrices"]

"""The paper's claims (EXPERIMENTS section) checked against an ablation's results.

Each claim becomes a :class:`Claim` with a verdict:

* ``"agrees"``: every comparison the claim makes has its 95% t-interval wholly on the
  claimed side of zero;
* ``"disagrees"``: at least one comparison's interval lies wholly on the wrong side;
* ``"cannot tell"``: otherwise (an interval covers zero, one seed only, or the data
  the claim needs was not produced); the evidence says which.

Comparisons between methods are differences of means over independent seeds (Welch t
interval); a deterministic baseline (passive) is an exact constant; a sweep trend is
the least-squares slope over all (setting, seed) points with its t interval. Every
comparison uses the final evaluation point (for learned runs: the exhaustive evaluation of
the final policy on every context, see :func:`uevavd.experiments.results.final_eval`).
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from ..data.grid import STEP_M
from .report_data import (
    SPLITS,
    baselines,
    curve_rows,
    default_setting,
    estimate,
    final_rows,
    gengap_estimate,
    label,
    learned,
    sweep_methods,
    sweep_rows,
)
from .stats import Estimate, difference, sign_verdict, slope

AGREES = "agrees"
DISAGREES = "disagrees"
CANNOT_TELL = "cannot tell"

CLAIM_TEXT: dict[str, str] = {
    "a": "Every method beats passive perception (return above passive's on every split: train, simple, hard).",
    "b": "IBE-MAP has the highest hard-test return and the smallest GenGap.",
    "c": "Memo-MAP's GenGap is below MAP's.",
    "d": "A higher thre gives a lower return and a longer path (Table 2).",
    "e": "A higher C gives a shorter path and a lower accuracy (Table 3).",
    "f": "Every method beats the scripted box gate (stop where the target's box is in view, else one fixed move "
         "chosen on the training contexts) on every split. Not a claim of the paper: a baseline that reads the "
         "observation alone.",
    "g": "Every method beats the scripted pose rule (stop where the target's box is in view, else fly toward the "
         "column above the target) on every split. Not a claim of the paper: a baseline that reads the observation "
         "and the viewpoint's pose relative to the target, which the task gives.",
}


@dataclass(frozen=True)
class Claim:
    """One checked claim: ``id`` ("a".."e"), the claim ``text``, the ``verdict``
    (``"agrees"``, ``"disagrees"`` or ``"cannot tell"``) and the ``evidence`` (numbers
    and 95% intervals it rests on, or why it cannot be judged)."""

    id: str
    text: str
    verdict: str
    evidence: str


def _ci(e: Estimate, digits: int = 3) -> str:
    if not e.defined:
        return f"{e.mean:+.{digits}f} (no interval: n={e.n})"
    return f"{e.mean:+.{digits}f} [{e.lo:+.{digits}f}, {e.hi:+.{digits}f}]"


def _combine(parts: list[tuple[str | None, str]]) -> tuple[str, str]:
    """Verdict over several comparisons, and the evidence joined. ``parts``: (verdict of
    one comparison or None when it has no interval, its evidence)."""
    verdicts = [v for v, _ in parts]
    evidence = "; ".join(e for _, e in parts)
    if DISAGREES in verdicts:
        return DISAGREES, evidence
    if verdicts and all(v == AGREES for v in verdicts):
        return AGREES, evidence
    if any(v is None for v in verdicts):
        return CANNOT_TELL, "not judged: fewer than two seeds, no interval. " + evidence
    return CANNOT_TELL, "the interval of a comparison covers zero (CIs overlap). " + evidence


def _missing(cid: str, what: str) -> Claim:
    return Claim(cid, CLAIM_TEXT[cid], CANNOT_TELL, f"not judged: {what}")


def _claim_a(final: pd.DataFrame, setting: str) -> Claim:
    """Every learned method's return above passive's on every split present."""
    return _beats(final, setting, "a", "passive")


def _claim_f(final: pd.DataFrame, setting: str) -> Claim:
    """Every learned method's return above the scripted box gate's on every split present."""
    return _beats(final, setting, "f", "box_gate")


def _claim_g(final: pd.DataFrame, setting: str) -> Claim:
    """Every learned method's return above the scripted pose rule's on every split present."""
    return _beats(final, setting, "g", "pose_seek")


def _beats(final: pd.DataFrame, setting: str, cid: str, reference: str) -> Claim:
    """Every learned method's return above ``reference``'s on every split present (train,
    simple, hard), each comparison judged on its own; the evidence gives a verdict per
    split, the claim's verdict combines all comparisons."""
    methods = learned(final["method"].unique())
    if not methods:
        return _missing(cid, "no learned method in the results")
    present = set(final.loc[final["setting"] == setting, "split"])
    splits = [s for s in SPLITS if s in present]
    verdicts: list[str | None] = []
    groups: list[str] = []
    for split in splits:
        ref = estimate(final, reference, split, "return", setting)
        if ref.n == 0:
            continue
        parts = []
        for m in methods:
            e = estimate(final, m, split, "return", setting)
            if e.n == 0:
                parts.append((None, f"{label(m)}: no {split} rows"))
                continue
            d = difference(e, ref)
            parts.append((sign_verdict(d, +1), f"{label(m)} {e.fmt()} minus {reference} {ref.mean:.3f} = {_ci(d)}"))
        verdict, evidence = _combine(parts)
        verdicts += [v for v, _ in parts]
        groups.append(f"{split} contexts: {verdict}, {evidence}")
    if not groups:
        return _missing(cid, f"no {reference} rows in setting {setting!r}")
    verdict, _ = _combine([(v, "") for v in verdicts])
    return Claim(cid, CLAIM_TEXT[cid], verdict, " | ".join(groups))


def _claim_b(final: pd.DataFrame, setting: str) -> Claim:
    methods = learned(final["method"].unique())
    if "ibe_map" not in methods:
        return _missing("b", "IBE-MAP (method 'ibe_map') is not in the results")
    others = [m for m in methods if m != "ibe_map"]
    if not others:
        return _missing("b", "no other learned method to compare IBE-MAP with")
    parts = []
    ibe_r = estimate(final, "ibe_map", "hard", "return", setting)
    ibe_g = gengap_estimate(final, "ibe_map", setting)
    for m in others:
        r = estimate(final, m, "hard", "return", setting)
        d = difference(ibe_r, r)
        parts.append((sign_verdict(d, +1), f"hard return IBE-MAP {ibe_r.fmt()} minus {label(m)} {r.fmt()} = {_ci(d)}"))
    for m in others:
        g = gengap_estimate(final, m, setting)
        d = difference(ibe_g, g)
        parts.append((sign_verdict(d, -1), f"GenGap IBE-MAP {ibe_g.fmt()} minus {label(m)} {g.fmt()} = {_ci(d)}"))
    return Claim("b", CLAIM_TEXT["b"], *_combine(parts))


def _claim_c(final: pd.DataFrame, setting: str) -> Claim:
    methods = learned(final["method"].unique())
    absent = [m for m in ("memo_map", "map") if m not in methods]
    if absent:
        return _missing("c", f"method(s) {absent} not in the results")
    memo = gengap_estimate(final, "memo_map", setting)
    plain = gengap_estimate(final, "map", setting)
    d = difference(memo, plain)
    return Claim("c", CLAIM_TEXT["c"], *_combine(
        [(sign_verdict(d, -1), f"GenGap Memo-MAP {memo.fmt()} minus MAP {plain.fmt()} = {_ci(d)}")]))


def _claim_sweep(final: pd.DataFrame, cid: str, param: str, checks: tuple[tuple[str, int, str], ...]) -> Claim:
    methods = sweep_methods(final, param)
    if not methods:
        return _missing(cid, f"the {param} sweep was not run (no '{param}=...' settings in results.csv)")
    m = methods[0]
    rows = sweep_rows(final, param, m)
    rows = rows[rows["split"] == "hard"]
    if rows.empty:
        return _missing(cid, f"the {param} sweep of {label(m)} has no hard-split rows")
    values = sorted(rows[param].unique())
    parts = []
    for metric, want, name in checks:
        s = slope(rows[param], rows[metric])
        means = ", ".join(
            f"{param}={v:g}: {rows.loc[rows[param] == v, metric].mean():.3f}" for v in values)
        verdict = sign_verdict(s, want) if rows.groupby(param)["seed"].nunique().min() >= 2 else None
        parts.append((verdict, f"{label(m)} hard-test {name} per unit {param}: slope {_ci(s)} ({means})"))
    return Claim(cid, CLAIM_TEXT[cid], *_combine(parts))


def stand_ins(results: pd.DataFrame, lineage: dict | None) -> tuple[pd.DataFrame, list[str]]:
    """The results with a derived arm standing in for each of the paper's methods that was not
    run: where exactly one learned method derives from ``map``, ``memo_map`` or ``ibe_map``
    (``lineage``, as ``ablation.json`` records it), its rows judge that method's claims. Returns
    the results and a note per stand-in."""
    present = set(learned(results["method"].unique()))
    rename, notes = {}, []
    for paper in ("map", "memo_map", "ibe_map"):
        derived = [m for m in sorted(present) if (lineage or {}).get(m) == paper]
        if paper not in present and len(derived) == 1:
            rename[derived[0]] = paper
            notes.append(f"{label(paper)} is judged on `{derived[0]}`, the one method of this ablation derived from "
                         f"`{paper}`.")
    return (results.replace({"method": rename}) if rename else results), notes


def check_claims(results: pd.DataFrame, lineage: dict | None = None) -> list[Claim]:
    """Check claims (a)-(e) of the paper and (f), against the scripted box gate, on a results
    table (the rows of ``results.csv`` as read by
    :func:`uevavd.experiments.report_data.load_results`; final rows are selected here).
    ``lineage`` (method -> the paper's method it derives from) lets a derived arm stand in for
    one the ablation did not run (:func:`stand_ins`). Returns seven :class:`Claim` in order a..g."""
    results, notes = stand_ins(results, lineage)
    final = final_rows(results)
    setting = default_setting(final)
    b, c = _claim_b(final, setting), _claim_c(final, setting)
    if notes:
        b, c = (Claim(x.id, x.text, x.verdict, " ".join(notes) + " " + x.evidence) for x in (b, c))
    return [
        _claim_a(final, setting),
        b,
        c,
        _claim_sweep(final, "d", "thre", (("return", -1, "return"), ("path_m", +1, "path (m)"))),
        _claim_sweep(final, "e", "C", (("path_m", -1, "path (m)"), ("accuracy", -1, "accuracy"))),
        _claim_f(final, setting),
        _claim_g(final, setting),
    ]


def _late_trend(results: pd.DataFrame, method: str, setting: str, split: str = "hard") -> Estimate:
    """Slope of the raw return against training episodes (per 10^4 episodes) over the
    second half of the evaluation points, pooled over seeds."""
    curves = curve_rows(results)
    rows = curves[(curves["method"] == method) & (curves["setting"] == setting) & (curves["split"] == split)
                  & (curves["episodes"] >= 0)]
    if rows.empty:
        return Estimate.of([])
    cut = rows["episodes"].quantile(0.5)
    late = rows[rows["episodes"] >= cut]
    return slope(late["episodes"] / 1e4, late["return"])


def diagnose(results: pd.DataFrame, claims: list[Claim]) -> list[str]:
    """Facts that bear on claims that do not agree, for the report: seeds, training
    length, whether returns still rise, the room active viewing has (oracle minus
    passive), the world's own train/hard difference (passive's GenGap), and sanity
    checks of the results that would point to a bug. Empty when every claim agrees and
    no sanity check fails."""
    final = final_rows(results)
    setting = default_setting(final)
    notes: list[str] = []
    runs = final[~final["method"].isin(baselines()) & (final["episodes"] >= 0)]
    if any(c.verdict != AGREES for c in claims):
        n_seeds = runs.groupby("method")["seed"].nunique()
        if len(n_seeds) and n_seeds.min() < 5:
            span = f"{n_seeds.min()}" if n_seeds.min() == n_seeds.max() else f"{n_seeds.min()} to {n_seeds.max()}"
            notes.append(f"Runs: {span} per method (the paper uses 5 seeds); with few runs "
                         "the intervals are wide and small differences cannot be told apart.")
        if len(runs):
            ep = int(runs["episodes"].max())
            notes.append(f"Training length: {ep:,} episodes at the final point, {ep / 300_000:.1%} of the paper's "
                         "300,000.")
        for m in learned(runs["method"].unique()):
            t = _late_trend(results, m, setting)
            if t.defined and t.lo > 0:
                notes.append(f"{label(m)}'s hard-test return is still rising over the second half of training "
                             f"(slope {_ci(t, 4)} per 10^4 episodes): not converged, train longer.")
        passive = estimate(final, "passive", "hard", "return", setting)
        for ref, what in (("visibility_oracle", "flying to the most visible reachable view (the visibility "
                                                "oracle: what finding the target alone gives)"),
                          ("oracle", "the class-knowing oracle (an upper bound no image-only policy reaches)")):
            oracle = estimate(final, ref, "hard", "return", setting)
            if not (passive.n and oracle.n):
                continue
            room = oracle.mean - passive.mean
            parts = []
            for m in learned(runs["method"].unique()):
                e = estimate(final, m, "hard", "return", setting)
                if e.n and room > 0:
                    parts.append(f"{label(m)} {(e.mean - passive.mean) / room:+.0%}")
            notes.append(f"Room for active viewing on the hard-test contexts by {what}: {oracle.mean:.3f} minus "
                         f"passive {passive.mean:.3f} = {room:.3f}; share of it recovered: "
                         f"{', '.join(parts) or 'n/a'}. A small or negative room means the world leaves little "
                         "to gain by moving.")
        pg = gengap_estimate(final, "passive", setting)
        if pg.n:
            notes.append(f"The world's own train − hard difference (passive's GenGap) is {pg.mean:.3f}: this part "
                         "of every GenGap comes from the contexts, not from the policy.")
    notes += _sanity(final)
    return notes


def _sanity(final: pd.DataFrame) -> list[str]:
    """Checks that hold by construction (the episode's rules, docs/environment.md); a failure points to a bug."""
    out = []
    bad = final[(final["path_m"] - STEP_M * final["path_steps"]).abs() > 1e-6 * (1 + final["path_m"].abs())]
    if len(bad):
        out.append(f"Possible bug: path_m != {STEP_M:g} x path_steps in {len(bad)} final row(s) (e.g. "
                   f"{bad.iloc[0]['method']} seed {bad.iloc[0]['seed']} {bad.iloc[0]['split']}).")
    # With 5 classes the argmax probability is >= 0.2, so a correct argmax is recognised at thre <= 0.2
    # (up to a uniform tie): recognition should not fall below accuracy there.
    low = final[(final["thre"] <= 0.2 + 1e-9) & (final["recognition"] + 1e-6 < final["accuracy"] - 0.01)]
    if len(low):
        out.append(f"Possible bug: recognition below accuracy at thre <= 0.2 in {len(low)} final row(s) (e.g. "
                   f"{low.iloc[0]['method']} {low.iloc[0]['split']}: {low.iloc[0]['recognition']:.3f} < "
                   f"{low.iloc[0]['accuracy']:.3f}).")
    for col in ("stop_rate", "accuracy", "recognition"):
        off = final[(final[col] < -1e-9) | (final[col] > 1 + 1e-9)]
        if len(off):
            out.append(f"Possible bug: {col} outside [0, 1] in {len(off)} final row(s).")
    return out

"""The ablation report: generated from a small synthetic ablation directory, every
section and figure present; the claims give the verdicts known by construction."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pandas as pd
import pytest

from uevavd.data.grid import view_coords
from uevavd.data.layout import view_stem
from uevavd.experiments.claims import AGREES, CANNOT_TELL, DISAGREES
from uevavd.experiments.report import check_claims, write_report
from uevavd.experiments.report_data import REQUIRED_COLUMNS, final_rows, load_results
from uevavd.experiments.stats import Estimate, difference, slope

POINTS = (100, 200, 300, 400)
SCENE, CONTEXT, TARGET = "026", 26, "sedan"


def _row(method, seed, setting, thre, C, episodes, final, split, ret, path_steps=3.0, acc=0.6):
    return {"method": method, "seed": seed, "setting": setting, "thre": thre, "C": C, "episodes": episodes,
            "final": final, "split": split, "return": ret, "accuracy": acc, "recognition": min(1.0, acc + 0.1),
            "path_m": 10.0 * path_steps, "path_steps": path_steps, "stop_rate": 0.5, "steps": 3.0,
            "wall_s": 1.0 + max(episodes, 0) / 100}


def make_results(final_returns: dict, *, seeds=(0, 1), noise=0.005, passive=(-0.1, -0.2), oracle=(0.45, 0.4),
                 box_gate=(-0.05, -0.15), pose_seek=(-0.04, -0.12), thre_sweep: dict | None = None, c_sweep: dict | None = None) -> pd.DataFrame:
    """``final_returns``: method -> (train return, hard return) at the final point; each
    seed is offset by +-noise; curves ramp up linearly to the final value. Sweeps:
    setting value -> (hard return, path steps, accuracy) for ibe_map."""
    rows = []
    offsets = np.linspace(-noise, noise, len(seeds)) if len(seeds) > 1 else [0.0]

    def run(method, setting, thre, C, finals, path_steps=3.0, acc=0.6):
        for seed, off in zip(seeds, offsets, strict=True):
            for i, ep in enumerate(POINTS):
                frac = (i + 1) / len(POINTS)
                for split, value in zip(("train", "simple", "hard"), (finals[0], finals[1], finals[1]), strict=True):
                    rows.append(_row(method, seed, setting, thre, C, ep, i == len(POINTS) - 1, split,
                                     -0.3 + frac * (value + 0.3) + off, path_steps, acc))

    def baselines(setting, thre, C):
        for split, p, o in zip(("train", "simple", "hard"), (passive[0], passive[1], passive[1]),
                               (oracle[0], oracle[1], oracle[1]), strict=True):
            rows.append(_row("passive", 0, setting, thre, C, -1, True, split, p, 0.0))
            g = box_gate[0] if split == "train" else box_gate[1]
            rows.append(_row("box_gate", 0, setting, thre, C, -1, True, split, g, 1.0))
            ps = pose_seek[0] if split == "train" else pose_seek[1]
            rows.append(_row("pose_seek", 0, setting, thre, C, -1, True, split, ps, 1.0))
            rows.append(_row("oracle", 0, setting, thre, C, -1, True, split, o, 2.0, 0.9))
            for seed, off in zip(seeds, offsets, strict=True):
                rows.append(_row("random", seed, setting, thre, C, -1, True, split, -0.35 + off, 6.0, 0.4))

    for method, finals in final_returns.items():
        run(method, "default", 0.2, 0.02, finals)
    baselines("default", 0.2, 0.02)
    for name, sweep in (("thre", thre_sweep), ("C", c_sweep)):
        for value, (ret, path, acc) in (sweep or {}).items():
            thre, C = (value, 0.02) if name == "thre" else (0.2, value)
            run("ibe_map", f"{name}={value:g}", thre, C, (ret + 0.1, ret), path, acc)
            baselines(f"{name}={value:g}", thre, C)
    return pd.DataFrame(rows, columns=list(REQUIRED_COLUMNS))


def _verdicts(df):
    return {c.id: c.verdict for c in check_claims(df)}


# -- statistics ------------------------------------------------------------------------


def test_t_interval_matches_textbook():
    e = Estimate.of([1.0, 2.0, 3.0])
    # t(0.975, df=2) = 4.3027; std = 1; half-width = 4.3027 / sqrt(3)
    assert e.mean == pytest.approx(2.0) and e.std == pytest.approx(1.0)
    assert e.hi - e.mean == pytest.approx(4.3027 / math.sqrt(3), rel=1e-4)
    one = Estimate.of([0.7])
    assert one.n == 1 and not one.defined
    # a deterministic baseline adds no variance: the difference is the one-sample interval
    d = difference(Estimate.of([1.0, 2.0, 3.0]), Estimate.exact(0.5))
    assert (d.lo, d.hi) == pytest.approx((e.lo - 0.5, e.hi - 0.5))


def test_slope_of_a_noisy_line():
    x = np.repeat([0.2, 0.4, 0.6, 0.8], 3)
    y = -0.5 * x + np.tile([-0.01, 0.0, 0.01], 4)
    s = slope(x, y)
    assert s.lo < -0.5 < s.hi and s.hi < 0


# -- claims ----------------------------------------------------------------------------


def test_claims_agree_when_constructed_to():
    df = make_results(
        {"map": (0.5, 0.05), "memo_map": (0.45, 0.1), "ibe_map": (0.35, 0.3)},
        thre_sweep={0.4: (0.2, 3.5, 0.6), 0.6: (0.1, 4.0, 0.6)},
        c_sweep={0.04: (0.25, 2.5, 0.55), 0.06: (0.2, 2.0, 0.5)},
    )
    claims = check_claims(df)
    assert [c.id for c in claims] == list("abcdefg")
    assert {c.id: c.verdict for c in claims} == dict.fromkeys("abcdefg", AGREES)
    assert all("[" in c.evidence for c in claims)  # the intervals are quoted


def test_claims_disagree_when_constructed_to():
    # MAP clearly below passive, IBE-MAP below MAP with a larger gap, Memo-MAP's gap larger
    df = make_results(
        {"map": (0.2, -0.3), "memo_map": (0.6, -0.05), "ibe_map": (0.5, -0.1)},
        thre_sweep={0.4: (0.4, 2.0, 0.6), 0.6: (0.5, 1.0, 0.6)},  # return rises, path shrinks with thre
    )
    v = _verdicts(df)
    assert v["a"] == DISAGREES and v["b"] == DISAGREES and v["c"] == DISAGREES and v["d"] == DISAGREES
    assert v["e"] == CANNOT_TELL  # the C sweep was not run
    assert v["f"] == DISAGREES  # MAP's hard -0.3 is below the box gate's -0.15
    assert v["g"] == DISAGREES  # and below the pose rule's -0.12


def test_box_gate_claim_compares_with_the_box_gate_not_passive():
    # every method above passive (-0.2 on hard) but below the box gate (0.0): (a) agrees, (f) does not
    df = make_results({"map": (0.5, -0.1), "ibe_map": (0.5, -0.1)}, box_gate=(0.6, 0.0))
    claims = {c.id: c for c in check_claims(df)}
    assert claims["a"].verdict == AGREES
    assert claims["f"].verdict == DISAGREES and "minus box_gate 0.000" in claims["f"].evidence
    no_gate = df[df["method"] != "box_gate"]
    assert {c.id: c for c in check_claims(no_gate)}["f"].verdict == CANNOT_TELL


def test_pose_rule_claim_compares_with_the_pose_rule():
    # every method above the box gate (-0.15 on hard) but below the pose rule (0.1): (f) agrees, (g) does not
    df = make_results({"map": (0.5, 0.0), "ibe_map": (0.5, 0.0)}, pose_seek=(0.6, 0.1))
    claims = {c.id: c for c in check_claims(df)}
    assert claims["f"].verdict == AGREES
    assert claims["g"].verdict == DISAGREES and "minus pose_seek 0.100" in claims["g"].evidence
    assert {c.id: c for c in check_claims(df[df["method"] != "pose_seek"])}["g"].verdict == CANNOT_TELL


def test_claims_cannot_tell_when_intervals_overlap_or_one_seed():
    # differences far inside the seed noise
    df = make_results({"map": (0.3, -0.195), "ibe_map": (0.3, -0.19)}, noise=0.05)
    claims = {c.id: c for c in check_claims(df)}
    assert claims["a"].verdict == CANNOT_TELL and "overlap" in claims["a"].evidence
    assert claims["b"].verdict == CANNOT_TELL
    assert claims["c"].verdict == CANNOT_TELL and "memo_map" in claims["c"].evidence
    # one seed: clearly above passive, yet no interval -> not judged
    one = make_results({"map": (0.5, 0.4), "ibe_map": (0.5, 0.45)}, seeds=(0,))
    c = check_claims(one)[0]
    assert c.verdict == CANNOT_TELL and "fewer than two seeds" in c.evidence


def test_curves_align_seeds_evaluated_at_different_episode_counts():
    from uevavd.experiments.figures import smoothed_curves

    df = make_results({"map": (0.5, 0.1)})
    df = df[df["method"] == "map"].copy()
    df.loc[df["seed"] == 1, "episodes"] += 7  # batched training ends epochs a few episodes apart
    data = smoothed_curves(df, window=2)
    xs = data.groupby("seed")["episodes"].apply(lambda e: sorted(set(e)))
    assert xs[0] == xs[1] == [p + 3.5 for p in POINTS]
    first = data[(data["seed"] == 0) & (data["split"] == "hard")].sort_values("episodes")["return"].to_numpy()
    raw = df[(df["seed"] == 0) & (df["split"] == "hard")]["return"].to_numpy()
    assert first[1] == pytest.approx((raw[0] + raw[1]) / 2)  # trailing 2-point mean


def test_interrupted_run_uses_its_last_point():
    df = make_results({"map": (0.5, 0.1)})
    df = df[~((df["seed"] == 1) & (df["episodes"] == POINTS[-1]))]  # seed 1 stopped early, no final row
    fin = final_rows(df)
    eps = fin[(fin["method"] == "map")].groupby("seed")["episodes"].max()
    assert eps.to_dict() == {0: POINTS[-1], 1: POINTS[-2]}


# -- the report ------------------------------------------------------------------------


def _write_ablation(tmp_path, df):
    d = tmp_path / "abl"
    d.mkdir()
    df.to_csv(d / "results.csv", index=False)
    data_root = tmp_path / "data"
    paths = {"map": [302, 307, 252], "ibe_map": [302, 303], "random": [302, 2, 600, 604, 550, 555],
             "oracle": [302, 304]}
    acts = {"map": [[0, 0], [2, 4 - 4], [6, 0]], "ibe_map": [[0, 0], [6, 0]],
            "random": [[1, 3], [3, 3], [5, 1], [2, 0], [0, 0]], "oracle": [[5, 0], [6, 0]]}
    trajs = []
    for m, views in paths.items():
        for seed in (0, 1):
            trajs.append({"method": m, "seed": seed, "setting": "default", "scene": SCENE, "context": CONTEXT,
                          "split": "hard", "start_view": 302, "views": views, "actions": acts[m][: len(views)],
                          "recognized": m != "random", "correct": m != "random", "return": 0.1})
            if m == "oracle":
                del trajs[-1]["actions"]  # the runner may leave them out: read the moves off the views
    (d / "trajectories.json").write_text(json.dumps(trajs))
    folder = data_root / SCENE
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for v in sorted({v for vs in paths.values() for v in vs}):
        x, y, z = view_coords(v)
        stem = view_stem(x, y, z, TARGET, SCENE)
        cv2.imwrite(str(folder / f"{stem}.png"), rng.integers(0, 255, (32, 32, 3), dtype=np.uint8))
        (folder / f"{stem}.txt").write_text("8 8 24 24\n")
    meta = {"preset": "quick", "methods": ["map", "ibe_map"], "seeds": 2,
            "sweeps": {"thre": [0.2, 0.4, 0.6], "C": []}, "data_root": str(data_root),
            "stages": {"world": 1.5, "perception": 3.0, "train": 20.0}}
    (d / "ablation.json").write_text(json.dumps(meta))
    return d


def test_report_has_every_section_and_figure(tmp_path):
    df = make_results({"map": (0.5, 0.05), "ibe_map": (0.35, 0.3)},
                      thre_sweep={0.4: (0.2, 3.5, 0.6), 0.6: (0.1, 4.0, 0.6)})
    d = _write_ablation(tmp_path, df)
    path = write_report(d)
    assert path == d / "report" / "report.md"
    text = path.read_text(encoding="utf-8")
    for heading in ("# Ablation report: preset `quick`", "## Setup", "## Results at the final evaluation point",
                    "## Generalisation gap", "## Learning curves (Fig. 9)", "## Table 2", "## Table 3",
                    "## Observation sequences (Fig. 8)", "## Claims checked"):
        assert heading in text, heading
    assert "](fig9_curves.png)" in text and "](fig8_strips.png)" in text  # relative links
    assert "thre=0.6" in text and "The C sweep was not run" in text
    assert "could not be found" not in text  # every crop was found by its canonical name
    for claim in "abcdefg":
        assert f"**({claim})" in text
    for fig in ("fig9_curves.png", "fig8_strips.png"):
        img = cv2.imread(str(d / "report" / fig))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 200
        assert (d / "report" / fig).with_suffix(".pdf").read_bytes()[:5] == b"%PDF-"  # vector copy for papers
    summary = pd.read_csv(d / "report" / "summary.csv")
    # 2 methods + 5 baselines, 3 splits, default setting; ibe_map and baselines also in 2 thre settings
    assert len(summary) == 7 * 3 + 2 * 6 * 3
    hard = summary[(summary["setting"] == "default") & (summary["split"] == "hard")].set_index("method")
    assert hard.loc["ibe_map", "return_mean"] == pytest.approx(0.3)
    assert hard.loc["passive", "return_ci_lo"] == hard.loc["passive", "return_ci_hi"] == pytest.approx(-0.2)
    # no stray temp files from the atomic writes
    assert sorted(p.name for p in (d / "report").iterdir()) == [
        "arms.csv", "fig8_strips.pdf", "fig8_strips.png", "fig9_curves.pdf", "fig9_curves.png", "report.md",
        "summary.csv"]
    # the thre settings of IBE-MAP against its default, paired seed by seed
    arms = pd.read_csv(d / "report" / "arms.csv")
    assert set(arms["method"]) == {"ibe_map"} and "## Arms against the default" in text
    # figures=False (--no-figures): the same report but for the figure links, and the figures
    # drawn above removed, so that none of other data is left beside it
    drawn = text.split("\n")
    plain = write_report(d, figures=False).read_text(encoding="utf-8").split("\n")
    assert sorted(p.name for p in (d / "report").iterdir()) == ["arms.csv", "report.md", "summary.csv"]
    links = [i for i, line in enumerate(drawn) if line.startswith("![")]
    assert [drawn[i] for i in links] == ["![Fig. 9: learning curves](fig9_curves.png)",
                                         "![Fig. 8: observation sequences](fig8_strips.png)"]
    assert [plain[i] for i in links] == ["(Fig. 9: learning curves: not drawn, the report was written with "
                                         "`--no-figures`.)", "(Fig. 8: observation sequences: not drawn, the report "
                                         "was written with `--no-figures`.)"]
    assert [line for i, line in enumerate(drawn) if i not in links] == [
        line for i, line in enumerate(plain) if i not in links]


def test_report_without_optional_files_and_via_cli(tmp_path, capsys):
    from uevavd.cli import main

    d = tmp_path / "abl"
    d.mkdir()
    make_results({"map": (0.5, 0.05)}).to_csv(d / "results.csv", index=False)
    assert main(["report", str(d), "--no-figures"]) == 0
    text = (d / "report" / "report.md").read_text(encoding="utf-8")
    assert "`ablation.json` not found" in text and "No `trajectories.json`" in text
    assert "not drawn, the report was written with `--no-figures`" in text
    assert not list((d / "report").glob("*.png"))
    assert "(a) agrees" in capsys.readouterr().out


def test_bad_input_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="results.csv"):
        write_report(tmp_path)
    df = make_results({"map": (0.5, 0.05)}).drop(columns=["path_m"])
    df.to_csv(tmp_path / "results.csv", index=False)
    with pytest.raises(ValueError, match=r"results\.csv.*path_m"):
        load_results(tmp_path / "results.csv")


# -- exhaustive final rows, claim (a) per split, Student-t bands -------------------------


def test_claim_a_is_checked_on_every_split():
    # every method beats passive on the hard contexts, but not on the training contexts
    df = make_results({"map": (0.5, 0.05), "ibe_map": (0.55, 0.3)}, passive=(0.7, -0.2))
    a = check_claims(df)[0]
    assert a.verdict == DISAGREES
    assert "train contexts: disagrees" in a.evidence and "hard contexts: agrees" in a.evidence
    assert "simple contexts: agrees" in a.evidence
    ok = check_claims(make_results({"map": (0.5, 0.05), "ibe_map": (0.55, 0.3)}))[0]
    assert ok.verdict == AGREES and all(f"{s} contexts: agrees" in ok.evidence for s in ("train", "simple", "hard"))


def _with_exhaustive_final_rows(df, shift=0.2):
    """As the runner writes it: every curve point final=False, plus a final row per split
    (the exhaustive evaluation) at the last episode count, its return shifted."""
    runs = ~df["method"].isin(("random", "passive", "box_gate", "pose_seek", "oracle"))
    last = df[runs & df["final"]].copy()
    df = df.copy()
    df.loc[runs, "final"] = False
    last["return"] += shift
    return pd.concat([df, last], ignore_index=True)


def test_final_rows_come_from_the_exhaustive_evaluation_and_curves_do_not():
    from uevavd.experiments.report_data import curve_rows

    base = make_results({"map": (0.5, 0.05)})
    df = _with_exhaustive_final_rows(base)
    fin = final_rows(df)
    hard = fin[(fin["method"] == "map") & (fin["split"] == "hard")].sort_values("seed")
    assert hard["return"].to_numpy() == pytest.approx([0.05 - 0.005 + 0.2, 0.05 + 0.005 + 0.2])
    curves = curve_rows(df)
    assert len(curves) == len(base[base["method"] == "map"]) and not curves["final"].any()
    # an older file (last curve point flagged final, no separate row) keeps that point in the curve
    assert len(curve_rows(base)) == len(base[base["method"] == "map"])


def test_curve_band_is_the_student_t_interval_over_seeds():
    from scipy import stats

    from uevavd.experiments.figures import curve_bands, smoothed_curves

    df = make_results({"map": (0.5, 0.1)}, seeds=(0, 1, 2), noise=0.02)
    df = df[df["method"] == "map"]
    data = smoothed_curves(df, window=2)
    band = curve_bands(data, "return")
    assert len(band) == 3 * len(POINTS) and (band["n"] == 3).all()
    for _, b in band.iterrows():
        v = data[(data["split"] == b["split"]) & (data["eval_point"] == b["eval_point"])]["return"].to_numpy()
        half = stats.t.ppf(0.975, 2) * v.std(ddof=1) / math.sqrt(3)
        assert b["mean"] == pytest.approx(v.mean())
        assert (b["lo"], b["hi"]) == pytest.approx((v.mean() - half, v.mean() + half))
    one = curve_bands(smoothed_curves(df[df["seed"] == 0], window=2), "return")
    assert one["lo"].isna().all() and one["hi"].isna().all()  # one seed: no band


def test_fig9_draws_the_t_band_and_none_for_one_seed(tmp_path, monkeypatch):
    """What the curves' panels draw (the bands), read off the axes; the figures are not saved
    (saving them is test_report_has_every_section_and_figure's)."""
    import matplotlib.axes
    import matplotlib.pyplot as plt

    from uevavd.experiments import figures
    from uevavd.experiments.figures import plot_curves

    monkeypatch.setattr(figures, "save_figure", lambda fig, path: plt.close(fig) or path)

    calls = []
    real = matplotlib.axes.Axes.fill_between

    def spy(self, x, y1, y2=0, **kw):
        calls.append((np.asarray(x), np.asarray(y1), np.asarray(y2)))
        return real(self, x, y1, y2, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "fill_between", spy)
    df = make_results({"map": (0.5, 0.1)}, seeds=(0, 1, 2), noise=0.02)
    curves = df[df["method"] == "map"]
    base = df[df["method"].isin(("passive", "oracle", "random"))]
    plot_curves(curves, base, tmp_path / "a.png", window=1)
    assert len(calls) == 6  # 3 metrics x 2 splits, one method
    hard_ret = curves[(curves["split"] == "hard")].groupby("episodes")["return"]
    lo = hard_ret.mean() - stats_t975(2) * hard_ret.std(ddof=1) / math.sqrt(3)
    assert any(np.allclose(c[1], lo.to_numpy()) for c in calls)
    calls.clear()
    plot_curves(curves[curves["seed"] == 0], base, tmp_path / "b.png", window=1)
    assert calls == []


def stats_t975(df: int) -> float:
    from scipy import stats

    return float(stats.t.ppf(0.975, df))


def test_setup_says_which_rows_are_exhaustive(tmp_path):
    df = _with_exhaustive_final_rows(make_results({"map": (0.5, 0.05)}))
    df["eval_contexts"] = np.where(df["final"], 5, 2)
    d = tmp_path / "new"
    d.mkdir()
    df.to_csv(d / "results.csv", index=False)
    text = write_report(d, window=2, figures=False).read_text(encoding="utf-8")
    assert "are exhaustive: every context of each split x all 605 start views" in text
    assert "(contexts per split: train 5, simple 5, hard 5)" in text and "(train 2, simple 2, hard 2)" in text
    assert "95% Student-t interval over seeds" in text and "trailing sliding-window mean" in text
    old = tmp_path / "old"
    old.mkdir()
    make_results({"map": (0.5, 0.05)}).to_csv(old / "results.csv", index=False)
    assert "flags each run's last per-epoch evaluation" in write_report(old, figures=False).read_text(encoding="utf-8")


def test_nested_bootstrap_spans_the_recognizers_and_stays_in_range():
    """Two recognizers whose runs differ by 0.2 and agree within: the interval covers both
    recognizer means (recognizer variance counts), and never leaves the values' range."""
    from uevavd.experiments.stats import nested_bootstrap

    values = np.array([0.40, 0.41, 0.39, 0.60, 0.61, 0.59])
    groups = np.array([0, 0, 0, 1, 1, 1])
    e = nested_bootstrap(values, groups)
    assert e.mean == pytest.approx(0.5)
    assert e.lo <= 0.41 and e.hi >= 0.59  # a t-interval over the 6 runs would be [0.39, 0.61] only by luck
    assert values.min() <= e.lo and e.hi <= values.max()
    plain = Estimate.of(values)  # the iid t-interval ignores the nesting
    assert Estimate.of(values, groups=groups).lo == e.lo and plain.lo != e.lo


def test_differences_of_nested_estimates_are_paired_by_recognizer():
    """Two methods that share each recognizer's offset differ by a constant 0.05: their
    difference is exact whatever the recognizers do."""
    from uevavd.experiments.stats import nested_bootstrap

    groups = np.array([0, 0, 1, 1])
    a = nested_bootstrap(np.array([0.30, 0.30, 0.70, 0.70]), groups)
    b = nested_bootstrap(np.array([0.25, 0.25, 0.65, 0.65]), groups)
    d = difference(a, b)
    assert d.mean == pytest.approx(0.05) and (d.lo, d.hi) == pytest.approx((0.05, 0.05))
    assert a.hi - a.lo > 0.3


def test_results_with_two_recognizers_use_the_nested_interval(tmp_path):
    from uevavd.experiments.report_data import estimate, final_rows, load_results

    rows = []
    for r, base in ((0, 0.3), (1, 0.6)):
        for s in range(3):
            rows.append({"method": "map", "recognizer": r, "seed": s, "setting": "default", "thre": 0.2, "C": 0.02,
                         "episodes": 100, "final": True, "split": "hard", "return": base + 0.01 * s,
                         "accuracy": 0.5, "recognition": 0.5, "path_m": 10.0, "path_steps": 1.0, "stop_rate": 1.0,
                         "steps": 2.0, "wall_s": 1.0})
        rows.append({**rows[-1], "method": "passive", "seed": 0, "episodes": -1, "return": base})
    pd.DataFrame(rows).to_csv(tmp_path / "results.csv", index=False)
    df = load_results(tmp_path / "results.csv")
    final = final_rows(df)
    e = estimate(final, "map", "hard", "return", "default")
    assert e.n == 6 and e.boot is not None and e.lo < 0.35 and e.hi > 0.6
    p = estimate(final, "passive", "hard", "return", "default")  # one value per recognizer: not exact
    assert p.n == 2 and p.hi - p.lo > 0.2
    d = difference(e, p)  # paired by recognizer: map is passive + 0.01 on average
    assert d.mean == pytest.approx(0.01) and d.hi - d.lo < 0.03


def test_curve_bands_stay_in_the_metrics_range():
    from uevavd.experiments.figures import curve_bands

    data = pd.DataFrame({"method": "map", "split": "train", "eval_point": 0, "episodes": 100.0,
                         "seed": [0, 1], "recognition": [0.99, 0.2], "path_m": [0.0, 30.0]})
    rec = curve_bands(data, "recognition").iloc[0]
    assert 0.0 <= rec["lo"] and rec["hi"] <= 1.0
    assert curve_bands(data, "path_m").iloc[0]["lo"] >= 0.0


def test_the_report_shows_the_stopping_diagnosis_per_split_and_terrain(tmp_path):
    df = make_results({"map": (0.5, 0.05), "ibe_map": (0.4, 0.1)})
    df["box_start"], df["moved_if_box"], df["box_lost"], df["reco_lost"] = 0.6, 0.3, 0.05, 0.04
    df.loc[df["method"].isin(("passive", "box_gate", "pose_seek")), ["moved_if_box", "box_lost"]] = 0.0
    df["gated_return"] = np.where(df["episodes"] >= 0, df["return"] + 0.05, np.nan)
    d = tmp_path / "abl"
    d.mkdir()
    df.to_csv(d / "results.csv", index=False)
    ctx = []
    for m, ret in (("ibe_map", 0.1), ("passive", 0.2)):
        for c, terrain, moved in ((26, "urban (shifted)", 0.2), (56, "woodland", 0.6)):
            ctx.append({"method": m, "recognizer": 0, "seed": 0, "setting": "default", "split": "hard", "context": c,
                        "target": "sedan", "terrain": terrain, "return": ret, "accuracy": 0.5, "recognition": 0.6,
                        "path_m": 10.0, "stop_rate": 1.0, "steps": 1.0, "box_start": 0.5,
                        "moved_if_box": moved if m == "ibe_map" else 0.0, "box_lost": 0.1,
                        "reco_lost": 0.1, "gated_return": ret + 0.05 if m == "ibe_map" else np.nan})
    pd.DataFrame(ctx).to_csv(d / "contexts.csv", index=False)
    text = write_report(d, window=2, figures=False).read_text(encoding="utf-8")
    section = text[text.index("## Stopping"):]
    assert "| hard | IBE-MAP | 60% | 30% | 5% |" in section and "| hard | Box gate (scripted) |" in section
    # the gated difference is paired by run: every run gains exactly 0.05
    assert "+0.050 [+0.050, +0.050]" in section
    assert "| woodland | IBE-MAP | 1 | 50% | 60% |" in section and "| urban (shifted) | Passive |" in section
    # each learned method against IBE-MAP, passive and the box gate: MAP's hard return is 0.05 below
    # IBE-MAP's, 0.25 above passive's, 0.20 above the box gate's; per terrain from contexts.csv
    against = section[section.index("| split | policy | return | minus IBE-MAP | minus passive | minus box gate |"):]
    map_hard = next(line for line in against.splitlines() if line.startswith("| hard | MAP |"))
    assert "| -0.050 [" in map_hard and "| +0.250 [" in map_hard and "| +0.200 [" in map_hard
    assert "| hard, woodland | IBE-MAP | 0.100 | | -0.100 |" in against.replace("|  |", "| |")
    old = tmp_path / "old"  # results written before the diagnosis: the section says why it is not there
    old.mkdir()
    make_results({"map": (0.5, 0.05)}).to_csv(old / "results.csv", index=False)
    text = write_report(old, window=2, figures=False).read_text(encoding="utf-8")
    assert "## Stopping" in text and "Not written: results.csv has no column(s) ['box_start'," in text


def test_report_refuses_a_results_table_cut_mid_row(tmp_path, capsys, monkeypatch):
    """A results.csv cut mid-row reported exit 0 and turned claim (f) from "cannot tell" to "agrees"."""
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    d = _write_ablation(tmp_path, make_results({"map": (0.5, 0.05), "ibe_map": (0.35, 0.3)}))
    text = (d / "results.csv").read_text()
    (d / "results.csv").write_text(text[: text.rindex(",", 0, len(text) - 40)])  # the last row loses its end
    assert main(["report", str(d)]) == 2
    err = capsys.readouterr().err.strip()
    lines = len(text[: text.rindex(",", 0, len(text) - 40)].splitlines())
    assert "\n" not in err and f"results.csv, line {lines}:" in err and "fields where the header has" in err


def test_the_room_table_gives_each_policy_its_share_of_the_oracles_gain_by_kind_of_start(tmp_path):
    from uevavd.experiments.report_room import room_section

    df = make_results({"map": (0.5, 0.05), "ibe_map": (0.35, 0.3)})
    vis = df[df["method"] == "oracle"].assign(method="visibility_oracle")
    df = pd.concat([df, vis], ignore_index=True)
    # a third of the starts have the box in view; on the others passive -0.3, the oracle +0.1
    returns = {"passive": (0.2, -0.3), "visibility_oracle": (0.3, 0.1), "map": (0.1, -0.2), "ibe_map": (0.2, 0.0)}
    df["box_start"] = 1 / 3
    for m, (box, hidden) in returns.items():
        df.loc[df["method"] == m, ["box_return", "hidden_return"]] = (box, hidden)
    final = final_rows(df)
    lines = room_section(final, "default", tmp_path)
    table = {tuple(c.strip() for c in line.split("|")[1:3]): [c.strip() for c in line.split("|")[3:-1]]
             for line in lines if line.startswith("| hard")}
    assert table[("hard", "box hidden")][:4] == ["67%", "-0.300", "0.100", "+0.400"]
    # box gate and pose rule (no room columns in their rows here), MAP, IBE-MAP
    assert table[("hard", "box hidden")][4:] == ["–", "–", "-0.200 (+25%)", "0.000 (+75%)"]
    assert table[("hard", "box in view")][6:] == ["0.100 (-100%)", "0.200 (+0%)"]
    assert room_section(final.drop(columns=["hidden_return"]), "default", tmp_path) == []  # earlier results
    assert room_section(final[final["method"] != "visibility_oracle"], "default", tmp_path) == []
    # the rule's departure ceilings, where evaluated, stand beside the visibility oracle
    ceiling = df[df["method"] == "oracle"].assign(method="departure_ceiling", box_return=0.4, hidden_return=0.5)
    lines = room_section(final_rows(pd.concat([df, ceiling], ignore_index=True)), "default", tmp_path)
    header = next(line for line in lines if line.startswith("| where"))
    assert [c.strip() for c in header.split("|")[6:9]] == ["room", "Pose rule, one exact departure (ceiling)",
                                                          "Box gate (scripted)"]
    hidden = next(line for line in lines if line.startswith("| hard | box hidden"))
    assert [c.strip() for c in hidden.split("|")[6:8]] == ["+0.400", "0.500 (+200%)"]


def test_the_start_kinds_split_the_return():
    from uevavd.env import EnvConfig, evaluate_policy
    from uevavd.env.baselines import RandomPolicy
    from uevavd.testing.policy import toy_table

    table = toy_table(n_train=1, n_hard=2, feature_dim=8)
    boxes = np.array(table.boxes)
    boxes[:, ::3] = 0.0  # a third of the views hide the target
    from uevavd.table import ObservationTable

    hidden = ObservationTable.from_arrays(np.array(table.features), np.array(table.probs), boxes,
                                          scenes=list(table.scenes), contexts=list(table.contexts),
                                          targets=list(table.targets), splits=list(table.splits))
    s = evaluate_policy(hidden, "hard", RandomPolicy(0), EnvConfig()).summary()
    assert 0.3 < 1 - s["box_start"] < 0.4
    assert s["box_start"] * s["box_return"] + (1 - s["box_start"]) * s["hidden_return"] == pytest.approx(
        s["mean_return"])

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
                 thre_sweep: dict | None = None, c_sweep: dict | None = None) -> pd.DataFrame:
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
    assert [c.id for c in claims] == list("abcde")
    assert {c.id: c.verdict for c in claims} == dict.fromkeys("abcde", AGREES)
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
    for claim in "abcde":
        assert f"**({claim})" in text
    for fig in ("fig9_curves.png", "fig8_strips.png"):
        img = cv2.imread(str(d / "report" / fig))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 200
    summary = pd.read_csv(d / "report" / "summary.csv")
    # 2 methods + 3 baselines, 3 splits, default setting; ibe_map and baselines also in 2 thre settings
    assert len(summary) == 5 * 3 + 2 * 4 * 3
    hard = summary[(summary["setting"] == "default") & (summary["split"] == "hard")].set_index("method")
    assert hard.loc["ibe_map", "return_mean"] == pytest.approx(0.3)
    assert hard.loc["passive", "return_ci_lo"] == hard.loc["passive", "return_ci_hi"] == pytest.approx(-0.2)
    # no stray temp files from the atomic writes
    assert sorted(p.name for p in (d / "report").iterdir()) == [
        "fig8_strips.png", "fig9_curves.png", "report.md", "summary.csv"]


def test_report_without_optional_files_and_via_cli(tmp_path, capsys):
    from uevavd.cli import main

    d = tmp_path / "abl"
    d.mkdir()
    make_results({"map": (0.5, 0.05)}).to_csv(d / "results.csv", index=False)
    assert main(["report", str(d)]) == 0
    text = (d / "report" / "report.md").read_text(encoding="utf-8")
    assert "`ablation.json` not found" in text and "No `trajectories.json`" in text
    assert "(a) agrees" in capsys.readouterr().out


def test_bad_input_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="results.csv"):
        write_report(tmp_path)
    df = make_results({"map": (0.5, 0.05)}).drop(columns=["path_m"])
    df.to_csv(tmp_path / "results.csv", index=False)
    with pytest.raises(ValueError, match=r"results\.csv.*path_m"):
        load_results(tmp_path / "results.csv")

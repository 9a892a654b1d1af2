"""The report's aggregate statistics (rliable): scores normalised per context between passive and
the oracle, the IQM / optimality gap / mean, the probability of improvement and the performance
profiles; the rliable parts skip cleanly without the ``rliable`` extra."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from uevavd.experiments import report_rliable as R


def _contexts(rng: np.random.Generator) -> pd.DataFrame:
    """2 recognizers x 3 seeds x 5 hard contexts; context 5 has no room (oracle = passive)."""
    rows = []
    floor = {(r, c): 0.1 * c + 0.05 * r for r in range(2) for c in range(1, 6)}
    room = {(r, c): (0.4 if c < 5 else 0.0) for r in range(2) for c in range(1, 6)}
    for r in range(2):
        for c in range(1, 6):
            base = {"recognizer": r, "setting": "default", "split": "hard", "context": c}
            rows.append({**base, "method": "passive", "seed": 0, "return": floor[r, c]})
            rows.append({**base, "method": "oracle", "seed": 0, "return": floor[r, c] + room[r, c]})
            rows.append({**base, "method": "box_gate", "seed": 0, "return": floor[r, c] + 0.1 * room[r, c]})
            for s in range(3):
                rows.append({**base, "method": "ibe_map", "seed": s,
                             "return": floor[r, c] + room[r, c] * (0.5 + 0.01 * rng.standard_normal())})
                rows.append({**base, "method": "map", "seed": s, "return": floor[r, c] - 0.2 * room[r, c]})
    return pd.DataFrame(rows)


def test_scores_are_normalised_per_context_between_passive_and_the_oracle():
    scores = R.score_matrices(_contexts(np.random.default_rng(0)), "default", "hard")
    assert set(scores) == {"map", "ibe_map", "passive", "box_gate"}
    assert all(s.shape == (6, 4) for s in scores.values())  # 2 x 3 runs; context 5 (no room) left out
    np.testing.assert_allclose(scores["passive"], 0.0)
    np.testing.assert_allclose(scores["box_gate"], 0.1)  # a baseline scores each seed of its recognizer alike
    np.testing.assert_allclose(scores["map"], -0.2)
    np.testing.assert_allclose(scores["ibe_map"], 0.5, atol=0.05)
    assert R.score_matrices(_contexts(np.random.default_rng(0)).query("method != 'oracle'"), "default", "hard") == {}


def test_the_fast_probability_of_improvement_is_rliables():
    pytest.importorskip("rliable", reason="the rliable extra is not installed")
    if not R.rliable_available():
        pytest.skip("rliable does not import here (arch under pandas 3): pip install -e '.[rliable]'")
    from rliable import metrics

    rng = np.random.default_rng(1)
    x, y = rng.integers(0, 4, (5, 7)).astype(float), rng.integers(0, 4, (8, 7)).astype(float)  # with ties
    assert R.probability_of_improvement(x, y) == pytest.approx(metrics.probability_of_improvement(x, y))


def test_the_report_section_on_a_small_ablation(tmp_path):
    pytest.importorskip("rliable", reason="the rliable extra is not installed")
    if not R.rliable_available():
        pytest.skip("rliable does not import here (arch under pandas 3): pip install -e '.[rliable]'")
    lines = R.rliable_section(_contexts(np.random.default_rng(0)), "default", tmp_path, reps=200, profile_reps=50)
    text = "\n".join(lines)
    assert "## Aggregate statistics (rliable)" in text
    assert "| hard | Passive | 6 x 4 | 0.000 [0.000, 0.000] | 1.000 [1.000, 1.000] | 0.000 [0.000, 0.000] |" in text
    assert "| hard | MAP | 6 x 4 | -0.200 [-0.200, -0.200] | 1.200 [1.200, 1.200] |" in text
    assert "| hard | MAP | IBE-MAP | 0.000 [0.000, 0.000] |" in text  # every run of IBE-MAP beats every run of MAP
    assert "| hard | IBE-MAP | Box gate (scripted) | 1.000 [1.000, 1.000] |" in text
    assert (tmp_path / "performance_profiles.png").stat().st_size > 0
    again = R.rliable_section(_contexts(np.random.default_rng(0)), "default", tmp_path, reps=200, profile_reps=50)
    assert again == lines  # a fixed random state: the same report twice


def test_without_rliable_the_section_says_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.setattr(R, "rliable_available", lambda: False)
    text = "\n".join(R.rliable_section(_contexts(np.random.default_rng(0)), "default", tmp_path))
    assert "pip install -e \".[rliable]\"" in text and not (tmp_path / "performance_profiles.png").exists()

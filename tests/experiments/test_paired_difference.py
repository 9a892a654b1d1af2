"""benchmarks/paired_difference.py: its pairing with a baseline is the report's own, number for
number, and it refuses a folder or method it cannot pair."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "paired_difference.py"
FOLDER = ROOT / "docs" / "results" / "mirror-quick-world2"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT)


def test_a_method_minus_a_baseline_is_the_reports_difference():
    out = _run(str(FOLDER), "--a", "ibe_map_boxpose_rule", "--b", "pose_seek", "--split", "hard")
    assert out.returncode == 0, out.stderr
    row = next(line for line in out.stdout.splitlines() if line.startswith("| hard | all |"))
    diff = row.rsplit("|", 2)[-2].strip()
    report = (FOLDER / "report.md").read_text(encoding="utf-8")
    label = "IBE-MAP (box + pose state, pose rule where the box is hidden)"
    cell = re.search(rf"^\| hard \| {re.escape(label)} \| [^|]+\| [^|]+\| [^|]+\| ([^|]+) \|$", report, re.M)
    assert cell is not None
    assert diff == cell.group(1).strip()  # the report's "minus pose rule", interval and all


def test_two_folders_pool_their_recognizers_and_bad_input_exits_2(tmp_path):
    out = _run(str(FOLDER), str(ROOT / "docs" / "results" / "rule-quick-world2"), "--a", "ibe_map_boxpose_rule",
               "--b", "pose_seek", "--split", "hard")
    assert out.returncode == 0, out.stderr
    assert "| hard | all | 4 | 20 |" in out.stdout
    missing = _run(str(tmp_path), "--a", "x", "--b", "y")
    assert missing.returncode == 2 and "contexts.csv not found" in missing.stderr
    unknown = _run(str(FOLDER), "--a", "nope", "--b", "pose_seek")
    assert unknown.returncode == 2 and "no method 'nope'" in unknown.stderr
    assert "Traceback" not in missing.stderr + unknown.stderr


def test_each_recognizers_own_difference_averages_to_the_pooled_one():
    folder = ROOT / "docs" / "results" / "reco4-quick-world2"
    out = _run(str(folder), "--a", "ibe_map_boxpose_rule_reco", "--b", "pose_seek", "--split", "hard", "--by-recognizer")
    assert out.returncode == 0, out.stderr
    pooled = next(line for line in out.stdout.splitlines() if line.startswith("| hard | all |"))
    own = [line for line in out.stdout.splitlines() if line.startswith(f"| hard | {folder}:")]
    assert len(own) == 4 and all("| 5 |" in line for line in own)  # 4 recognizers of 5 seeds each

    def mean(line: str) -> float:
        return float(line.rsplit("|", 2)[-2].split("[")[0])

    # the pooled estimate is the mean of the recognizers' means (the two-stage bootstrap's point)
    assert abs(sum(mean(line) for line in own) / 4 - mean(pooled)) < 0.001
    assert min(mean(line) for line in own) < 0 < max(mean(line) for line in own)  # a gain only some give


def test_by_world_makes_the_world_the_unit(tmp_path):
    results = ROOT / "docs" / "results"
    folders = [results / f for f in ("reco4-quick-world2", "reco4-quick-world3", "reco4-quick-world7")]
    out = _run(*map(str, folders), "--a", "ibe_map_boxpose_rule", "--b", "pose_seek", "--split", "hard", "--by-world")
    assert out.returncode == 0, out.stderr
    rows = {line.split("|")[2].strip(): line for line in out.stdout.splitlines() if line.startswith("| hard | ")}

    def mean(line: str) -> tuple[float, float, float]:
        cell = line.rsplit("|", 2)[-2]
        m, lo, hi = cell.replace("[", " ").replace("]", " ").replace(",", " ").split()
        return float(m), float(lo), float(hi)

    each = [mean(rows[f"quick world {w}"]) for w in (2, 3, 7)]
    over = mean(rows["mean over 3 worlds"])
    assert abs(sum(m for m, _, _ in each) / 3 - over[0]) < 0.001  # the mean of the worlds' differences
    # each world's own estimate is the pooled one of that folder alone
    alone = _run(str(folders[1]), "--a", "ibe_map_boxpose_rule", "--b", "pose_seek", "--split", "hard")
    assert rows["quick world 3"].rsplit("|", 2)[-2] == \
        next(line for line in alone.stdout.splitlines() if line.startswith("| hard | all |")).rsplit("|", 2)[-2]
    # worlds that disagree (3 above the rule, 7 below) give an interval over worlds wider than any world's own
    assert over[2] - over[1] > max(hi - lo for _, lo, hi in each)
    # a folder without its ablation.json cannot be placed in a world: one line, exit 2
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "contexts.csv").write_bytes((folders[0] / "contexts.csv").read_bytes())
    refused = _run(str(bare), "--a", "ibe_map_boxpose_rule", "--b", "pose_seek", "--by-world")
    assert refused.returncode == 2 and "ablation.json" in refused.stderr and "Traceback" not in refused.stderr

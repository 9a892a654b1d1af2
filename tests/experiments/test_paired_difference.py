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

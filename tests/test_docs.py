"""The README and the docs as a newcomer meets them: the README short, every published result
indexed in docs/results.md with the figures its folder holds, no issue numbers anywhere a user
reads, and every relative link pointing at a file that exists."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _index():
    spec = importlib.util.spec_from_file_location("results_index", ROOT / "benchmarks" / "results_index.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_is_read_in_a_minute():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    words = len(re.sub(r"```.*?```", "", text, flags=re.S).split())
    assert len(text.splitlines()) <= 150 and words <= 1300, (len(text.splitlines()), words)
    paragraphs = [p for p in re.split(r"\n\s*\n", re.sub(r"```.*?```", "", text, flags=re.S)) if p.strip()]
    long = [p[:60] for p in paragraphs if len(p.split()) > 150]
    assert not long, f"README paragraphs over 150 words: {long}"
    first = text.split("##", 1)[0]
    for command in ('pip install -e . && uevavd demo', 'pip install -e ".[test]" && pytest'):
        assert command in first, command


def test_every_published_result_is_in_the_index_with_its_figures():
    index = _index()
    text = (DOCS / "results.md").read_text(encoding="utf-8")
    folders = sorted(p.name for p in (DOCS / "results").iterdir() if p.is_dir())
    for folder in folders:
        assert f"### {folder}\n" in text, f"docs/results.md does not list docs/results/{folder}"
        assert "\n".join(index.table(folder)) in text, f"docs/results.md's {folder} table is not its summary.csv's"
        assert folder in index.COMMANDS


def test_no_issue_numbers_where_a_user_reads():
    places = [ROOT / "README.md", *DOCS.glob("*.md"), *(ROOT / "uevavd").rglob("*.py"),
              *(ROOT / "model_zoo" / "methods").glob("*.toml")]
    found = [f"{p.relative_to(ROOT)}:{i}" for p in places
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if re.search(r"\bissues? \d+", line, re.I)]
    assert not found, f"issue numbers (commit messages keep them): {found}"


def test_relative_links_point_at_files_that_exist():
    broken = []
    for page in [ROOT / "README.md", *DOCS.glob("*.md")]:
        text = re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S))
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text):
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, f"links to missing files: {broken}"

"""The README and the docs as a newcomer meets them: the README short, every published result
indexed in docs/results.md with the figures its folder holds, no issue numbers anywhere a user
reads, every relative link pointing at a file that exists, and the API reference covering the
public API and building from the docstrings with warnings as errors."""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

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


def _reference() -> dict[str, str]:
    """Every object the API reference documents (``::: dotted.path``), by its last name."""
    paths = [p for page in (DOCS / "api").glob("*.md")
             for p in re.findall(r"^::: (\S+)", page.read_text(encoding="utf-8"), re.M)]
    return {p.rsplit(".", 1)[-1]: p for p in paths}


def test_the_api_reference_covers_the_public_api():
    import uevavd
    import uevavd.env
    from uevavd.plugins import hookspecs

    documented = _reference()
    public = [*uevavd.__all__, *uevavd.env.__all__]
    missing = [n for n in public if n not in documented and n != "registry"]
    assert not missing, f"public names the API reference (docs/api/) does not document: {missing}"
    assert "uevavd.registry" in (DOCS / "api" / "python-api.md").read_text(encoding="utf-8")
    assert "hookspecs" in documented and all(hasattr(hookspecs, h) for h in dir(hookspecs) if h.startswith("register_"))
    for protocol in ("StateEstimator", "QHead", "Policy"):  # the state, head and baseline protocols
        assert protocol in documented, protocol


def test_every_object_in_the_api_reference_has_a_docstring():
    griffe = pytest.importorskip("griffe", reason="the docs extra (mkdocstrings) brings griffe")
    package = griffe.GriffeLoader(search_paths=[str(ROOT)]).load("uevavd")
    bare = []
    for path in _reference().values():
        obj = package[path.removeprefix("uevavd.")]
        bare += [path] if not obj.docstring else []
        if obj.is_class:
            bare += [f"{path}.{name}" for name, m in obj.members.items()
                     if not name.startswith("_") and not m.is_alias and (m.is_function or m.is_class) and not m.docstring]
    assert not bare, f"documented without a docstring: {bare}"


@pytest.mark.skipif(shutil.which("mkdocs") is None and importlib.util.find_spec("mkdocs") is None,
                    reason="the docs extra (mkdocs) is not installed")
def test_the_api_reference_builds_with_warnings_as_errors(tmp_path):
    pytest.importorskip("mkdocstrings", reason="the docs extra is not installed")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    page = (tmp_path / "site" / "environment" / "index.html").read_text(encoding="utf-8")
    assert "uevavd.env.aod_env.AODEnv" in page and "Start an episode" in page  # rendered from the docstrings


#: Pages for contributors, naming internals by design (the API reference is for users).
CONTRIBUTOR_PAGES = {"architecture.md", "faults.md"}


def _public_objects() -> dict[str, set[str]]:
    """Every public class and function defined in a public module of uevavd, by name: its
    dotted paths (a module whose optional dependency is absent is skipped)."""
    import importlib
    import inspect
    import pkgutil

    import uevavd

    found: dict[str, set[str]] = {}
    for info in pkgutil.walk_packages(uevavd.__path__, "uevavd."):
        if any(part.startswith("_") for part in info.name.split(".")):
            continue
        try:
            module = importlib.import_module(info.name)
        except ImportError:
            continue
        for name, obj in vars(module).items():
            if (not name.startswith("_") and (inspect.isclass(obj) or inspect.isfunction(obj))
                    and getattr(obj, "__module__", None) == info.name):
                found.setdefault(name, set()).add(f"{info.name}.{obj.__qualname__}")
    return found


def _names_the_docs_use() -> dict[str, set[str]]:
    """Every name a user page imports from uevavd (``from uevavd.x import A, B``), calls by its
    dotted path (``uevavd.x.A(``), or calls by name in a code block or inline code (``A(``), with
    the pages using it (README and docs/, not the contributor pages nor the reference)."""
    used: dict[str, set[str]] = {}
    for page in [ROOT / "README.md", *DOCS.glob("*.md")]:
        if page.name in CONTRIBUTOR_PAGES:
            continue
        text = page.read_text(encoding="utf-8")
        imports = [*re.findall(r"from (uevavd(?:\.\w+)*) import \(([^)]*)\)", text),
                   *re.findall(r"from (uevavd(?:\.\w+)*) import ([\w ,]+)", text)]
        names = {entry.split()[0] for _, entries in imports for entry in entries.split(",") if entry.split()}
        names |= {p.rsplit(".", 1)[-1] for p in re.findall(r"\b(uevavd(?:\.\w+)+)\(", text)}
        code = "\n".join(re.findall(r"```.*?```", text, flags=re.S))
        names |= set(re.findall(r"(?<![\w.])([A-Za-z_]\w*)\(", code)) | set(re.findall(r"`([A-Za-z_]\w*)\(", text))
        for name in names:
            used.setdefault(name, set()).add(page.name)
    return used


def test_every_name_a_page_imports_or_calls_is_in_the_api_reference():
    """The guides taught names the reference lacked (FlatTransitions, SB3VecEnv, the scripted
    baselines, uevavd.testing's checks): every public class or function of uevavd that a user
    page imports or calls is documented in docs/api/ (itself, or its module whole)."""
    objects = _public_objects()
    documented = set(_reference().values())
    missing = []
    for name, pages in sorted(_names_the_docs_use().items()):
        if name.startswith("_") or name not in objects:
            continue
        paths = objects[name]
        if not any(p in documented or p.rsplit(".", 1)[0] in documented for p in paths) \
                and name not in _reference():
            missing.append(f"{name} ({sorted(paths)[0]}; {', '.join(sorted(pages))})")
    assert not missing, f"names the docs use that the API reference (docs/api/) lacks: {missing}"


def _minutes(page: Path) -> float:
    """Reading time at 240 words a minute (58,000 words in about four hours), code left out."""
    return len(re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S).split()) / 240


def test_the_docs_map_lists_every_page_and_the_main_path_reads_in_20_minutes():
    text = (DOCS / "README.md").read_text(encoding="utf-8")
    unlisted = [p.name for p in DOCS.glob("*.md") if p.name != "README.md" and f"]({p.name}" not in text]
    assert not unlisted, f"docs/README.md does not list {unlisted}"
    path = text.split("## The main path", 1)[1].split("\n## ", 1)[0]
    pages = [DOCS / target for target in re.findall(r"\]\(([^)#]+\.md)\)", path)]
    assert len(pages) >= 3 and sum(_minutes(p) for p in pages) <= 20, [(p.name, _minutes(p)) for p in pages]


def test_no_page_names_a_file_the_repository_does_not_have():
    """A page's `benchmarks/x.py`, `tests/...::test`, `docs/x.md`, `uevavd/...` or `model_zoo/...`
    file exists: pages pointed to a DESIGN.md the repository lacks, and to a test file renamed."""
    missing = []
    for page in [ROOT / "README.md", *DOCS.glob("*.md"), *(DOCS / "api").glob("*.md")]:
        for path in re.findall(r"`((?:benchmarks|tests|docs|uevavd|model_zoo)/[\w./-]+?)(?:::\w+)?`",
                               page.read_text(encoding="utf-8")):
            if "*" not in path and "." in path.rsplit("/", 1)[-1] and not (ROOT / path).exists():  # a file
                missing.append(f"{page.relative_to(ROOT)}: {path}")
    assert not missing, f"pages name files the repository does not have: {missing}"


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    return {re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
            for line in text.splitlines() if line.startswith("#")}


def test_every_link_to_a_section_finds_it():
    """Sections moved between pages (results and measurements out of the how-to pages) leave no
    link pointing at a heading that is gone."""
    broken = []
    for page in [ROOT / "README.md", *DOCS.glob("*.md")]:
        text = re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S))
        for target, fragment in re.findall(r"\]\(([^)#:\s]*)#([^)\s]+)\)", text):
            dest = page.parent / target if target else page
            if dest.suffix == ".md" and dest.is_file() and fragment not in _anchors(dest):
                broken.append(f"{page.relative_to(ROOT)} -> {target}#{fragment}")
    assert not broken, f"links to sections that do not exist: {broken}"


def test_the_config_reference_holds_every_section_and_built_in_component():
    """Every config key with its default: the training and perception sections, and every
    built-in component's builder (whose arguments are its section's keys)."""
    from uevavd.plugins.manager import manager

    documented = set(_reference().values())
    want = {"uevavd.policy.config.TrainConfig", "uevavd.config.PerceptionSection", "uevavd.env.config.EnvConfig"}
    for kind in ("segmenter", "encoder", "classifier", "state", "head"):
        want |= {e.target.replace(":", ".") for e in manager.registry.in_order(kind) if e.plugin.startswith("uevavd")}
    assert not want - documented, f"the API reference lacks {sorted(want - documented)}"


def test_the_install_notes_and_the_demos_output_are_where_a_new_user_needs_them():
    """A plain install resolved pandas 3 with rliable's arch, which fails to import: the README
    names the [rliable] extra; it names the venv's size and the CPU-only torch route; the demo's
    default output folder, written into the current folder, is ignored by git."""
    import argparse

    from uevavd.experiments.cli import add_demo

    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert '.[rliable]' in readme and "download.pytorch.org/whl/cpu" in readme and "6 GB" in readme
    parser = argparse.ArgumentParser()
    add_demo(parser)
    out = parser.parse_args([]).out
    ignored = subprocess.run(["git", "check-ignore", "-q", f"{out}/report.md"], cwd=ROOT)
    if ignored.returncode == 128:
        pytest.skip("not a git checkout")
    assert ignored.returncode == 0, f"the demo's default output {out}/ is not ignored by git"

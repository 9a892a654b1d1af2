"""The package's shape (docs/architecture.md): no module-level import cycle, no module over
400 lines, and imports of its own modules inside functions only where the map says why."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

import uevavd

ROOT = Path(uevavd.__file__).resolve().parent
MAX_LINES = 400
#: modules that may run longer because one job needs them whole, with their own limit; their
#: functions stay short instead (a split made only for length leaks private names)
ONE_JOB = {"table.py": 480}  # the observation table: build, check, select, save and load one contract
ONE_JOB_FUNCTION_LINES = 50
#: where an import of the package's own modules may sit inside a function, and why
LAZY_MODULES = {"api.py", "info.py"}  # the lazy CLI and API
MUTUAL = {  # a module and the one it uses lazily: the two use each other
    ("data/synthetic/world.py", "render"),
    ("perception/training/classifier.py", "report"),
    ("perception/training/report.py", "classifier"),
}
OPTIONAL = {("experiments/references.py", "env.sb3")}  # Stable-Baselines3, only for --sb3


@functools.cache
def _modules(root: Path = ROOT) -> dict[str, tuple[Path, ast.Module]]:
    """Each module of the package at ``root`` (benchmarks/architecture_figures.py reads
    another checkout's) by dotted name, with its path and syntax tree; parsed once per root
    (the checks only read them)."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        rel = p.relative_to(root.parent).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        out[name] = (p, ast.parse(p.read_text(encoding="utf-8")))
    return out


@pytest.fixture(autouse=True, scope="module")
def _drop_the_trees():
    """The syntax trees (about 600,000 objects) go when this module's tests end: kept, every
    later full garbage collection of the worker walks them."""
    yield
    _modules.cache_clear()


def _target(mods, name: str, path: Path, node: ast.ImportFrom) -> list[str]:
    pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    if node.level:
        parts = pkg.split(".")
        base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
    else:
        base = node.module or ""
    found = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
    return [f for f in found if f in mods]


def _own_import(node: ast.AST) -> bool:
    return isinstance(node, ast.ImportFrom) and bool(node.level or (node.module or "").startswith("uevavd"))


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The cycles a depth-first walk of ``graph`` (module -> the modules it imports) meets."""
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(u: str, stack: list[str]) -> None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == 1:
                cycles.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    return cycles


def test_no_module_level_import_cycle():
    mods = _modules()
    graph = {}
    for name, (path, tree) in mods.items():
        deps = set()
        for node in tree.body:
            if _own_import(node):
                deps |= set(_target(mods, name, path, node))
        graph[name] = deps - {name}
    cycles = _cycles(graph)
    assert not cycles, f"module-level import cycles: {cycles}"


def test_no_module_over_the_limit():
    long = {rel: n for p, _ in _modules().values()
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > ONE_JOB.get(rel := str(p.relative_to(ROOT)),
                                                                                   MAX_LINES)}
    assert not long, f"modules over {MAX_LINES} lines (or their ONE_JOB limit): {long}"


def test_a_longer_module_keeps_its_functions_short():
    modules = {str(p.relative_to(ROOT)): tree for p, tree in _modules().values()}
    assert set(ONE_JOB) <= set(modules), f"ONE_JOB names modules that do not exist: {set(ONE_JOB) - set(modules)}"
    long = [f"{rel}:{fn.name} ({fn.end_lineno - fn.lineno + 1} lines)" for rel in ONE_JOB
            for fn in ast.walk(modules[rel]) if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef)
            and fn.end_lineno - fn.lineno + 1 > ONE_JOB_FUNCTION_LINES]
    assert not long, f"functions over {ONE_JOB_FUNCTION_LINES} lines in a module allowed to be longer: {long}"


def test_function_level_own_imports_only_where_the_map_allows():
    unexplained = []
    for _name, (path, tree) in _modules().items():
        rel = str(path.relative_to(ROOT))
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if not _own_import(node):
                    continue
                mod = node.module or ""
                allowed = (
                    path.name in ("cli.py", "__init__.py") or rel in LAZY_MODULES
                    or (node.level and not mod)  # uevavd.__version__ or a sibling package's lazy export
                    or (rel, mod) in MUTUAL or (rel, mod) in OPTIONAL
                )
                if not allowed:
                    unexplained.append(f"{rel}:{node.lineno} from {'.' * node.level}{mod}")
    assert not unexplained, ("imports of the package's own modules inside functions, not explained in "
                             f"docs/architecture.md: {unexplained}; import them at module level")


def test_no_private_name_is_imported_across_modules():
    """A name that starts with ``_`` is its module's own: another module that needs it gets
    it public (a review found 26 such names in 10 imports, left by 400-line splits)."""
    leaks = []
    for _name, (path, tree) in _modules().items():
        for node in ast.walk(tree):
            if _own_import(node):
                private = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                if private:
                    leaks.append(f"{path.relative_to(ROOT)}:{node.lineno} {private}")
    assert not leaks, f"private names imported from other modules: {leaks}; make them public in their module"


def _runtime_imports(tree: ast.Module):
    """Every import statement of the package's own modules, at any depth, except those under
    ``if TYPE_CHECKING:`` (annotations for readers and type checkers, never run)."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING":
            skip.update(id(n) for n in ast.walk(node))
    return [n for n in ast.walk(tree) if _own_import(n) and id(n) not in skip]


def test_the_whole_import_graph_has_no_cycle_beside_the_written_lazy_edges():
    """Function-level imports included: the only edges that may close a cycle are the lazy
    loading of the command line and of package ``__init__`` files (``uevavd --help`` and
    ``import uevavd`` stay light) and the mutual pairs of :data:`MUTUAL` (docs/architecture.md,
    "Imports inside functions")."""
    mods = _modules()
    graph: dict[str, set[str]] = {}
    for name, (path, tree) in mods.items():
        rel = str(path.relative_to(ROOT))
        if path.name in ("__init__.py", "cli.py"):  # the written lazy edges
            graph[name] = set()
            continue
        graph[name] = {t for node in _runtime_imports(tree) for t in _target(mods, name, path, node)
                       if t != name and (rel, node.module) not in MUTUAL}
    cycles = _cycles(graph)
    assert not cycles, f"import cycles outside the written lazy edges: {cycles}"


#: The layers, bottom first (docs/architecture.md draws the same order): a module may import its
#: own layer and those below it. Each package's ``cli.py`` and the entry modules form the top
#: layer, the commands: they load the layers lazily. A name is a module or a package (all its
#: modules); the longest match decides.
LAYERS = (
    ("foundation", ("uevavd.version", "uevavd.paths", "uevavd.atomic", "uevavd.hashing", "uevavd.runtime")),
    ("plugins", ("uevavd.plugins",)),
    ("config", ("uevavd.config_rules", "uevavd.config_layers", "uevavd.config")),
    ("data", ("uevavd.data",)),
    ("presets", ("uevavd.presets",)),
    ("table", ("uevavd.table", "uevavd.toy")),
    ("perception", ("uevavd.perception",)),
    ("zoo", ("uevavd.zoo",)),
    ("env", ("uevavd.env",)),
    ("state", ("uevavd.state",)),
    ("policy", ("uevavd.policy",)),
    ("pretrained", ("uevavd.pretrained",)),
    ("experiments", ("uevavd.experiments",)),
    ("testing", ("uevavd.testing",)),
    ("commands", ("uevavd", "uevavd.cli", "uevavd.api", "uevavd.info")),
)
#: Imports allowed to go up, each with its reason (none today).
UPWARD_ALLOWED: dict[tuple[str, str], str] = {}
#: Import cycles (every import counted: module level, inside functions, under TYPE_CHECKING) are
#: allowed inside one layer only, and at most this many.
MAX_CYCLES = 3


def _layer(module: str) -> int:
    if module == "uevavd.cli" or module.endswith(".cli"):
        return len(LAYERS) - 1
    best = max(((len(name), i) for i, (_, names) in enumerate(LAYERS) for name in names
                if module == name or module.startswith(name + ".")), default=None)
    assert best is not None, f"{module} is in no layer of tests/test_architecture.py's LAYERS"
    return best[1]


def _all_edges(root: Path = ROOT) -> dict[str, set[str]]:
    """module -> the package's modules it imports, every import statement counted."""
    mods = _modules(root)
    return {name: {t for node in ast.walk(tree) if _own_import(node) for t in _target(mods, name, path, node)
                   if t != name} for name, (path, tree) in mods.items()}


def upward_imports(root: Path = ROOT) -> list[str]:
    """Each import of a module of a higher layer, as ``importer -> imported (layer -> layer)``."""
    out = []
    for name, deps in _all_edges(root).items():
        for dep in sorted(deps):
            if _layer(dep) > _layer(name) and (name, dep) not in UPWARD_ALLOWED:
                out.append(f"{name} -> {dep} ({LAYERS[_layer(name)][0]} -> {LAYERS[_layer(dep)][0]})")
    return out


def test_every_import_goes_down_the_layers():
    up = upward_imports()
    assert not up, f"imports going up the layers (docs/architecture.md): {up}"


def test_import_cycles_stay_inside_one_layer_and_are_few():
    cycles = _cycles(_all_edges())
    across = [c for c in cycles if len({LAYERS[_layer(m)][0] for m in c}) > 1]
    assert not across, f"import cycles between layers: {across}"
    assert len(cycles) <= MAX_CYCLES, f"{len(cycles)} import cycles, at most {MAX_CYCLES}: {cycles}"


def test_the_layer_check_fails_on_an_import_going_up(tmp_path):
    """The check itself: a copy of the package with one upward import added is refused."""
    import shutil

    copy = tmp_path / "uevavd"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns("__pycache__", "model_zoo"))
    env = copy / "env" / "config.py"
    env.write_text(env.read_text(encoding="utf-8") + "\nfrom ..experiments import runner  # noqa\n", encoding="utf-8")
    assert upward_imports(copy) == ["uevavd.env.config -> uevavd.experiments.runner (env -> experiments)"]
    assert not upward_imports(ROOT)

"""Shared test setup: plugin autoload off, caches in a temporary folder, one thread."""

from __future__ import annotations

import atexit
import gc
import os
import pickle
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

# Third-party plugins installed in the environment must not change what tests see.
os.environ.setdefault("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "1")
# The xdist workers keep every core busy, so an OpenMP thread that spins while it waits for
# work takes a core another worker needs (a 2-thread recognizer fit beside a busy core: 10.9 s
# spinning, 5.1 s sleeping). Set here, before any worker or subprocess imports torch; results
# do not depend on it (it changes how idle threads wait, not how work is split).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# A test process holds about half a million long-lived objects (torch, scipy, pandas and the
# session's builds), and each full garbage collection walks them all: 0.15 to 0.5 s, about
# twenty times per worker (8.8 s in both). A full collection after every 100 younger ones
# instead of 10 (Python's default) walks them four times; young garbage is still collected as
# often, and no test depends on when a cycle is freed.
gc.set_threshold(*gc.get_threshold()[:2], 100)


def _ram_temproot(mounts: Path = Path("/proc/mounts"), folder: str = "/dev/shm", room: int = 3 << 30) -> str | None:
    """``folder`` where it is a RAM disk (tmpfs) with ``room`` bytes free, else None. The
    suite writes tens of thousands of small files (worlds, tables, runs; about 1 GB at its
    peak): on a journaling disk creating them costs ten times the CPU it does in RAM."""
    try:
        tmpfs = any(line.split()[1:3] == [folder, "tmpfs"] for line in mounts.read_text().splitlines())
        st = os.statvfs(folder)
    except OSError:
        return None
    return folder if tmpfs and st.f_bavail * st.f_frsize >= room else None


# pytest's own numbered temporary folders (kept and cleaned as usual), on a RAM disk where
# there is one with room; --basetemp or a PYTEST_DEBUG_TEMPROOT of the user's own wins
if "PYTEST_XDIST_WORKER" not in os.environ and (_ram := _ram_temproot()):
    os.environ.setdefault("PYTEST_DEBUG_TEMPROOT", _ram)
    if "TMPDIR" not in os.environ:  # and the system temp folder of the suite's processes (the zoo's render
        # check, Ray's session files, SB3's logs): one of the session's own, removed when it ends
        os.environ["TMPDIR"] = _tmp = tempfile.mkdtemp(prefix="uevavd-tests-", dir=_ram)
        tempfile.tempdir = None  # read TMPDIR again
        atexit.register(shutil.rmtree, _tmp, True)


if "PYTEST_XDIST_WORKER" in os.environ:
    @atexit.register  # before any library a test imports registers its own: this one runs after theirs
    def _end_the_worker_now() -> None:
        """Leave an xdist worker once its exit handlers have run, without the interpreter's
        teardown: it frees every object of the session one by one (2 to 4 s after the suite,
        which the controller waits for). The results went to the controller before."""
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


#: The tests that run on a local Ray instance, in this order and one after the other: they
#: share one (starting it, and the imports of its task process, cost about 10 s each time).
#: The xdist scheduler runs the second in the first's module's scope, after that module's tests.
RAY_TESTS = ("tests/experiments/test_runner.py::test_ray_backend_gives_the_local_results",
             "tests/perception/test_prepare.py::test_ray_backend_builds_the_same_table")


def pytest_collection_modifyitems(items):
    """The Ray tests after the first one's module's last test, one after the other."""
    ray_items = [next((i for i in items if i.nodeid == n), None) for n in RAY_TESTS]
    if None in ray_items:  # a test renamed, or not selected: each starts its own instance
        return
    for item in ray_items:
        items.remove(item)
    module = ray_items[0].nodeid.split("::")[0]
    at = max((k for k, i in enumerate(items) if i.nodeid.split("::")[0] == module), default=len(items) - 1) + 1
    items[at:at] = ray_items


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadscope``, but for the Ray tests, which share the first one's scope."""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    first = RAY_TESTS[0].rsplit("::", 1)[0]

    class RayTogether(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return first if nodeid in RAY_TESTS else super()._split_scope(nodeid)

    return RayTogether(config, log)


@pytest.fixture
def local_ray():
    """A local Ray instance of one CPU (one task process: less startup), shared by the Ray
    tests that run one after the other and stopped after the last of them."""
    ray = pytest.importorskip("ray")
    if not ray.is_initialized():
        ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    return ray


def pytest_runtest_teardown(item, nextitem):
    """Stop the local Ray instance after the last test of a run of tests that share it (an idle
    instance takes about 8% of a core); nothing where Ray is not installed."""
    ray = sys.modules.get("ray")
    if ray is not None and "local_ray" in getattr(item, "fixturenames", ()) and (
            nextitem is None or "local_ray" not in getattr(nextitem, "fixturenames", ())):
        ray.shutdown()


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(shared):
    """One uevavd cache for the session's workers, in the folder they share: a recognizer or
    table one worker built is found by the other (the cache is keyed by content and safe to
    share between processes); tests that change a cache use their own."""
    cache = shared.root / "uevavd-cache"
    cache.mkdir(exist_ok=True)
    os.environ["UEVAVD_CACHE"] = str(cache)
    yield


@pytest.fixture(autouse=True, scope="session")
def _threads():
    try:
        import torch

        from uevavd.runtime import usable_cores

        # the cores shared among pytest-xdist's workers (addopts runs -n auto): oversubscribed
        # torch threads wait on each other and run many times slower
        workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        torch.set_num_threads(max(1, min(2, usable_cores() // workers)))
    except ImportError:  # pragma: no cover
        pass
    yield


class SharedBuilds:
    """Things a test only reads, built once per test session for all xdist workers: in a folder
    beside the workers' own temporary folders, under a file lock, written to a temporary name
    and renamed (a worker that waits on the lock finds it whole). Without xdist, in the
    session's temporary folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)

    def once(self, name: str, build) -> Path:
        """``self.root / name``, made by ``build(path)`` where no worker made it before."""
        from filelock import FileLock

        path = self.root / name
        with FileLock(str(self.root / f"{name}.lock")):
            if not path.exists():
                tmp = self.root / f".{name}.tmp"
                shutil.rmtree(tmp, ignore_errors=True)
                build(tmp)
                tmp.rename(path)
        return path

    def once_with(self, name: str, build) -> tuple[Path, Any]:
        """``(folder, value)``: ``build(folder)`` writes the folder and returns a value the
        tests need beside it (pickled, so a worker that did not build it reads it back)."""

        def build_and_keep(tmp: Path) -> None:
            value = build(tmp / "root")
            tmp.mkdir(exist_ok=True)
            (tmp / "value.pkl").write_bytes(pickle.dumps(value))

        path = self.once(name, build_and_keep)
        return path / "root", pickle.loads((path / "value.pkl").read_bytes())

    def tiny_world(self, contexts: tuple[int, ...], train605: bool) -> Path:
        """:func:`uevavd.testing.worlds.write_tiny_world` of these contexts (read it only)."""
        from uevavd.testing.worlds import write_tiny_world

        name = "world-" + "-".join(map(str, contexts)) + ("-605" if train605 else "")
        return self.once(name, lambda tmp: write_tiny_world(tmp, contexts=contexts, train605=train605))


@pytest.fixture(scope="session")
def shared(tmp_path_factory) -> SharedBuilds:
    """The session's :class:`SharedBuilds`, in a folder beside the xdist workers' own."""
    base = tmp_path_factory.getbasetemp()
    return SharedBuilds((base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-builds")


@pytest.fixture(scope="session")
def synthetic_root(shared) -> Path:
    """One hard-test context (26) of the synthetic world at 16 px, written by its writer (world
    seed 1, whose draw the validity search finds: no record of it); read it only."""
    synthetic = pytest.importorskip("uevavd.data.synthetic")
    return shared.once("synthetic-26", lambda out: synthetic.write_world(out, contexts=[26], size=16, seed=1,
                                                                          include_unoccluded=False, progress=False))


@pytest.fixture(scope="session")
def ablation_world(shared) -> Path:
    """The tiny world the ablation tests run on: contexts 1 (train) and 26 (hard) of the
    hatchback block, 31 / 56 of the pickup block, and train_605 (read it only)."""
    return shared.tiny_world((1, 26, 31, 56), train605=True)

"""Where the test suite's time goes: its slowest tests, its slowest fixtures and each xdist
worker's load, from one run of the README's test command (nothing else should run beside it).

    python benchmarks/suite_profile.py                 # the whole suite, as the README runs it
    python benchmarks/suite_profile.py tests/env -n 0  # any pytest arguments after the script's

It runs pytest with a small plugin (this file, loaded with ``-p``) that records, in every worker,
each test's setup / call / teardown and each fixture's setup (a session or module fixture is
built once, inside the first test that asks for it, so --durations alone cannot tell it from
the test), then prints:

- the wall time pytest reports, and each worker's busy time and last finish (how evenly
  ``--dist`` spread the work: the suite ends when the last worker does);
- the slowest tests (setup + call + teardown) and the slowest fixture setups;
- the time per test file.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_OUT = "UEVAVD_SUITE_PROFILE"  # the folder each worker writes its records to


# -- the plugin (runs inside pytest and its workers) ------------------------------------------------
_records: list[dict] = []
_start = time.perf_counter()


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef, request):
    t0 = time.perf_counter()
    yield
    _records.append({"kind": "fixture", "name": fixturedef.argname, "scope": fixturedef.scope,
                     "seconds": time.perf_counter() - t0, "test": request.node.nodeid})


def pytest_runtest_logreport(report):
    _records.append({"kind": "phase", "test": report.nodeid, "phase": report.when, "seconds": report.duration,
                     "end": time.perf_counter() - _start})


def pytest_sessionfinish(session):
    folder = os.environ.get(_OUT)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        Path(folder, f"{worker}.json").write_text(json.dumps(_records))


# -- the report --------------------------------------------------------------------------------------
def _table(rows: list[tuple], header: tuple) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]

    def line(r: tuple) -> str:
        return "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)
                         for i, (c, w) in enumerate(zip(r, widths, strict=True)))

    return "\n".join([line(header), *(line(r) for r in rows)])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=25, help="rows per table")
    args, pytest_args = ap.parse_known_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        env = {**os.environ, _OUT: folder, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "benchmarks"),
                                                                                       os.environ.get("PYTHONPATH")]))}
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "suite_profile", *pytest_args], cwd=ROOT,
                              env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        summary = [line for line in done.stdout.splitlines() if " passed" in line or " failed" in line]
        records = {p.stem: json.loads(p.read_text()) for p in Path(folder).glob("*.json")}
    if len(records) > 1:  # xdist: the controller sees its workers' reports again; the workers' count
        records.pop("main", None)
    if not records:
        print(done.stdout[-3000:], done.stderr[-3000:], sep="\n")
        return done.returncode or 1
    print(f"pytest: {summary[-1] if summary else '(no summary)'}; {wall:.1f} s wall with startup")
    tests: dict[str, float] = defaultdict(float)
    files: dict[str, float] = defaultdict(float)
    workers = []
    for worker, recs in sorted(records.items()):
        phases = [r for r in recs if r["kind"] == "phase"]
        busy = sum(r["seconds"] for r in phases)
        workers.append((worker, f"{busy:.1f}", f"{max((r['end'] for r in phases), default=0):.1f}",
                        len({r["test"] for r in phases})))
        for r in phases:
            tests[r["test"]] += r["seconds"]
            files[r["test"].split("::")[0]] += r["seconds"]
    print("\nworkers (busy s, last finish s after its start, tests):")
    print(_table(workers, ("worker", "busy", "finish", "tests")))
    total = sum(tests.values())
    print(f"\nslowest tests (setup + call + teardown; {len(tests)} tests, {total:.1f} s in all):")
    print(_table([(t, f"{s:.2f}", f"{s / total:.1%}") for t, s in sorted(tests.items(), key=lambda x: -x[1])[:args.top]],
                 ("test", "s", "share")))
    fixtures: dict[tuple, list[float]] = defaultdict(list)
    for recs in records.values():
        for r in recs:
            if r["kind"] == "fixture":
                fixtures[(r["name"], r["scope"])].append(r["seconds"])
    print("\nslowest fixtures (setup, summed over the times each was built):")
    rows = sorted(fixtures.items(), key=lambda x: -sum(x[1]))[:args.top]
    print(_table([(f"{n} ({scope})", f"{sum(v):.2f}", len(v)) for (n, scope), v in rows], ("fixture", "s", "built")))
    print("\ntime per file:")
    print(_table([(f, f"{s:.1f}", f"{s / total:.1%}") for f, s in sorted(files.items(), key=lambda x: -x[1])[:args.top]],
                 ("file", "s", "share")))
    return done.returncode


if __name__ == "__main__":
    raise SystemExit(main())

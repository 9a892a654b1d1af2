"""A cold `uevavd demo` (empty cache, fresh output folder), timed stage by stage, for this
checkout and optionally a baseline checkout, alternately, in the same hour.

    python benchmarks/cold_demo.py [--baseline DIR] [--rounds 2]

``--baseline DIR`` is another checkout (e.g. ``git worktree add /tmp/base <commit>``): its
package runs the same command through ``PYTHONPATH``. Each run gets a fresh temporary
``UEVAVD_CACHE`` and output folder. Prints, per run, the machine-speed reference
(``../shared/tools/refwork.py``, seconds of a fixed CPU workload) measured just before it,
the demo's total and stage times and their multiples of that reference; then each
checkout's median and the ratio. Also checks that the runs printed the same hard-split table
digit for digit. Nothing else should run meanwhile (2 cores: a second heavy job slows
both).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine_speed import refwork_seconds as refwork

ROOT = Path(__file__).resolve().parents[1]
STAGES = re.compile(r"demo finished in (\d+) s \((.*)\) on")


def cold_demo(checkout: Path) -> tuple[float, dict[str, float], str]:
    """(wall seconds, {stage: seconds}, hard-split table) of one cold demo run by ``checkout``."""
    with tempfile.TemporaryDirectory(prefix="uevavd-cold-") as tmp:
        env = {**os.environ, "PYTHONPATH": str(checkout), "UEVAVD_CACHE": str(Path(tmp) / "cache")}
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-c", "import sys; from uevavd.cli import entry; sys.exit(entry())",
                              "demo", "--out", str(Path(tmp) / "demo")],
                             env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if run.returncode:
        sys.exit(f"cold_demo: the demo of {checkout} exited {run.returncode}:\n{run.stderr[-2000:]}")
    found = STAGES.search(run.stdout)
    if not found:
        sys.exit(f"cold_demo: no closing line in the demo's output of {checkout}")
    stages = {name: float(sec) for name, sec in re.findall(r"(\w+) (\d+) s", found.group(2))}
    hard = run.stdout.split("hard contexts", 1)[-1].split("\ndemo finished", 1)[0]
    return wall, stages, hard


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, default=None, help="another checkout to time alternately")
    ap.add_argument("--rounds", type=int, default=2, help="runs of each checkout (default 2)")
    args = ap.parse_args()
    checkouts = {"this": ROOT} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    walls: dict[str, list[float]] = {k: [] for k in checkouts}
    tables = set()
    for r in range(args.rounds):
        for name, path in (reversed(checkouts.items()) if r % 2 else checkouts.items()):
            ref = refwork()
            wall, stages, hard = cold_demo(path)
            walls[name].append(wall)
            tables.add(hard)
            per = ", ".join(f"{k} {v:.0f}" for k, v in stages.items())
            times = f" = {wall / ref:.0f} x refwork" if ref else ""
            print(f"{name:8s} round {r}: refwork {ref} s; demo {wall:.0f} s{times} ({per})", flush=True)
    for name, w in walls.items():
        print(f"{name:8s} median {statistics.median(w):.0f} s over {len(w)} runs")
    if args.baseline:
        ratio = statistics.median(walls["baseline"]) / statistics.median(walls["this"])
        print(f"baseline / this: {ratio:.2f}x")
    print("hard-split tables: " + ("the same digit for digit in every run" if len(tables) == 1
                                   else f"{len(tables)} different tables (see the demos' outputs)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

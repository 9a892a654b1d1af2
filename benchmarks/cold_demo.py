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

With ``--cores`` each run also samples the machine's busy cores (``/proc/stat``, every
0.5 s) and prints, per stage (from the demo's ``[stage] ...`` and ``[stage] done`` lines, the
start-up before the first stage included), its seconds, the cores it kept busy on average and
the core-seconds left idle: how much overlapping the stages could still win.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from itertools import pairwise
from pathlib import Path

from machine_speed import refwork_seconds as refwork

ROOT = Path(__file__).resolve().parents[1]
STAGES = re.compile(r"demo finished in (\d+) s \((.*)\) on")
STAGE_LINE = re.compile(r"^\[(\w+)\] (?:\.\.\.|done in)")


def _cpu_times() -> tuple[int, int]:
    """(all, idle) jiffies of the machine so far, from the first line of ``/proc/stat``."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v), v[3] + v[4]  # idle + iowait


class CoreSampler:
    """Busy cores every ``period`` seconds (``/proc/stat``) in a thread: ``samples`` holds
    (seconds since ``t0``, busy cores over the period before it)."""

    def __init__(self, t0: float, period: float = 0.5) -> None:
        self.t0, self.period, self.cores = t0, period, os.cpu_count() or 1
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = _cpu_times()
        while not self._stop.wait(self.period):
            now = _cpu_times()
            total, idle = now[0] - last[0], now[1] - last[1]
            self.samples.append((time.perf_counter() - self.t0, self.cores * (total - idle) / max(total, 1)))
            last = now

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def mean(self, a: float, b: float) -> float:
        """Average busy cores over (a, b] seconds (nan without a sample there)."""
        got = [u for t, u in self.samples if a < t <= b]
        return sum(got) / len(got) if got else float("nan")


def cold_demo(checkout: Path, cores: bool = False) -> tuple[float, dict[str, float], str, list[tuple[str, float, float]]]:
    """(wall seconds, {stage: seconds}, hard-split table, [(stage, seconds, busy cores)]) of one
    cold demo run by ``checkout``; the last list only with ``cores``."""
    with tempfile.TemporaryDirectory(prefix="uevavd-cold-") as tmp:
        env = {**os.environ, "PYTHONPATH": str(checkout), "UEVAVD_CACHE": str(Path(tmp) / "cache")}
        t0 = time.perf_counter()
        sampler = CoreSampler(t0) if cores else None
        marks: list[tuple[float, str]] = [(0.0, "start-up")]
        with open(Path(tmp) / "stderr", "w+") as err:
            proc = subprocess.Popen([sys.executable, "-c", "import sys; from uevavd.cli import entry; sys.exit(entry())",
                                     "demo", "--out", str(Path(tmp) / "demo")],
                                    env=env, stdout=subprocess.PIPE, stderr=err, text=True, bufsize=1)
            out = []
            for line in proc.stdout:
                out.append(line)
                found = STAGE_LINE.match(line)
                if found:
                    marks.append((time.perf_counter() - t0, found.group(1) if "..." in line else "between stages"))
            proc.wait()
            wall = time.perf_counter() - t0
            err.seek(0)
            stderr = err.read()
        if sampler:
            sampler.stop()
    stdout = "".join(out)
    if proc.returncode:
        sys.exit(f"cold_demo: the demo of {checkout} exited {proc.returncode}:\n{stderr[-2000:]}")
    found = STAGES.search(stdout)
    if not found:
        sys.exit(f"cold_demo: no closing line in the demo's output of {checkout}")
    stages = {name: float(sec) for name, sec in re.findall(r"(\w+) (\d+) s", found.group(2))}
    hard = stdout.split("hard contexts", 1)[-1].split("\ndemo finished", 1)[0]
    use = []
    if sampler:
        bounds = [*marks, (wall, "end")]
        use = [(name, b - a, sampler.mean(a, b)) for (a, name), (b, _) in pairwise(bounds)
               if b - a >= 0.5]
    return wall, stages, hard, use


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, default=None, help="another checkout to time alternately")
    ap.add_argument("--rounds", type=int, default=2, help="runs of each checkout (default 2)")
    ap.add_argument("--cores", action="store_true", help="also print each stage's busy cores (/proc/stat)")
    args = ap.parse_args()
    if args.cores and not Path("/proc/stat").is_file():
        sys.exit("cold_demo: --cores reads /proc/stat, which this system does not have (Linux only)")
    checkouts = {"this": ROOT} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    walls: dict[str, list[float]] = {k: [] for k in checkouts}
    tables = set()
    for r in range(args.rounds):
        for name, path in (reversed(checkouts.items()) if r % 2 else checkouts.items()):
            ref = refwork()
            wall, stages, hard, use = cold_demo(path, args.cores)
            walls[name].append(wall)
            tables.add(hard)
            per = ", ".join(f"{k} {v:.0f}" for k, v in stages.items())
            times = f" = {wall / ref:.0f} x refwork" if ref else ""
            print(f"{name:8s} round {r}: refwork {ref} s; demo {wall:.0f} s{times} ({per})", flush=True)
            if use:
                n = os.cpu_count() or 1
                for stage, sec, busy in use:
                    print(f"    {stage:15s} {sec:6.1f} s, {busy:4.2f} of {n} cores busy, "
                          f"{sec * (n - busy):5.1f} core-seconds idle")
                idle = sum(sec * (n - busy) for _, sec, busy in use if busy == busy)
                print(f"    all stages: {idle:.0f} core-seconds idle, {idle / n:.0f} s if every one were filled",
                      flush=True)
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

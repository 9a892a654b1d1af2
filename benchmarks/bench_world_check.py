"""What checking a cached world costs: every scene's files hashed against its scene.json (the
check before each scene kept a stamp) against the stamp's stat per file, in one process.

    python benchmarks/bench_world_check.py [--preset quick] [--rounds 2]

The preset's world comes from the cache (`uevavd synth`; built here when absent). Each round
removes the stamps and checks every scene (each file read and hashed, then the stamp written),
then checks again (a stat per file). Prints seconds, views per second and the ratio, with the
machine's refwork beside them.
"""

from __future__ import annotations

import argparse
import json
import time

from machine_speed import refwork


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="quick", help="preset whose world (default quick)")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()

    from uevavd.data.synthetic import writer
    from uevavd.experiments.plan import make_plan
    from uevavd.experiments.stages import stage_world

    plan = make_plan(preset=args.preset, out="/tmp/uevavd-bench-world-check", methods=["map"])
    root = stage_world(plan, lambda _: None)
    size, seed = int(plan.preset["world"]["size"]), int(plan.preset["world"]["seed"])
    scenes = sorted(p for p in root.iterdir() if (p / "scene.json").is_file())
    views = sum((len(json.loads((p / 'scene.json').read_text())['files']) - 1) // 3 for p in scenes)
    print(f"{args.preset} world {root.name}: {len(scenes)} scenes, {views} views; {refwork()}")
    print("| round | hashed (no stamps) | stat only (stamps) | ratio |")
    print("|---|---|---|---|")
    for r in range(args.rounds):
        for p in scenes:
            (p / writer._STAMP).unlink(missing_ok=True)
        t0 = time.perf_counter()
        assert all(writer.scene_complete(p, size=size, seed=seed) for p in scenes)
        hashed = time.perf_counter() - t0
        t0 = time.perf_counter()
        assert all(writer.scene_complete(p, size=size, seed=seed) for p in scenes)
        stat = time.perf_counter() - t0
        print(f"| {r + 1} | {hashed:.2f} s ({views / hashed:,.0f} views/s) | {stat:.2f} s ({views / stat:,.0f} "
              f"views/s) | {hashed / stat:.1f}x |")
    print(refwork())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

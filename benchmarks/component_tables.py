"""What one more component value costs an ablation's tables stage: the default's table and the
table of one swept encoder value, each built from an empty table cache in this process, and the
ratio of the second to the first. An encoder value should cost one table like the first (image
decoding, decomposition and the recognizer's pass are the same work), plus the difference of the
encoders' own forward passes; nothing else of the ablation is repeated (its world, its
recognizers and the default's runs are shared).

    python benchmarks/component_tables.py --world W                     # the quick world, IBE-MAP
    python benchmarks/component_tables.py --world W --value '{name="resnet50",weights="random"}'

W is a synthetic world the quick preset made (``$UEVAVD_CACHE/worlds/world-<digest>``). Prints
each table's seconds and views per second, the ratio, and ``refwork`` (seconds of a fixed CPU
workload, ../shared/tools/refwork.py) before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from machine_speed import refwork


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--world", required=True, type=Path, help="a quick-preset synthetic world")
    ap.add_argument("--method", default="ibe_map")
    ap.add_argument("--value", default='{name="resnet18",weights="random"}',
                    help="the swept perception.encoder value (a TOML inline table)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    print(refwork())
    with tempfile.TemporaryDirectory(prefix="uevavd-bench-") as tmp:
        os.environ["UEVAVD_CACHE"] = tmp  # empty table cache; the recognizer comes from the model zoo
        from uevavd.experiments.axes import parse_sweeps
        from uevavd.experiments.plan import make_plan
        from uevavd.experiments.stages import stage_classifier
        from uevavd.perception.prepare import prepare_table
        from uevavd.table import ObservationTable

        plan = make_plan(preset="quick", out=Path(tmp) / "out", methods=[args.method], data=args.world,
                         sweeps=parse_sweeps([f"perception.encoder={args.value}"]), sweep_methods=[args.method],
                         workers=args.workers, recognizers=1)
        classifier = stage_classifier(plan, args.world, lambda *_: None)[0]
        times = []
        for name, setting in plan.settings(args.method):
            t0 = time.perf_counter()
            path = prepare_table(args.world, plan.spec(args.method, setting), classifier_path=classifier,
                                 workers=args.workers, progress=False)
            dt = time.perf_counter() - t0
            views = ObservationTable.load(path).features.shape[0] * ObservationTable.load(path).features.shape[1]
            times.append(dt)
            print(f"{name:<50} {dt:7.1f} s  {views / dt:7.0f} views/s  table {path.name}")
        print(f"extra value / first table: {times[1] / times[0]:.2f}x")
    print(refwork())
    return 0


if __name__ == "__main__":
    sys.exit(main())

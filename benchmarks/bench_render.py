"""Rendering speed of the synthetic world, one process (issue 3, part 7).

Prints views per second at 128 and 256 px on a training (urban) and a hard-test (woodland)
context, over a spread of viewpoints, with wall-clock and CPU time (the machine is shared:
CPU time is the steadier figure), and the ratio against the same renderer without per-view
culling (every primitive cast over the whole frame) measured in the same run on a few views.

    OMP_NUM_THREADS=1 python benchmarks/bench_render.py [--views 121] [--sizes 128,256]

Goals: >= 100 views/s at 128 px and >= 30 views/s at 256 px.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from uevavd.data.grid import N_VIEWS  # noqa: E402
from uevavd.data.synthetic import build_context, render_view  # noqa: E402
from uevavd.data.synthetic.render import _Prep  # noqa: E402


def _time(scene, views, size, cull=True) -> tuple[float, float]:
    prep = _Prep(scene)
    render_view(scene, views[0], size, prep, cull=cull)  # warm-up (imports, first shadow tiles)
    w0, c0 = time.perf_counter(), time.process_time()
    for v in views:
        render_view(scene, int(v), size, prep, cull=cull)
    n = len(views)
    return n / (time.perf_counter() - w0), n / (time.process_time() - c0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=121, help="viewpoints per measurement (spread over 605)")
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--contexts", default="1,26")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    views = np.linspace(0, N_VIEWS - 1, args.views).round().astype(int)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {len(views)} views each")
    print(f"{'context':>8} {'size':>5} {'views/s wall':>13} {'views/s cpu':>12} {'no-cull cpu':>12} {'ratio':>6}")
    for cid in (int(c) for c in args.contexts.split(",")):
        scene = build_context(cid, seed=args.seed)
        for size in (int(s) for s in args.sizes.split(",")):
            wall, cpu = _time(scene, views, size)
            _, ref = _time(scene, views[:: max(len(views) // 8, 1)], size, cull=False)
            print(f"{cid:>8} {size:>5} {wall:>13.1f} {cpu:>12.1f} {ref:>12.1f} {cpu / ref:>5.1f}x", flush=True)


if __name__ == "__main__":
    main()

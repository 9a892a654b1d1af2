"""Rendering speed of the synthetic world, one process.

Prints views per second at 128 and 256 px on a training (urban) and a hard-test (woodland)
context, over a spread of viewpoints, with wall-clock and CPU time (the machine is shared:
CPU time is the steadier figure), and the ratio against the same renderer without per-view
culling (every primitive cast over the whole frame) measured in the same run on a few views.

    OMP_NUM_THREADS=1 python benchmarks/bench_render.py [--views 121] [--sizes 128,256]
    OMP_NUM_THREADS=1 python benchmarks/bench_render.py --against /tmp/old   # old: a checkout

``--against DIR`` also times the renderer of another checkout (DIR holds its ``uevavd``
package, e.g. ``mkdir /tmp/old && git archive 851b8f2 uevavd | tar -x -C /tmp/old``) in
the same process, interleaved view by view with this one, and prints each one's views/s
from the minimum CPU time of ``--repeats`` renders per view: on a loaded machine the ratio
is steadier than either figure.

Goals: >= 100 views/s at 128 px and >= 30 views/s at 256 px.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from uevavd.data.grid import N_VIEWS  # noqa: E402
from uevavd.data.synthetic import build_context, render_view  # noqa: E402
from uevavd.data.synthetic.render import PreparedScene  # noqa: E402


def _time(scene, views, size, cull=True) -> tuple[float, float]:
    prep = PreparedScene(scene)
    render_view(scene, views[0], size, prep, cull=cull)  # warm-up (imports, first shadow tiles)
    w0, c0 = time.perf_counter(), time.process_time()
    for v in views:
        render_view(scene, int(v), size, prep, cull=cull)
    n = len(views)
    return n / (time.perf_counter() - w0), n / (time.process_time() - c0)


def _renderer_from(root: Path):
    """(build_context, PreparedScene, render_view) of the ``uevavd`` package under ``root``, loaded
    beside this checkout's (which stays in ``sys.modules``)."""
    ours = {k: sys.modules.pop(k) for k in list(sys.modules) if k == "uevavd" or k.startswith("uevavd.")}
    sys.path.insert(0, str(root))
    try:
        import uevavd.data.synthetic as other
        import uevavd.data.synthetic.render as other_module
        from uevavd.data.synthetic.render import render_view as other_render

        # the class was private (_Prep) before commit "no private name imported across modules"
        other_prep = getattr(other_module, "PreparedScene", None) or other_module._Prep

        if not other.__file__.startswith(str(root.resolve())):
            raise SystemExit(f"--against {root}: no uevavd package there")
        return other.build_context, other_prep, other_render
    finally:
        sys.path.remove(str(root))
        for k in [k for k in sys.modules if k == "uevavd" or k.startswith("uevavd.")]:
            del sys.modules[k]
        sys.modules.update(ours)


def _interleaved(renderers: dict, cid: int, seed: int, views, size: int, repeats: int) -> dict[str, float]:
    """views/s of each renderer from its minimum CPU time per view over ``repeats`` rounds,
    the renderers taking turns view by view (shadow tiles built before timing)."""
    runs = {}
    for name, (build, prep_cls, render) in renderers.items():
        scene = build(cid, seed=seed)
        prep = prep_cls(scene)
        for v in views:
            render(scene, int(v), size, prep)
        runs[name] = (scene, prep, render)
    best = {name: np.full(len(views), np.inf) for name in runs}
    for _ in range(repeats):
        for j, v in enumerate(views):
            for name, (scene, prep, render) in runs.items():
                c0 = time.process_time()
                render(scene, int(v), size, prep)
                best[name][j] = min(best[name][j], time.process_time() - c0)
    return {name: len(views) / b.sum() for name, b in best.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=121, help="viewpoints per measurement (spread over 605)")
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--contexts", default="1,26")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--against", type=Path, help="a checkout whose renderer to time in the same run")
    ap.add_argument("--repeats", type=int, default=3, help="renders per view with --against")
    args = ap.parse_args()
    against = _renderer_from(args.against) if args.against else None
    views = np.linspace(0, N_VIEWS - 1, args.views).round().astype(int)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {len(views)} views each")
    print(f"{'context':>8} {'size':>5} {'views/s wall':>13} {'views/s cpu':>12} {'no-cull cpu':>12} {'ratio':>6}")
    for cid in (int(c) for c in args.contexts.split(",")):
        scene = build_context(cid, seed=args.seed)
        for size in (int(s) for s in args.sizes.split(",")):
            wall, cpu = _time(scene, views, size)
            _, ref = _time(scene, views[:: max(len(views) // 8, 1)], size, cull=False)
            print(f"{cid:>8} {size:>5} {wall:>13.1f} {cpu:>12.1f} {ref:>12.1f} {cpu / ref:>5.1f}x", flush=True)
    if args.against:
        renderers = {"this": (build_context, PreparedScene, render_view), "against": against}
        print(f"\ninterleaved with {args.against}: views/s from the minimum CPU time of {args.repeats} renders per view")
        print(f"{'context':>8} {'size':>5} {'this':>8} {'against':>8} {'ratio':>6}")
        for cid in (int(c) for c in args.contexts.split(",")):
            for size in (int(s) for s in args.sizes.split(",")):
                r = _interleaved(renderers, cid, args.seed, views, size, args.repeats)
                print(f"{cid:>8} {size:>5} {r['this']:>8.1f} {r['against']:>8.1f} {r['this'] / r['against']:>5.2f}x", flush=True)


if __name__ == "__main__":
    main()

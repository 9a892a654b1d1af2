"""Record the validity search's outcome: ``python -m uevavd.data.synthetic.draws [--seed 0]``.

Runs :func:`~uevavd.data.synthetic.world.search_draw` for every context (1..150) of a world
seed in parallel processes and writes :data:`~uevavd.data.synthetic.world.DRAWS_FILE`
(atomically), which :func:`~uevavd.data.synthetic.world.context_draw` then reads instead of
searching. Run it after bumping the generator version or changing the validity rule (the
file is ignored until then, so worlds stay right, only slower to write).
"""

from __future__ import annotations

import argparse

from ...atomic import atomic_write_json
from ...runtime import WorkerPool, single_threaded_worker, usable_cores
from ..splits import N_CONTEXTS
from .world import DRAWS_FILE, draws_record, search_draw


def _search(args: tuple[int, int]) -> tuple[int, int]:
    context, seed = args
    return context, search_draw(context, seed=seed)


def record_draws(seeds: list[int], *, workers: int) -> dict:
    draws = {}
    with WorkerPool(workers, initializer=single_threaded_worker) as pool:
        for seed in seeds:
            found = dict(f.result() for f in [pool.submit(_search, (c, seed)) for c in range(1, N_CONTEXTS + 1)])
            draws[str(seed)] = {str(c): found[c] for c in sorted(found)}
    data = {**draws_record(), "draws": draws}
    atomic_write_json(DRAWS_FILE, data)
    return data


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="record the first valid draw of every context of a world seed")
    ap.add_argument("--seed", type=int, action="append", default=None, help="world seed(s) (default: 0)")
    ap.add_argument("--workers", type=int, default=usable_cores())
    args = ap.parse_args(argv)
    data = record_draws(args.seed or [0], workers=args.workers)
    redraws = sum(d for by_context in data["draws"].values() for d in by_context.values())
    print(f"wrote {DRAWS_FILE}: {sum(len(v) for v in data['draws'].values())} contexts, {redraws} redraws")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

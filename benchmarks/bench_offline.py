"""How fast is the flat view of an exported dataset, against the fit it feeds?

Exports the oracle's episodes on a toy table with ResNet-sized features (512) as Minari
data, then times, in the same run:

* ``flat_dataset(dataset)``: the flat view, read straight from the dataset's HDF5 file;
* the baseline: ``flat_dataset(dataset.iterate_episodes())``, every episode through Minari's
  own reader (which decodes each episode's infos and spaces);
* where d3rlpy is installed (the d3rlpy extra), a short fit: the MDPDataset built from the
  flat view and ``DiscreteBCConfig().create().fit(n_steps=1000)``, as docs/environment.md writes.

The two flat views are checked equal. Run: ``python benchmarks/bench_offline.py
[--episodes 2000 8000] [--fit-steps 1000]``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, nargs="+", default=[2000, 8000], help="dataset sizes to export")
    parser.add_argument("--fit-steps", type=int, default=1000, help="d3rlpy DiscreteBC steps of the short fit")
    args = parser.parse_args()
    tmp = tempfile.mkdtemp(prefix="uevavd-bench-offline-")
    os.environ["UEVAVD_CACHE"], os.environ["MINARI_DATASETS_PATH"] = f"{tmp}/cache", f"{tmp}/datasets"

    from uevavd.env.offline import flat_dataset
    from uevavd.paths import tables_dir
    from uevavd.policy.minari_export import export_minari
    from uevavd.toy import toy_table

    table = toy_table(20, 10, 512, n_simple=5)
    folder = table.save(tables_dir() / table.key)
    print(f"{'episodes':>8} {'decisions':>9} {'flat_dataset':>12} {'via Minari':>10} {'ratio':>6} "
          f"{'fit':>8} {'fit / flat':>10}")
    for n in args.episodes:
        data = export_minari(folder, "train", "oracle", f"uevavd/bench{n}-oracle-v0", episodes=n, progress=False)
        os.sync()  # a dataset on disk, as one loaded later is, not one still being written back
        t0 = time.perf_counter()
        flat = flat_dataset(data)
        t1 = time.perf_counter()
        base = flat_dataset(data.iterate_episodes())
        t2 = time.perf_counter()
        for field in ("observations", "actions", "rewards", "terminals", "timeouts", "masks"):
            np.testing.assert_array_equal(getattr(flat, field), getattr(base, field))
        fit = short_fit(flat, args.fit_steps)
        fit_s = f"{fit:7.2f}s" if fit is not None else f"{'-':>8}"
        ratio = f"{fit / (t1 - t0):9.1f}x" if fit is not None else f"{'-':>10}"
        print(f"{n:>8} {len(flat.actions):>9} {t1 - t0:11.2f}s {t2 - t1:9.2f}s {(t2 - t1) / (t1 - t0):5.1f}x "
              f"{fit_s} {ratio}")


def short_fit(flat, steps: int) -> float | None:
    """Seconds for d3rlpy's DiscreteBC, dataset built and fitted; None without d3rlpy."""
    try:
        import d3rlpy
    except ImportError:
        return None
    t0 = time.perf_counter()
    data = d3rlpy.dataset.MDPDataset(flat.observations, flat.actions[:, None], flat.rewards, flat.terminals,
                                     timeouts=flat.timeouts, action_space=d3rlpy.constants.ActionSpace.DISCRETE,
                                     action_size=flat.n_actions)
    bc = d3rlpy.algos.DiscreteBCConfig().create(device="cpu:0")
    bc.fit(data, n_steps=steps, n_steps_per_epoch=steps, show_progress=False, save_interval=steps + 1,
           experiment_name="bench", with_timestamp=False, logger_adapter=d3rlpy.logging.NoopAdapterFactory())
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()

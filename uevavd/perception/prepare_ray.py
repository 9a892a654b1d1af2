"""``uevavd prepare --backend ray``: :func:`~uevavd.perception.prepare.prepare_table` with
the image -> shard work spread over Ray tasks that write into the same ``<key>.partial``
folder; the driver assembles the table exactly as the local build does."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..config import MethodSpec, as_method
from ..data.grid import N_VIEWS
from ..data.splits import TARGETS
from ..paths import tables_dir
from ..table import ObservationTable, TableError
from .prepare import plan_table, prepare_table
from .shards import read_shard


def _prepare_shards(data_root: str, spec_path: str, classifier_path: str | None, out_dir: str,
                    scenes: list[str], threads: int) -> list[str]:
    """A Ray task: the shards of ``scenes``, written into the shared ``<key>.partial`` folder."""
    import torch

    torch.set_num_threads(max(1, threads))
    prepare_table(data_root, spec_path, classifier_path=classifier_path, out_dir=out_dir, workers=1,
                  progress=False, only_scenes=scenes, assemble=False)
    return scenes


def prepare_table_ray(
    data_root: str | os.PathLike[str],
    spec_or_method: MethodSpec | str | os.PathLike[str],
    *,
    classifier_path: str | os.PathLike[str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    preset: Mapping[str, Any] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    shards: int | None = None,
    cpus_per_task: float = 1.0,
    gpus_per_task: float = 0.0,
    address: str | None = None,
    progress: bool = True,
) -> Path:
    """:func:`prepare_table` with the image -> shard work spread over Ray tasks.

    The scenes still missing are split into ``shards`` groups (default: the cluster's CPUs
    divided by ``cpus_per_task``); each task builds the perception components itself and
    writes its scenes' shards into ``<out_dir>/<key>.partial``, which every worker must
    reach (a shared file system on a cluster). The driver then assembles the table exactly
    as the local build does, so both give the same table under the same key. A failed task
    is retried; scenes already written are not recomputed.
    """
    try:
        import ray
    except ImportError:
        raise RuntimeError("--backend ray needs Ray: pip install 'uevavd[ray]'") from None
    from tqdm.auto import tqdm

    spec = as_method(spec_or_method, overrides, preset=preset)
    p = plan_table(data_root, spec, classifier_path=classifier_path)
    out_dir = Path(out_dir).expanduser().resolve() if out_dir is not None else tables_dir()
    final = out_dir / p.key
    if final.is_dir():
        try:
            ObservationTable.load(final, expect_key=p.key)
            return final
        except TableError:
            pass
    partial = out_dir / f"{p.key}.partial"
    partial.mkdir(parents=True, exist_ok=True)
    spec_path = partial / "method.toml"  # the resolved spec, so every task builds the same components
    spec.save(spec_path)
    k = len(TARGETS)
    todo = [s for s, _ in p.scenes if read_shard(partial / f"{s}.npz", p.encoder.feature_dim, k) is None]
    del p  # the driver's models are not needed while the tasks run
    if todo:
        started = not ray.is_initialized()
        if started:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
        try:
            cpus = float(ray.cluster_resources().get("CPU", 1.0))
            n = max(1, min(len(todo), shards or int(cpus // max(cpus_per_task, 1e-9)) or 1))
            groups = [todo[i::n] for i in range(n)]
            task = ray.remote(num_cpus=cpus_per_task, num_gpus=gpus_per_task, max_retries=3,
                              retry_exceptions=True)(_prepare_shards)
            refs = [task.remote(str(Path(data_root).expanduser().resolve()), str(spec_path),
                                None if classifier_path is None else str(classifier_path), str(out_dir), g,
                                max(1, int(cpus_per_task))) for g in groups]
            with tqdm(total=len(todo) * N_VIEWS, desc="prepare (ray)", unit="view", disable=not progress) as bar:
                pending = list(refs)
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    bar.update(len(ray.get(ready[0])) * N_VIEWS)
        finally:
            if started:
                ray.shutdown()
    return prepare_table(data_root, spec_path, classifier_path=classifier_path, out_dir=out_dir,
                         workers=1, progress=False)

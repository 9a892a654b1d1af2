"""uevavd.runtime.tune_malloc: freed memory is reused instead of faulted in again."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import resource, sys
import numpy as np
from uevavd.runtime import tune_malloc
tuned = tune_malloc() if sys.argv[1] == "1" else False
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def step():  # a training step's pattern: buffers of 128 KB - 1 MB, allocated and freed
    arrs = [np.ones(k << 14) for k in (1, 3, 2, 5, 4, 8, 6)]
    del arrs
step()
before = faults()
for _ in range(20):
    step()
print(tuned, faults() - before)
"""


def _run(tune: str, env: dict[str, str] | None = None) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", SCRIPT, tune], capture_output=True, text=True, check=True,
                         env={**os.environ, **(env or {})})
    tuned, faults = out.stdout.split()
    return tuned, int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tuned_process_reuses_freed_memory():
    tuned, faults_tuned = _run("1")
    plain, faults_plain = _run("0")
    assert tuned == "True" and plain == "False"
    # untuned: glibc maps and unmaps the buffers, so every step faults ~500 pages in again
    assert faults_plain > 20 * 200
    assert faults_tuned < faults_plain / 10


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tuning_can_be_switched_off():
    tuned, _ = _run("1", {"UEVAVD_MALLOC_TUNING": "0"})
    assert tuned == "False"


def _blas_threads() -> list[int]:
    import numpy  # noqa: F401  (loads its BLAS)
    from threadpoolctl import threadpool_info

    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_single_threaded_worker_limits_blas_in_pool_workers():
    """The renderer's pool workers run numpy's BLAS on one thread each (N workers with N
    spinning BLAS threads each oversubscribe the cores N-fold)."""
    from concurrent.futures import ProcessPoolExecutor

    from uevavd.runtime import single_threaded_worker

    with ProcessPoolExecutor(1, initializer=single_threaded_worker) as pool:
        assert set(pool.submit(_blas_threads).result()) == {1}
    if (os.cpu_count() or 1) > 1:  # what the limit changes: a plain worker takes every core
        with ProcessPoolExecutor(1) as pool:
            assert max(pool.submit(_blas_threads).result()) > 1

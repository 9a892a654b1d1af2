"""Process-level settings for uevavd's own processes (the CLI and the workers it starts).

:func:`tune_malloc` keeps glibc from handing freed memory back to the kernel after every
large allocation. By default glibc serves allocations above its mmap threshold (128 KB
at first, raised on the fly up to 32 MB) with fresh ``mmap`` pages and trims the heap
whenever 128 KB sit free at its top, so every training step of the recognizer (batches
of ~10 MB activations) faults its memory in again, page by page: about 22,000 minor
page faults and 60-70 ms of kernel time per batch on the development machine. With a
high mmap threshold and trim threshold the pages are reused: one epoch of the recognizer
on 1,275 crops took 20 s instead of 22.5-28.8 s (`uevavd train-classifier --epochs 1
--max-views 300`, 2026-11-23), with 5x fewer page faults. The price is that a process
keeps up to ``trim`` bytes of freed memory mapped. The library never calls this on
import: a user's own process keeps its allocator as it was.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_done = False


def tune_malloc(mmap_threshold: int = 256 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Raise glibc's mmap and trim thresholds in this process (Linux with glibc only;
    elsewhere, or with ``UEVAVD_MALLOC_TUNING=0``, it does nothing). Returns True when
    both settings took. Idempotent; forked children inherit it, spawned ones call it."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux") or os.environ.get("UEVAVD_MALLOC_TUNING", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl): leave the allocator alone
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    ok_trim = bool(mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))
    ok_mmap = bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)))
    if not ok_mmap:  # older glibc caps the threshold at 32 MB
        ok_mmap = bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20))
    _done = ok_trim and ok_mmap
    log.debug("malloc tuning: trim threshold %s, mmap threshold %s", ok_trim, ok_mmap)
    return _done


def single_threaded_worker() -> None:
    """Initializer for process pools whose workers each run numpy work (the synthetic
    world's renderer): one thread for the BLAS and OpenMP pools in the worker. Left alone,
    each of N workers starts one BLAS thread per core, and OpenBLAS threads spin while they
    wait, so N workers oversubscribe N cores N-fold; on a 16-core machine the paper world
    rendered at about 11 views/s per worker against 55-73 views/s of one core alone
    (docs/experiments.md, "On one GPU"). joblib's workers make the same limit by default."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)

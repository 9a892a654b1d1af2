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

:func:`single_threaded_worker` limits a pool worker's BLAS to one thread, and
:class:`WorkerPool` is the process pool of the renderer and the local ablation backend, which
stops at once on Ctrl-C or a failed job.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor, wait
from typing import Any

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


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the OS has one (``taskset``,
    a container's cpuset, a Slurm allocation), else the machine's count. The default number
    of workers and each run's torch threads come from it, so a job given 4 of a node's 64
    cores starts 4 workers, not 64."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS and Windows have no affinity call
        return max(1, os.cpu_count() or 1)


def resolve_device(device: str) -> Any:
    """``"auto"`` -> cuda when available else cpu; anything else as torch reads it, refused in
    one line where it is not a device or not there (before any work is done)."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"device {device!r}: expected 'auto', 'cpu', 'cuda' or 'cuda:N'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but no CUDA device is available; use device='auto'")
    return dev


@contextlib.contextmanager
def torch_threads(n: int | None):
    """torch's CPU thread count set to ``n`` for the block and restored after it (``None``:
    left as it is). Float sums split between threads round differently, so a result that
    must not depend on the machine's cores runs under a fixed count."""
    import torch

    before = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


# -- process pools that stop when asked ------------------------------------------------------
#: Seconds after a Ctrl-C in which a second SIGINT to a WorkerPool's parent is taken as a copy
#: of the first (``timeout`` sends two), not as the second Ctrl-C that stops the waiting.
REPEAT_S = 1.0
# In a worker of a WorkerPool: the pool's stop event, and whether a job is running.
_stop_event: Any = None
_job_running = False


#: Libraries whose native threads make a fork unsafe once imported: Ray's driver, and JAX
#: (which Minari's DataCollector imports; JAX itself warns that a fork beside it may deadlock).
FORK_UNSAFE = ("ray", "jax")


def safe_context() -> Any:
    """The start method for a pool whose caller named none: Python's default, except that a
    process that has imported Ray or JAX (:data:`FORK_UNSAFE`) spawns its workers instead of
    forking them. A Ray driver's
    native threads (gRPC, the core worker) outlive ``ray.shutdown()``, and a worker forked
    beside them can wait forever on a lock one of them held at the fork: a pool's worker
    forked after the Ray test hung the suite for 20 minutes. Other threads (numpy's BLAS
    pool, which every process importing numpy runs, tqdm's monitor) are forked beside as
    before, and a script without an ``if __name__ == "__main__"`` guard keeps working; a
    worker computes the same either way. A caller that needs one method passes ``mp_context``."""
    ctx = multiprocessing.get_context()
    if ctx.get_start_method() == "fork" and any(m in sys.modules for m in FORK_UNSAFE):
        return multiprocessing.get_context("spawn")
    return ctx


class WorkerPool:
    """A :class:`~concurrent.futures.ProcessPoolExecutor` that stops at once when the block
    it serves ends with an exception: Ctrl-C, a ``SIGINT`` from ``timeout``, or a failed
    job. The standard executor's ``with`` block runs every queued job to its end before
    the exception leaves it (Python 3.14 adds ``terminate_workers``): an interrupted
    ablation went on training all its runs, an interrupted world rendered all its scenes.
    Here the jobs not started end without running (``CancelledError``), the running ones
    get one ``KeyboardInterrupt`` in their worker (their ``finally`` blocks run: atomic
    writes remove their temporary files) and a worker still busy after ``grace`` seconds
    is terminated. Every caller's jobs resume from what they wrote.

    A worker ignores ``SIGINT`` between jobs and takes only the first during a job, so
    the terminal's Ctrl-C (sent to the whole process group) and the pool's own do not
    cut a job's clean-up short. The parent, while the pool is open, takes a ``SIGINT``
    that comes within :data:`REPEAT_S` of the first as the same interrupt: ``timeout -s
    INT`` signals the process and then its whole group, so the parent may get it twice,
    and the copy would otherwise count as the second Ctrl-C, the one that stops waiting
    for the clean-up. (joblib's loky executor would kill its workers outright, with no
    clean-up, and sets their thread counts, on which results depend.)

        with WorkerPool(2, initializer=single_threaded_worker) as pool:
            futures = [pool.submit(render, name) for name in names]
            for fut in as_completed(futures): ...
    """

    def __init__(self, workers: int, *, mp_context: Any = None, initializer: Callable[..., None] | None = None,
                 initargs: tuple = (), grace: float = 10.0) -> None:
        ctx = mp_context or safe_context()
        self.grace = grace
        self._stop = ctx.Event()
        self._futures: list[Future] = []
        self._before = set(multiprocessing.active_children())
        self._interrupted_at: float | None = None
        self._sigint: Any = None  # the handler this pool replaced, while it is open
        self._sigterm: Any = None
        self.executor = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                                            initargs=(self._stop, initializer, initargs))

    def _on_sigint(self, signum: int, frame: Any) -> None:
        now = time.monotonic()
        if self._interrupted_at is not None and now - self._interrupted_at < REPEAT_S:
            return  # the same interrupt delivered twice
        self._interrupted_at = now
        raise KeyboardInterrupt

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        fut = self.executor.submit(_worker_run, fn, *args, **kwargs)
        self._futures.append(fut)
        return fut

    def stop(self) -> None:
        """End the jobs not started, interrupt the running ones, end the workers."""
        # Jobs not started are not cancelled here but end at once in their worker (the stop
        # event): a future cancelled while the executor still holds it makes the executor's
        # thread fail if the pool then breaks (Python 3.11), as terminate() below does.
        self._stop.set()
        workers = [p for p in multiprocessing.active_children() if p not in self._before]
        try:
            for p in workers:
                if p.pid is not None and p.is_alive():
                    try:
                        os.kill(p.pid, signal.SIGINT)
                    except ProcessLookupError:  # it ended in the meantime (a broken pool ends them all)
                        pass
            # in slices: a signal the kernel hands to another thread than this one does not
            # wake a blocked wait, so a second Ctrl-C was seen only when the jobs ended
            deadline = time.monotonic() + self.grace
            while not all(f.done() for f in self._futures) and (left := deadline - time.monotonic()) > 0:
                wait(self._futures, timeout=min(0.1, left))
        except KeyboardInterrupt:  # a second Ctrl-C: wait no longer
            pass
        finally:
            if not all(f.done() for f in self._futures):  # a job deaf to the interrupt
                for p in workers:
                    if p.is_alive():
                        p.terminate()
            self.executor.shutdown(wait=True)

    def _on_sigterm(self, signum: int, frame: Any) -> None:
        # a plain `kill` of the parent: the same orderly stop as Ctrl-C (it used to leave the
        # workers training, holding their runs' locks, so the rerun was refused)
        if self._interrupted_at is None:
            self._interrupted_at = time.monotonic()
            raise KeyboardInterrupt

    def __enter__(self) -> WorkerPool:
        # replaces the default Ctrl-C and SIGTERM handlers only, in the main thread only (where
        # signal handlers run); a pool opened inside another keeps the outer one's
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
                self._sigint = signal.signal(signal.SIGINT, self._on_sigint)
            if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
                self._sigterm = signal.signal(signal.SIGTERM, self._on_sigterm)
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            if exc_type is None:
                self.executor.shutdown(wait=True)
            else:
                self.stop()
        finally:
            if self._sigint is not None:
                signal.signal(signal.SIGINT, self._sigint)
            if self._sigterm is not None:
                signal.signal(signal.SIGTERM, self._sigterm)


def _die_with_parent() -> None:
    """Linux: the kernel sends this worker SIGTERM when its parent dies, however it dies (a
    ``kill -9`` of an ablation left its workers training, ~770 MB each, holding the runs'
    locks). Elsewhere nothing: the parent's handlers still stop the pool on Ctrl-C and SIGTERM."""
    if not sys.platform.startswith("linux"):
        return
    parent = multiprocessing.parent_process()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent.pid:  # it died before the request: none would come
        os._exit(1)


def skip_teardown() -> None:
    """End this process, once its exit handlers have run, without the interpreter's teardown.

    Python's exit collects and frees every object before the process ends: with torch,
    the tables and a trained network in memory that took 2-4 s per process on 2 cores (a
    stopped ablation's workers, then its parent), for memory the kernel frees at once.
    Registered first, the handler runs after every other ``atexit`` handler (Ray's
    shutdown, logging's flush; Python has joined the other threads before these), flushes
    stdout and stderr and ends the process with the status given to :func:`exit_status`
    (0 unless set; 1 after an uncaught exception). The same as Instagram's
    ``atexit.register(os._exit, 0)`` for its web workers. Only for processes uevavd owns:
    the CLI and its pool workers, never on import.
    """
    global _status
    _status = 0
    atexit.register(_exit_now)
    hook = sys.excepthook

    def excepthook(*exc: Any) -> None:
        exit_status(1)
        hook(*exc)

    sys.excepthook = excepthook


_status: int | None = None  # set by skip_teardown


def exit_status(code: object) -> int:
    """Record the status this process ends with (:func:`sys.exit`'s rules: None is 0, an
    int itself, anything else 1) and return it."""
    global _status
    status = 0 if code is None else code if isinstance(code, int) else 1
    if _status is not None:
        _status = status
    return status


def _exit_now() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(_status or 0)


def _worker_init(stop: Any, initializer: Callable[..., None] | None, initargs: tuple) -> None:
    global _stop_event
    _stop_event = stop
    skip_teardown()  # a spawned worker ends through sys.exit, with the interpreter's full teardown
    _die_with_parent()
    signal.signal(signal.SIGINT, _worker_interrupt)
    # a forked worker inherits the parent's SIGTERM handler (the pool's own): terminate() must end it
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if initializer is not None:
        initializer(*initargs)


def _worker_interrupt(signum: int, frame: Any) -> None:
    global _job_running
    if _job_running:  # the first SIGINT of a job interrupts it; between jobs, and after, none does
        _job_running = False
        raise KeyboardInterrupt


def _worker_run(fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
    global _job_running
    _job_running = True
    try:
        if _stop_event.is_set():  # queued in the worker before the pool was stopped
            raise CancelledError("the pool was stopped before this job started")
        return fn(*args, **kwargs)
    finally:
        _job_running = False

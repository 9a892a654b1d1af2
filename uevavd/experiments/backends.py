"""Where training runs execute: local worker processes, or Ray tasks.

Both call :func:`uevavd.experiments.jobs.run_job`, which resumes a run from its last
checkpoint, so a retried Ray task (or a rerun after a kill) continues where it stopped.
Each job gets ``cores // parallel`` torch threads on both backends, so the same seeds
give the same results whichever backend ran them.
"""

from __future__ import annotations

import dataclasses
import errno
import os
from collections.abc import Callable, Sequence

from ..runtime import WorkerPool
from .jobs import Job, run_job


def _threads(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def run_jobs(jobs: Sequence[Job], *, backend: str = "local", workers: int = 1, log: Callable = print,
             ray_address: str | None = None, gpus_per_job: float = 0.0) -> list[str]:
    if not jobs:
        return []
    # threads from the workers asked for, not from the runs left: a resumed ablation gives
    # its last runs the same thread count as an uninterrupted one (results depend on it)
    threads = _threads(workers)
    workers = max(1, min(workers, len(jobs)))
    jobs = [dataclasses.replace(j, threads=threads) for j in jobs]
    if backend == "ray":
        return run_ray(jobs, workers=workers, log=log, address=ray_address, gpus_per_job=gpus_per_job)
    return run_local(jobs, workers=workers, log=log)


def run_local(jobs: Sequence[Job], *, workers: int, log: Callable) -> list[str]:
    from tqdm import tqdm

    done: list[str] = []
    bar = tqdm(total=len(jobs), desc="runs", unit="run")
    try:
        if workers == 1:
            for job in jobs:
                done.append(run_job(job))
                bar.update()
            return done
        import multiprocessing as mp
        from concurrent.futures import as_completed

        # spawn: a fresh interpreter per worker (torch and forked thread pools do not mix);
        # Ctrl-C or a failed run stops the others at once (they resume from their checkpoints)
        with WorkerPool(workers, mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(run_job, job): job for job in jobs}
            for fut in as_completed(futures):
                done.append(job_result(fut, futures[fut]))
                bar.update()
        return done
    finally:
        bar.close()


def job_result(fut, job: Job) -> str:
    """A finished future's result; a run that failed names itself: a worker process that died
    (killed, out of memory) is a ``ChildProcessError`` naming the run and how to resume, and
    any other failure carries a note with the run's key and folder."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return fut.result()
    except BrokenProcessPool as exc:
        raise ChildProcessError(errno.ECHILD, f"the worker process of run {job.key} died ({exc or 'killed'}); "
                                "finished runs are kept: rerun the same command to resume", job.out) from None
    except Exception as exc:
        exc.add_note(f"in run {job.key} ({job.out})")
        raise


def run_ray(jobs: Sequence[Job], *, workers: int, log: Callable, address: str | None = None,
            gpus_per_job: float = 0.0, max_retries: int = 3) -> list[str]:
    try:
        import ray
    except ImportError:
        raise RuntimeError("--backend ray needs Ray: pip install 'uevavd[ray]'") from None
    address = address or os.environ.get("RAY_ADDRESS") or None
    started = False
    if not ray.is_initialized():
        ray.init(address=address, num_cpus=None if address else max(workers, 1),
                 include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
        started = True
    try:
        task = ray.remote(num_cpus=1, num_gpus=gpus_per_job, max_retries=max_retries,
                          retry_exceptions=True)(run_job)
        refs = [task.remote(job) for job in jobs]
        from tqdm import tqdm

        done: list[str] = []
        with tqdm(total=len(refs), desc="runs (ray)", unit="run") as bar:
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                done.append(ray.get(ready[0]))
                bar.update()
        return done
    finally:
        if started:
            ray.shutdown()

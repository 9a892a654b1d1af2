"""Where training runs execute: local worker processes, or Ray tasks.

Both call :func:`uevavd.experiments.jobs.run_job`, which resumes a run from its last
checkpoint, so a retried Ray task (or a rerun after a kill) continues where it stopped.
A run trains on its method's ``train.threads`` (default 1) on both backends, so the same
seeds give the same results whichever backend, machine or ``--workers`` ran them; a method
that sets 0 gets ``cores // parallel``.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import threading
from collections.abc import Callable, Sequence

from tqdm import tqdm

from ..policy.rundir import RunDir
from ..runtime import WorkerPool, usable_cores
from .jobs import Job, run_job


def _threads(workers: int) -> int:
    return max(1, usable_cores() // max(1, workers))


def run_jobs(jobs: Sequence[Job], *, backend: str = "local", workers: int = 1, log: Callable = print,
             ray_address: str | None = None, gpus_per_job: float = 0.0) -> list[str]:
    if not jobs:
        return []
    # for methods with train.threads = 0: threads from the workers asked for, not from the runs
    # left, so a resumed ablation gives its last runs an uninterrupted one's count
    threads = _threads(workers)
    workers = max(1, min(workers, len(jobs)))
    jobs = [dataclasses.replace(j, threads=threads) for j in jobs]
    if backend == "ray":
        return run_ray(jobs, workers=workers, log=log, address=ray_address, gpus_per_job=gpus_per_job)
    return run_local(jobs, workers=workers, log=log)


def run_local(jobs: Sequence[Job], *, workers: int, log: Callable) -> list[str]:
    done: list[str] = []
    with RunsProgress(jobs) as bar:
        if workers == 1:
            for job in jobs:
                done.append(run_job(job))
                bar.finished(job)
            return done
        import multiprocessing as mp
        from concurrent.futures import as_completed

        # spawn: a fresh interpreter per worker (torch and forked thread pools do not mix);
        # Ctrl-C or a failed run stops the others at once (they resume from their checkpoints)
        with WorkerPool(workers, mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(run_job, job): job for job in jobs}
            for fut in as_completed(futures):
                done.append(job_result(fut, futures[fut]))
                bar.finished(futures[fut])
        return done


class RunsProgress:
    """One progress bar over the episodes of the runs to do, as each run's ``evals.jsonl``
    records them (every ``train.epoch_episodes``), read every ``every`` seconds in a
    thread: the runs train in other processes, or here without a bar of their own, and a
    paper-sized run takes minutes to hours, so a bar of finished runs alone would stand
    still that long. The description counts the finished runs."""

    def __init__(self, jobs: Sequence[Job], *, every: float = 2.0, desc: str = "runs") -> None:
        self.jobs, self.desc, self.every = list(jobs), desc, every
        self.episodes = {j.key: j.episodes for j in self.jobs}
        self.ended: set[str] = set()
        self.bar = tqdm(total=sum(self.episodes.values()), unit="ep", unit_scale=True,
                        desc=self._desc(), dynamic_ncols=True)
        self._lock = threading.Lock()  # the polling thread and finished() both refresh
        self.refresh()  # resumed runs show what they have already trained,
        self.bar.initial = self.bar.n  # which the rate and the time left do not count
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="uevavd-runs-progress", daemon=True)
        self._thread.start()

    def _desc(self) -> str:
        return f"{self.desc} {len(self.ended)}/{len(self.jobs)}"

    def _poll(self) -> None:
        while not self._stop.wait(self.every):
            self.refresh()

    def refresh(self) -> None:
        n = sum(self.episodes[j.key] if j.key in self.ended else min(self.episodes[j.key], episodes_trained(j))
                for j in self.jobs)
        with self._lock:
            self.bar.n = n
            self.bar.set_description(self._desc(), refresh=False)
            self.bar.refresh()

    def finished(self, job: Job) -> None:
        self.ended.add(job.key)
        self.refresh()

    def __enter__(self) -> RunsProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.bar.close()


def last_evaluation(job: Job) -> dict:
    """A run's last per-epoch evaluation row of ``evals.jsonl`` (its ``episodes``, its
    training ``wall_s``, ...), or {} before its first (a line that does not parse is skipped)."""
    try:
        lines = RunDir(job.out).evals.read_text(encoding="utf-8").splitlines()
    except OSError:
        return {}
    for line in reversed(lines):
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and "episodes" in row:
            return row
    return {}


def episodes_trained(job: Job) -> int:
    """Episodes a run has trained as its last per-epoch evaluation records them (0 before its first)."""
    return int(last_evaluation(job).get("episodes", 0))


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
        done: list[str] = []
        with RunsProgress(jobs, desc="runs (ray)") as bar:
            pending = dict(zip(refs, jobs, strict=True))
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                done.append(ray.get(ready[0]))
                bar.finished(pending.pop(ready[0]))
        return done
    finally:
        if started:
            ray.shutdown()

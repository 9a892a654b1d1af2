"""Training runs: one :class:`Job` per method x setting x recognizer x seed, and the
function a worker process or Ray task runs for it."""

from __future__ import annotations

from pathlib import Path

from ..config import MethodSpec, load_method
from ..policy.trainer import train
from ..runtime import torch_threads, tune_malloc
from .plan import Job, Plan
from .results import final_eval


def save_spec(spec: MethodSpec, path: Path) -> Path:
    """Write a run's resolved method spec for its workers, unless ``path`` already holds it
    (a resumed ablation leaves the file, and its time, as they were). Returns ``path``."""
    text = spec.to_toml()  # its hash in its first line: the same text is the same spec
    try:
        same = path.read_text(encoding="utf-8") == text
    except (OSError, UnicodeDecodeError):
        same = False
    if not same:
        spec.save(path)
    return path


def plan_jobs(plan: Plan, tables: dict[int, dict]) -> list[Job]:
    jobs = []
    for m in plan.methods:
        for setting_name, setting in plan.settings(m):
            spec = plan.spec(m, setting)
            spec_path = save_spec(spec, plan.out / "specs" / f"{m}-{setting_name}.toml")
            episodes = int(spec.train_config().episodes)
            for r in plan.recognizers:
                for seed in plan.seeds:
                    out = plan.out / "runs" / m / setting_name / f"rec{r}" / f"seed{seed}"
                    table = tables[r].get((m, setting_name), tables[r][m])
                    jobs.append(Job(m, setting_name, seed, str(spec_path), str(table), str(out),
                                    device=plan.device, recognizer=r, episodes=episodes))
    return jobs


def run_job(job: Job) -> str:
    """Train (or resume, or skip a finished) run, then evaluate its final policy on every
    context (:func:`final_eval`), on ``job.threads`` torch threads. Runs in a worker process, a
    Ray task, or in the caller's process (one local worker), whose thread count it restores."""
    tune_malloc()  # a spawned worker: reuse freed memory as the CLI's process does
    with torch_threads(job.threads):  # run here (one worker), the caller's count comes back after
        spec = load_method(job.spec_path)
        train(spec, Path(job.table), out=Path(job.out), seed=job.seed, device=job.device, progress=False)
        final_eval(job)
    return job.key

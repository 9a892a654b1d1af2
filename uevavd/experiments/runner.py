"""The ablation runner: world -> classifier -> observation tables -> training -> results.

Every stage reuses what exists: the world and the classifier are cached by their
settings, tables by the hash of everything that produced them, runs by (method spec,
seed); a killed ablation resumes where it stopped. Results go to one tidy file,
``DIR/results.csv`` (a row per method x seed x setting x evaluation point x split),
rebuilt from the run directories at the end, plus ``DIR/report/``.
"""

import json
from pathlib import Path
from typing import Any

from ..atomic import atomic_write_json, folder_lock, is_temporary, remove_temporaries, write_sealed_json
from ..config_rules import ConfigError
from ..env.baselines import check_baselines
from ..perception.decompose import check_decomposition
from ..policy.contract import build_checked_network
from .audit import audit_table, classifier_summary
from .axes import parse_sweeps, resolved_value, value_label
from .backends import run_jobs
from .io import ABLATION_FILE, output_digests, read_ablation_meta, write_csv
from .jobs import Job, plan_jobs, run_job
from .plan import AblationError, Plan, make_plan
from .references import sb3_rows
from .report import write_report
from .report_data import roles_now
from .results import (
    CONTEXT_COLUMNS,
    RESULT_COLUMNS,
    baseline_rows,
    context_terrains,
    final_eval,
    is_done,
    run_rows,
)
from .stages import Stage, stage_classifier, stage_tables, stage_world
from .trajectories import trajectory_rows


def check_out_dir(plan: Plan) -> None:
    """Refuse a results directory written by another configuration."""
    meta = plan.out / ABLATION_FILE
    if not meta.is_file():
        # a temporary file is what an ablation killed in its first write leaves: rerun, it resumes
        if plan.out.exists() and any(not is_temporary(p) for p in plan.out.iterdir()):
            raise AblationError(
                f"--out {plan.out} exists, is not empty and holds no ablation.json: choose a new directory"
            )
        return
    old = read_ablation_meta(meta).get("fingerprint")
    new = json.loads(json.dumps(plan.fingerprint(), default=str))
    if old != new:
        diff = sorted(k for k in set(old or {}) | set(new) if (old or {}).get(k) != new.get(k))
        raise AblationError(
            f"--out {plan.out} holds an ablation of another configuration (differs in {diff}); "
            "use a new --out directory"
        )


def perception_line(perception: dict) -> str:
    """"encoder NAME (WEIGHTS), segmenter NAME[, decomposed], recognizer NAME" of a perception section."""
    enc, seg, clf = perception.get("encoder", {}), perception.get("segmenter", {}), perception.get("classifier", {})
    return (f"encoder {enc.get('name')} ({enc.get('weights', 'default weights')}), segmenter "
            f"{seg.get('name')}{', decomposed' if perception.get('decompose') else ''}, recognizer {clf.get('name')}")


def perception_summary(plan: Plan) -> dict[str, str]:
    """``{method: "encoder NAME (WEIGHTS), segmenter NAME, recognizer NAME"}`` as the runs
    see them (``"method @ setting"`` for a setting whose perception differs from the method's
    default), and ``{"recognizer training": settings}``: what the report names as the
    perception every method used."""
    out = {}
    for m in plan.methods:
        out[m] = perception_line(plan.spec(m).perception.as_dict())
        for name, setting in plan.settings(m)[1:]:
            line = perception_line(plan.spec(m, setting).perception.as_dict())
            if line != out[m]:
                out[f"{m} @ {name}"] = line
    out["recognizer training"] = json.dumps(plan.preset.get("classifier", {}), sort_keys=True)
    return out


def components_summary(plan: Plan) -> dict[str, dict[str, Any]]:
    """``{method: {setting: components}}``: every run's components as resolved
    (:meth:`Plan.components`), the preset keys a method file kept out included."""
    return {m: {name: plan.components(m, setting) for name, setting in plan.settings(m)} for m in plan.methods}


def write_meta(plan: Plan, data: Path | None, status: str) -> None:
    meta = {
        "perception": perception_summary(plan),
        "components": components_summary(plan),
        "lineage": {m: plan.lineage(m) for m in plan.methods},
        "preset": plan.preset.get("name"),
        "fingerprint": plan.fingerprint(),
        "methods": plan.methods,
        "seeds": len(plan.seeds),
        "recognizers": len(plan.recognizers),
        "sweeps": plan.sweeps,
        "sweep_methods": plan.sweep_methods,
        "cross": plan.cross,
        "sets": plan.sets,
        "method_files": plan.method_files,
        "backend": plan.backend,
        "data_root": str(data) if data else None,
        "stages": {k: round(v, 2) for k, v in plan.stages.items()},
        "status": status,
        # the sha256 of results.csv and contexts.csv as written: the report refuses another table
        **({"outputs": output_digests(plan.out)} if status in ("reporting", "done") else {}),
        # which rows are references, as installed now: `uevavd report` reads this, not the
        # plugins installed when it runs
        "roles": roles_now(),
    }
    write_sealed_json(plan.out / ABLATION_FILE, meta, fsync=True)


def _with_swept_columns(plan: Plan, rows: list[dict]) -> tuple[list[dict], list[str]]:
    """The rows and columns of ``results.csv``: :data:`RESULT_COLUMNS` plus, after C, one
    column per swept dotted key, holding each row's resolved value (the method's own where
    its setting does not vary the key)."""
    extra = plan.extra_sweeps
    if not extra:
        return rows, RESULT_COLUMNS
    resolved = {m: plan.spec(m) for m in plan.methods}
    first = resolved[plan.methods[0]]
    defaults = {m: {k: resolved_value(resolved.get(m) or first, k) for k in extra}
                for m in {*resolved, *(r["method"] for r in rows)}}
    rows = [{**defaults[r["method"]], **r} for r in rows]
    rows = [{**r, **{k: value_label(r[k]) for k in extra if isinstance(r.get(k), dict | list | bool)}} for r in rows]
    at = RESULT_COLUMNS.index("C") + 1
    return rows, [*RESULT_COLUMNS[:at], *extra, *RESULT_COLUMNS[at:]]


def check_components(plan: Plan) -> None:
    """Each method's state estimator and head through their rules (at a toy feature size; each
    run checks them again at its table's) and every plugin's baseline on a toy table, before
    anything is written: a broken one ended the ablation after its world, recognizers and
    tables were made and ``ablation.json``, ``specs/`` and ``runs/`` written (a baseline, after
    every run trained). One line naming the component and its plugin."""
    import torch

    with torch.random.fork_rng(devices=[]):  # the checks draw nothing a run's numbers depend on
        for method in plan.methods:
            for _, setting in plan.settings(method):
                spec = plan.spec(method, setting)
                build_checked_network(spec.state, spec.head, 16, n_ranges=spec.env.max_range)
        check_perception(plan)
    check_baselines()


def check_perception(plan: Plan) -> None:
    """Build every distinct encoder and segmenter the runs' tables need, before any work: a
    missing weights file or SAM checkpoint is refused in one line naming the method, the setting
    and the file, not when the tables stage reaches it minutes later. An encoder that takes the
    recognizer's backbone (``weights="classifier"``) is built by its table, after the recognizer."""
    seen: set[str] = set()
    for method in plan.methods:
        for name, setting in plan.settings(method):
            perception = plan.spec(method, setting).perception
            where = f"method {method!r}" + (f" at {name}" if name != "default" else "")
            try:
                check_decomposition(perception, where)
            except ValueError as exc:
                raise AblationError(str(exc)) from None
            parts = [("perception.encoder", perception.encoder)]
            if perception.decompose:
                parts.append(("perception.segmenter", perception.segmenter))
            for section, comp in parts:
                if comp is None or comp.kwargs.get("weights") == "classifier":
                    continue
                key = json.dumps([comp.kind, comp.name, dict(comp.kwargs)], sort_keys=True, default=str)
                if key in seen:
                    continue
                seen.add(key)
                try:
                    comp.build(**({"device": "cpu"} if comp.accepts("device") else {}))
                except (ValueError, OSError, RuntimeError) as exc:
                    raise AblationError(f"{where}: {section} {comp.name!r} cannot be built: {exc}") from None


def run_ablation(plan: Plan, *, log=print) -> Path:
    """Run (or resume) the whole ablation; returns the results file. One process at a time
    writes an ``--out`` folder: a second is refused while the first holds it."""
    check_components(plan)
    busy = lambda lock: AblationError(f"--out {plan.out} is being written by another ablation (it holds {lock}): "  # noqa: E731
                                      "wait for it to finish, or choose another --out")
    with folder_lock(plan.out, busy):
        return _run_ablation(plan, log)


def _run_ablation(plan: Plan, log) -> Path:
    check_out_dir(plan)
    plan.out.mkdir(parents=True, exist_ok=True)
    remove_temporaries(plan.out)  # what a killed write left here (the runs and the report clean their own)
    write_meta(plan, None, "running")
    with Stage(plan, "world", log):
        data = stage_world(plan, log)
    with Stage(plan, "classifier", log):
        classifiers = stage_classifier(plan, data, log)
    with Stage(plan, "tables", log):
        tables = stage_tables(plan, data, classifiers, log)
    write_meta(plan, data, "training")
    jobs = plan_jobs(plan, tables)
    with Stage(plan, "training", log):
        todo = [j for j in jobs if not is_done(j)]
        log(f"  {len(jobs)} runs, {len(jobs) - len(todo)} finished already, {len(todo)} to run "
            f"on the {plan.backend} backend with {plan.workers} worker(s)")
        run_jobs(todo, backend=plan.backend, workers=plan.workers, log=log, gpus_per_job=plan.gpus_per_run)
    with Stage(plan, "evaluation", log):
        rows, ctx_rows = [], []
        for job in jobs:
            setting = dict(plan.settings(job.method))[job.setting]
            rows += run_rows(job, setting, device=plan.device)
            final = final_eval(job, device=plan.device)
            base = {"method": job.method, "recognizer": job.recognizer, "seed": job.seed, "setting": job.setting}
            for split, summary in (final or {}).get("splits", {}).items():
                ctx_rows += [{**base, "split": split, **c} for c in summary["per_context"]]
        splits = sorted({r["split"] for r in rows}) or ["train", "hard"]
        first_tables = {r: t[plan.methods[0]] for r, t in tables.items()}
        base_rows, base_ctx = baseline_rows(plan, first_tables, splits, log)
        rows += base_rows
        if plan.sb3:
            ref_rows, ref_ctx = sb3_rows(plan, jobs, first_tables, splits, log)
            rows += ref_rows
            base_ctx += ref_ctx
        terrains = context_terrains(data)
        ctx_rows = [{**c, "terrain": terrains.get(int(c["context"]), "")} for c in ctx_rows + base_ctx]

        audit = {str(r): {"classifier": classifier_summary(classifiers[r]),
                          "splits": audit_table(tables[r][plan.methods[0]], terrains)} for r in plan.recognizers}
        atomic_write_json(plan.out / "recognizer_audit.json", audit, fsync=True)
        results = write_csv(plan.out / "results.csv", *_with_swept_columns(plan, rows))
        write_csv(plan.out / "contexts.csv", ctx_rows, CONTEXT_COLUMNS)
        traj = trajectory_rows(plan, jobs, tables[plan.recognizers[0]])
        atomic_write_json(plan.out / "trajectories.json", traj, fsync=True)
    write_meta(plan, data, "reporting")
    with Stage(plan, "report", log):
        write_meta(plan, data, "done")
        report = write_report(plan.out, figures=plan.figures)
        log(f"  report: {report}")
    write_meta(plan, data, "done")
    return results


__all__ = [
    "AblationError", "ConfigError", "Job", "Plan", "make_plan", "parse_sweeps", "run_ablation", "run_job",
]

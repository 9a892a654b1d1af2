"""A training run's directory: the one place that names its files.

==========================  =====================================================================
``settings.json``           what the run is: method, spec hash, table, seed, training and env
                            settings, torch threads (checked on resume)
``method.toml``             the resolved method spec
``checkpoint.pt``           the latest checkpoint (networks, optimizer, replay, RNG states, loop)
``evals.jsonl``             one row per (epoch, split) evaluation
``done.json``               written last: the run finished (counts, wall time, final evaluation)
``policy.safetensors``      the shareable policy: the network and its method, no replay buffer
``final_eval.json``         an ablation's exhaustive evaluation of the final policy (a cache)
``tb/``                     TensorBoard scalars
==========================  =====================================================================

``settings.json``, ``evals.jsonl`` (each line) and ``done.json`` carry the sha256 of their
content (:func:`~uevavd.hashing.seal`), checked wherever they are read: an edited or damaged
file is refused, naming it, instead of moving a result.

Beside the directory, ``.NAME.lock`` is held while a process trains into it (:func:`run_lock`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..atomic import atomic_write, folder_lock, is_temporary, load_sealed_json, write_sealed_json
from ..config import MethodSpec, load_method
from ..env.config import LEGACY_ENV
from ..hashing import DamagedFileError, is_sealed, json_digest, seal, unseal
from .config import LEGACY_TRAIN


@dataclass(frozen=True)
class RunDir:
    """The files of the run directory at ``path``."""

    path: Path

    def __init__(self, path: str | os.PathLike[str]) -> None:
        object.__setattr__(self, "path", Path(path))

    @property
    def settings(self) -> Path:
        return self.path / "settings.json"

    @property
    def method(self) -> Path:
        return self.path / "method.toml"

    @property
    def checkpoint(self) -> Path:
        return self.path / "checkpoint.pt"

    @property
    def evals(self) -> Path:
        return self.path / "evals.jsonl"

    @property
    def done(self) -> Path:
        return self.path / "done.json"

    @property
    def policy(self) -> Path:
        return self.path / "policy.safetensors"

    @property
    def final_eval(self) -> Path:
        return self.path / "final_eval.json"

    @property
    def tensorboard(self) -> Path:
        return self.path / "tb"

    @property
    def finished(self) -> bool:
        return self.done.is_file()

    def owns(self, path: str | os.PathLike[str]) -> bool:
        """Whether ``path`` is one of the files (or inside the folders) a run writes and reads
        back: writing anything else there would destroy the run."""
        own = (self.settings, self.method, self.checkpoint, self.evals, self.done, self.policy, self.final_eval)
        p = Path(path).resolve()
        tb = self.tensorboard.resolve()
        return p in {f.resolve() for f in own} or p == tb or tb in p.parents


#: Settings whose change makes a run directory another run (check_run_dir also refuses to resume an
#: unfinished run on another kind of device; progress may change).
RUN_KEYS = ("method", "spec_hash", "table_key", "seed", "train", "env", "feature_dim")


class RunDirError(ValueError):
    """A run directory holds another configuration, is not a run directory, or is being
    trained by another process."""


@contextmanager
def run_lock(run_dir: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold a run directory for one trainer. A second process training into it (the same
    ``uevavd train`` started twice, two ablations with one ``--out``) is refused with a
    :class:`RunDirError` instead of interleaving its checkpoints and evaluations with the
    first's. The lock is a file beside the directory (``.NAME.lock``), so that the run
    directory holds the run's files only, and the OS releases it when its process ends,
    however it ends. Yields the lock file's path."""
    def busy(lock_file: str) -> RunDirError:
        return RunDirError(f"{run_dir} is being trained by another process (it holds {lock_file}); "
                           "wait for that run to finish, or train into another --out")

    with folder_lock(run_dir, busy) as lock:
        yield lock


#: What to do about a run file that is damaged or was edited since the run wrote it.
RETRAIN = ("train the run again (remove its folder and rerun the `uevavd train` or `uevavd ablate` that made it), "
           "or restore the folder from a copy")


def read_settings(run_dir: str | Path) -> dict[str, Any]:
    """A run's ``settings.json``, checked against the digest written with it; a missing,
    unreadable, edited or damaged file is an error naming it."""
    path = RunDir(run_dir).settings
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a training run: no settings.json (train one with `uevavd train`)")
    settings = load_sealed_json(path, RETRAIN, legacy=not _sealed_beside(run_dir, path))
    if "env" not in settings:
        raise RunDirError(f"{path}: not a uevavd run's settings (no env section); train it again into a new --out")
    return settings


def write_settings(run_dir: str | Path, settings: dict[str, Any]) -> Path:
    """Write a run's ``settings.json``, sealed."""
    return write_sealed_json(RunDir(run_dir).settings, settings, sort_keys=True)


def _sealed_beside(run_dir: str | Path, path: Path) -> bool:
    """Whether another record of the run (``settings.json``, ``done.json``, ``evals.jsonl``'s
    first line) is sealed: then this version wrote the run, and ``path`` must be sealed too (a
    record without its digest beside sealed ones had it removed)."""
    run = RunDir(run_dir)
    for other in (run.settings, run.done, run.evals):
        if other == path or not other.is_file():
            continue
        try:
            with other.open(encoding="utf-8") as fh:  # a JSON file whole, a JSON-lines file's first line
                if is_sealed(json.loads(fh.readline() if other == run.evals else fh.read())):
                    return True
        except (OSError, ValueError):
            continue
    return False


def run_identity(settings: dict[str, Any]) -> str:
    """The digest of what makes a run this run (:data:`RUN_KEYS` of its settings): its records
    (``evals.jsonl``'s lines, ``done.json``) carry it under ``run``, so another run's copied in
    is refused (a seal proves the bytes, not whose they are)."""
    return json_digest({k: settings.get(k) for k in RUN_KEYS}, 16)


def _owned(record: dict[str, Any], run_dir: str | Path, where: str) -> dict[str, Any]:
    """``record`` without its ``run`` mark, after checking the mark is this run's (records of
    earlier versions have none)."""
    record = dict(record)
    mark = record.pop("run", None)
    if mark is not None and mark != run_identity(read_settings(run_dir)):
        raise DamagedFileError(f"{where}: written by another run (another seed, method, table or setting) and copied "
                               f"here; {RETRAIN}")
    return record


def read_done(run_dir: str | Path) -> dict[str, Any]:
    """A finished run's ``done.json`` (its counts, wall time and last evaluation), checked,
    and checked to be this run's."""
    path = RunDir(run_dir).done
    return _owned(load_sealed_json(path, RETRAIN, legacy=not _sealed_beside(run_dir, path)), run_dir, str(path))


def write_done(run_dir: str | Path, settings: dict[str, Any], record: dict[str, Any]) -> Path:
    """A finished run's ``done.json``: ``record`` sealed, with the run's mark."""
    return write_sealed_json(RunDir(run_dir).done, {**record, "run": run_identity(settings)}, sort_keys=True)


def write_evals(run_dir: str | Path, rows: list[dict[str, Any]]) -> Path:
    """A run's ``evals.jsonl``: one sealed JSON object per line, each with the run's mark."""
    mark = run_identity(read_settings(run_dir))
    return atomic_write(RunDir(run_dir).evals, "".join(json.dumps(seal({**r, "run": mark})) + "\n" for r in rows))


def read_evals(run_dir: str | Path) -> list[dict[str, Any]]:
    """A run's per-epoch evaluation rows (none before its first epoch), each checked against
    the digest written with it; a damaged or edited line is an error naming the file and line."""
    path = RunDir(run_dir).evals
    if not path.is_file():
        return []
    rows = []
    legacy = not _sealed_beside(run_dir, path)
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except ValueError as exc:
            raise DamagedFileError(f"{path}, line {n}: damaged ({exc}); {RETRAIN}") from None
        row = _owned(unseal(obj, f"{path}, line {n}", RETRAIN, legacy=legacy), run_dir, f"{path}, line {n}")
        if not isinstance(row.get("episodes"), int) or not isinstance(row.get("split"), str):
            raise DamagedFileError(f"{path}, line {n}: not an evaluation row (no episodes or split); {RETRAIN}")
        rows.append(row)
    _check_sequence(rows, path)
    if RunDir(run_dir).done.is_file():
        done = read_done(run_dir)
        if "evals_digest" in done and (len(rows), evals_digest(rows)) != (done.get("evals_rows"), done["evals_digest"]):
            raise DamagedFileError(f"{path}: {len(rows)} rows that are not the {done.get('evals_rows')} the finished run "
                                   f"recorded in done.json (lines deleted, duplicated, swapped or copied in); {RETRAIN}")
    return rows


def evals_digest(rows: list[dict[str, Any]]) -> str:
    """The digest of a run's evaluation rows, in order: ``done.json`` records it, binding
    ``evals.jsonl`` as a whole (each line's own seal cannot tell a line deleted or repeated)."""
    return json_digest(rows, 16)


def _check_sequence(rows: list[dict[str, Any]], path: Path) -> None:
    """Rows of epochs 1, 2, ... in order, each epoch's splits in the first epoch's order, none
    twice: a duplicated, deleted or swapped line of an unfinished run is named too."""
    if not rows or not all(isinstance(r.get("epoch"), int) for r in rows):
        return  # an earlier version's rows carry no epoch
    splits = [r["split"] for r in rows if r["epoch"] == rows[0]["epoch"]]
    splits = splits[:next((i for i in range(1, len(splits)) if splits[i] in splits[:i]), len(splits))]
    epochs = -(-len(rows) // len(splits))  # a deleted line leaves an epoch short, named below
    want = [(e, s) for e in range(1, epochs + 1) for s in splits]
    have = [(r["epoch"], r["split"]) for r in rows]
    if have != want:
        i = next(i for i in range(len(want) + 1) if i >= len(have) or i >= len(want) or have[i] != want[i])
        found = f"epoch {have[i][0]}, split {have[i][1]}" if i < len(have) else "no row"
        expected = f"epoch {want[i][0]}, split {want[i][1]}" if i < len(want) else "no row"
        raise DamagedFileError(f"{path}, line {i + 1}: {found} where {expected} belongs (lines deleted, duplicated "
                               f"or swapped); {RETRAIN}")


def run_spec(run_dir: str | Path) -> MethodSpec:
    """The method spec saved in a run directory, checked against the spec hash its sealed
    ``settings.json`` records (an edited ``method.toml`` is an error naming it)."""
    path = RunDir(run_dir).method
    if not path.is_file():
        raise RunDirError(f"{run_dir} is not a training run: no method.toml")
    spec = load_method(path)
    recorded = read_settings(run_dir).get("spec_hash") if RunDir(run_dir).settings.is_file() else None
    if recorded is not None and spec.hash != recorded:
        raise DamagedFileError(f"{path}: edited since the run wrote it (its spec hash is {spec.hash}, the run's "
                               f"settings.json records {recorded}); {RETRAIN}")
    return spec


def with_legacy_settings(recorded: dict[str, Any]) -> dict[str, Any]:
    """A run's recorded settings (``settings.json``, a checkpoint's meta) with the ``train``
    and ``env`` settings it predates filled in as it ran (:data:`LEGACY_TRAIN`,
    :data:`~uevavd.env.config.LEGACY_ENV`), so that resuming a run of an earlier version
    compares like with like: it resumes when nothing else differs, and a setting that does
    differ is named instead of a missing key."""
    out = dict(recorded)
    for key, legacy in (("train", LEGACY_TRAIN), ("env", LEGACY_ENV)):
        if isinstance(out.get(key), dict):
            out[key] = {**legacy, **out[key]}
    return out


def check_run_dir(out: Path, settings: dict[str, Any]) -> None:
    path = RunDir(out).settings
    if out.exists() and not out.is_dir():
        raise RunDirError(f"--out {out} is a file, not a run directory: choose a new --out (or a run's folder, "
                          "to resume it)")
    if not path.is_file():
        # a run killed before its settings.json leaves at most its method.toml (written first by
        # earlier versions), tb/ and the temporary file of a write it was killed in: that folder is
        # an unstarted run, not someone else's (the trainer removes the temporary)
        unstarted = {RunDir(out).tensorboard, RunDir(out).method}
        if out.exists() and any(p not in unstarted and not is_temporary(p) for p in out.iterdir()):
            raise RunDirError(f"{out} exists and is not a training run (no settings.json); choose an empty --out")
        return
    old = with_legacy_settings(read_settings(out))  # a damaged file is named, as evaluate names it
    diffs = []
    for k in RUN_KEYS:
        if old.get(k) != settings.get(k):
            if isinstance(old.get(k), dict) and isinstance(settings.get(k), dict):
                for kk in sorted(set(old[k]) | set(settings[k])):
                    if old[k].get(kk) != settings[k].get(kk):
                        diffs.append(f"{k}.{kk}: run has {old[k].get(kk)!r}, now {settings[k].get(kk)!r}")
            else:
                diffs.append(f"{k}: run has {old.get(k)!r}, now {settings.get(k)!r}")
    if diffs:
        raise RunDirError(f"{out} holds a run of another configuration ({'; '.join(diffs)}); "
                          "use another --out, or the same settings to resume it")
    # the device changes a run's numbers (other kernels): an unfinished run resumes on the kind
    # it started on, so that it ends as an uninterrupted run would (another GPU of the kind is fine)
    was, now = str(old.get("device") or ""), str(settings.get("device") or "")
    if was and now and was.split(":")[0] != now.split(":")[0] and not RunDir(out).finished:
        raise RunDirError(f"{out} was trained on {was} so far; resuming it on {now} would go on with other "
                          f"kernels, and the run would differ from an uninterrupted one: resume with --device {was}, "
                          "or train on the other device into a new --out")

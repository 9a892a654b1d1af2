"""A cold start killed at random moments, resumed each time, against one left alone.

    python benchmarks/kill_resume.py [--kills 8] [--seed 0] [--no-zoo] [--keep DIR]

Runs `uevavd demo` from an empty cache twice, in the same folder (so every path it records is
the same): once uninterrupted (its time T), then again, killed with SIGKILL (its whole process
group, workers included) after a random delay of 5 % to 40 % of T from each start, `--kills`
times, and finally left to finish. Prints the stage each kill fell in (the demo's last line of
output), then compares every file of both caches and output folders:

- files only in one of them (a temporary file left behind counts);
- files whose content differs, after leaving out what records how long a stage took or when a
  file was written, and the seals over them (``wall_s``, ``seconds``, ``stages``, ``mtime_ns``, ``ctime_ns``
  and ``sha256`` keys in JSON, ablation.json's digests of its output files (compared themselves), ``sha256`` arrays in ``.npz``, ``wall_s*`` columns in CSV, the
  report's stage-timing rows and durations in seconds in Markdown). A table's cache key and its scenes' file names hash the world's
  file times (a cache key, not content), so the killed run's keys are mapped to the
  uninterrupted run's by the table's settings and the scene before comparing; lock files,
  TensorBoard event files (named by their start time, one per resume) and the world's check
  stamps (``.verified.json``, file times) are not compared.

Exits 1 when any file is missing, left over or different. About 3 x T on 2 cores (T is
2.5 to 4 minutes); nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from machine_speed import refwork
from safetensors import safe_open

DEMO = [sys.executable, "-c", "import sys; from uevavd.cli import entry; sys.exit(entry())", "demo"]
#: keys and columns that record a duration, and the seals computed over them
TIMING_KEYS = re.compile(r"^(wall|wall_s.*|seconds|stages|sha256|meta_sha256|evals_digest|outputs|mtime_ns|ctime_ns)$")
STAGE_ROW = re.compile(r"^\| (\*\*)?(world|classifier|tables|training|evaluation|report|total)(\*\*)? \| ")
SKIPPED = re.compile(r"(^|/)(\.[^/]*\.lock|events\.out\.tfevents\.[^/]*|\.verified\.json)$")
SCENE_FILE = re.compile(r"^(\d{3}|00|train_605)-([0-9a-f]{16})\.npz$")


def start(work: Path, log: Path, extra: list[str]) -> subprocess.Popen:
    env = {**os.environ, "UEVAVD_CACHE": str(work / "cache"), "SOURCE_DATE_EPOCH": "1700000000"}
    with open(log, "ab") as out:
        return subprocess.Popen([*DEMO, "--out", str(work / "demo"), *extra], cwd=work, env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)


def last_line(log: Path) -> str:
    text = log.read_bytes().decode(errors="replace").replace("\r", "\n")
    lines = [s.strip() for s in text.splitlines() if s.strip()]
    return lines[-1][:100] if lines else "(no output yet)"


def _drop_timing(x):
    """``x`` (JSON, or a checkpoint's objects) as comparable JSON, without its timing keys;
    tensors and arrays as their dtype, shape and bytes' hash, JSON inside strings parsed."""
    if isinstance(x, dict):
        return {str(k): _drop_timing(v) for k, v in x.items() if not TIMING_KEYS.match(str(k))}
    if isinstance(x, (list, tuple)):
        return [_drop_timing(v) for v in x]
    if isinstance(x, str) and x[:1] in "[{":
        try:
            return _drop_timing(json.loads(x))
        except ValueError:
            return x
    if torch.is_tensor(x):
        x = x.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy() if x.numel() else x.cpu().numpy()
    if isinstance(x, np.ndarray):
        return [str(x.dtype), list(x.shape), hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()]
    if isinstance(x, (int, float, bool)) or x is None:
        return x
    return repr(x)


def key_map(ref: Path, killed: Path) -> dict[str, str]:
    """The killed run's time-derived cache keys -> the uninterrupted run's (the folders holding
    ``cache`` and ``demo``): each table's key and dataset fingerprint (tables matched by their
    settings), each scene file's hash, and each run's id (a hash of its table's key)."""
    def tables(cache: Path) -> dict[str, tuple[str, str]]:
        out = {}
        for meta in (cache / "tables").glob("*/meta.json"):
            cfg = json.loads(meta.read_text())["config"]
            dataset = cfg["key_parts"].pop("dataset")
            out[json.dumps(cfg, sort_keys=True)] = (meta.parent.name, dataset)
        return out

    def scenes(cache: Path) -> dict[tuple[str, str], str]:
        return {(str(p.parent.relative_to(cache)), m.group(1)): m.group(2)
                for p in (cache / "tables").glob("*/*/*.npz") if (m := SCENE_FILE.match(p.name))}

    out: dict[str, str] = {}
    a, b = tables(ref / "cache"), tables(killed / "cache")
    for sig, (key, dataset) in b.items():
        if sig in a:
            out |= {key: a[sig][0], dataset: a[sig][1]}
    sa, sb = scenes(ref / "cache"), scenes(killed / "cache")
    out |= {h: sa[k] for k, h in sb.items() if k in sa}
    for done in (killed / "demo").glob("runs/**/done.json"):
        other = ref / "demo" / done.relative_to(killed / "demo")
        if other.is_file():
            out[json.loads(done.read_text())["run"]] = json.loads(other.read_text())["run"]
    return {k: v for k, v in out.items() if k != v}


def mapped(text: str, keys: dict[str, str]) -> str:
    return re.sub("|".join(map(re.escape, keys)), lambda m: keys[m.group(0)], text) if keys else text


def normalised(path: Path, keys: dict[str, str]) -> bytes:
    """The file's content less what records a duration or a file time (see the module's
    docstring), with ``keys`` mapped."""
    if path.suffix == ".npz":
        with np.load(path) as z:
            return b"".join(n.encode() + str((z[n].dtype, z[n].shape)).encode() + z[n].tobytes()
                            for n in sorted(z.files) if n != "sha256")
    if path.suffix == ".pt":
        obj = torch.load(path, map_location="cpu", weights_only=False)
        return mapped(json.dumps(_drop_timing(obj), sort_keys=True), keys).encode()
    if path.suffix == ".safetensors":
        with safe_open(path, "pt") as f:
            obj = {"metadata": f.metadata(), "tensors": {k: f.get_tensor(k) for k in f.keys()}}  # noqa: SIM118
        return mapped(json.dumps(_drop_timing(obj), sort_keys=True), keys).encode()
    data = mapped(path.read_bytes().decode("latin-1"), keys).encode("latin-1")
    if path.suffix == ".json":
        return json.dumps(_drop_timing(json.loads(data)), sort_keys=True).encode()
    if path.suffix == ".jsonl":
        return b"\n".join(json.dumps(_drop_timing(json.loads(s)), sort_keys=True).encode()
                          for s in data.splitlines() if s.strip())
    if path.suffix == ".csv":
        rows = list(csv.reader(io.StringIO(data.decode())))
        keep = [i for i, name in enumerate(rows[0] if rows else []) if not name.startswith("wall_s")]
        return "\n".join(",".join(r[i] for i in keep if i < len(r)) for r in rows).encode()
    if path.suffix == ".md":  # the report's stage rows; a duration in seconds anywhere
        return re.sub(rb"\b\d+(\.\d+)? s\b", b"N s", b"\n".join(
            s for s in data.splitlines() if not STAGE_ROW.match(s.decode(errors="replace"))))
    return data


def compare(a: Path, b: Path, keys: dict[str, str]) -> tuple[int, list[str]]:
    """(files compared, problems) between two trees, ``b``'s cache keys mapped by ``keys``."""
    files = {p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()}
    other = {mapped(p.relative_to(b).as_posix(), keys): p for p in b.rglob("*") if p.is_file()}
    problems = [f"only in the uninterrupted run: {f}" for f in sorted(files - other.keys()) if not SKIPPED.search(f)]
    problems += [f"left by the killed run: {f}" for f in sorted(other.keys() - files) if not SKIPPED.search(f)]
    same = sorted(f for f in files & other.keys() if not SKIPPED.search(f))
    problems += [f"differs: {f}" for f in same if normalised(a / f, {}) != normalised(other[f], keys)]
    return len(same), problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=8, help="kills before the run is left to finish (default 8)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the kill delays (default 0)")
    ap.add_argument("--no-zoo", action="store_true", help="the demo trains its recognizer (kills can fall in it)")
    ap.add_argument("--keep", type=Path, default=None, help="keep both runs' folders in DIR")
    args = ap.parse_args()
    extra = ["--no-zoo"] if args.no_zoo else []
    print(refwork(), flush=True)
    base = Path(tempfile.mkdtemp(prefix="uevavd-kill-")) if args.keep is None else args.keep.resolve()
    work, ref, killed = base / "work", base / "uninterrupted", base / "killed"
    for p in (work, ref, killed):
        if p.exists():
            sys.exit(f"kill_resume: {p} exists: give --keep an empty or new folder")
    work.mkdir(parents=True)
    t0 = time.perf_counter()
    rc = start(work, base / "uninterrupted.log", extra).wait()
    total = time.perf_counter() - t0
    if rc:
        sys.exit(f"kill_resume: the uninterrupted demo exited {rc}: see {base / 'uninterrupted.log'}")
    print(f"uninterrupted: {total:.0f} s", flush=True)
    work.rename(ref)
    work.mkdir()
    rng = random.Random(args.seed)
    log = base / "killed.log"
    attempts = 0
    for k in range(args.kills):
        delay = rng.uniform(0.05, 0.4) * total
        proc = start(work, log, extra)
        attempts += 1
        try:
            proc.wait(timeout=delay)
            print(f"kill {k + 1}: the run finished within {delay:.0f} s", flush=True)
            break
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            print(f"kill {k + 1} after {delay:.0f} s, at: {last_line(log)}", flush=True)
    else:
        t1 = time.perf_counter()
        rc = start(work, log, extra).wait()
        attempts += 1
        if rc:
            sys.exit(f"kill_resume: the last resume exited {rc}: see {log}")
        print(f"resumed to the end: {time.perf_counter() - t1:.0f} s", flush=True)
    work.rename(killed)
    n = 0
    problems: list[str] = []
    keys = key_map(ref, killed)
    for part in ("cache", "demo"):
        m, found = compare(ref / part, killed / part, keys)
        n += m
        problems += [f"{part}/{p}" for p in found]
    print(f"{attempts} starts; {n} files compared; {len(problems)} problems")
    for p in problems[:50]:
        print("  " + p)
    if args.keep is None:
        shutil.rmtree(base, ignore_errors=True)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())

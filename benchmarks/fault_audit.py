"""A fault audit of the integrity classes: offline datasets, policy formats, run records,
report inputs, stopping and simple mistakes. Each case damages a copy of a freshly made
artefact (a tiny ablation, an exported Minari dataset, a policy file) as a user or a disk
might, runs what a user runs on it, and classifies the outcome:

- right: refused in one line that names the file or value (exit 2 on the command line, a
  ValueError from the API), no traceback;
- wrong: refused, but with a traceback or a raw error that names neither;
- silent: accepted, with a result that is not the artefact's;
- lost: finished work gone.

    python benchmarks/fault_audit.py            # about 3 minutes on 2 cores
    python benchmarks/fault_audit.py --keep DIR # keep the artefacts in DIR

Prints one row per case and the tally; exits 1 when any case is not right.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ENTRY = [sys.executable, "-c", "from uevavd.cli import entry; entry()"]
ROWS: list[tuple[str, str, str]] = []


def uevavd(*args: str, env: dict | None = None, timeout: int = 900) -> subprocess.CompletedProcess:
    return subprocess.run([*ENTRY, *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def record(case: str, outcome: str, detail: str) -> None:
    ROWS.append((case, outcome, detail.strip().splitlines()[-1][:150] if detail.strip() else ""))
    print(f"{outcome:7s} {case:58s} {ROWS[-1][2]}", flush=True)


def cli_case(case: str, args: list, names: str, env: dict | None = None) -> None:
    """A command that must refuse: exit 2, one line naming ``names``."""
    out = uevavd(*args, env=env)
    err = out.stderr.strip()
    if out.returncode == 0:
        record(case, "silent", out.stdout)
    elif out.returncode == 2 and "Traceback" not in err and len(err.splitlines()) == 1 and names in err:
        record(case, "right", err)
    else:
        record(case, "wrong", f"exit {out.returncode}: {err}")


def api_case(case: str, call: Callable[[], object], names: str) -> None:
    """An API call that must refuse with a ValueError (or OSError) naming ``names``."""
    try:
        call()
    except (ValueError, OSError) as exc:
        text = str(exc)
        record(case, "right" if names in text and "\n" not in text else "wrong", f"{type(exc).__name__}: {text}")
    except Exception as exc:  # noqa: BLE001 - a raw error is the finding
        record(case, "wrong", f"{type(exc).__name__}: {exc}")
    else:
        record(case, "silent", "accepted")


def ablation(root: Path) -> Path:
    from uevavd.testing.worlds import tiny_preset, write_tiny_world

    write_tiny_world(root / "world", contexts=(1, 26, 31, 56))
    (root / "tiny.toml").write_text(tiny_preset(episodes=200))
    out = uevavd("ablate", "--preset", root / "tiny.toml", "--data", root / "world", "--methods", "map", "--seeds", "1",
                 "--out", root / "abl", "--no-zoo", "--no-figures", env={"UEVAVD_CACHE": str(root / "cache")})
    if out.returncode != 0:
        raise SystemExit(f"the tiny ablation failed: {out.stderr[-2000:]}")
    return root / "abl"


def table_of(root: Path) -> Path:
    """The tiny ablation's observation table (a folder of the cache's tables)."""
    return next(p for p in (root / "cache" / "tables").iterdir() if (p / "meta.json").is_file())


def copy_of(src: Path, name: str) -> Path:
    dst = src.parent / name
    shutil.copytree(src, dst)
    return dst


def report_inputs(abl: Path) -> None:
    cuts = {"results.csv cut inside the last field": ("results.csv", lambda t: t[:-3]),
            "results.csv cut at a row boundary": ("results.csv", lambda t: "".join(t.splitlines(True)[:-5])),
            "contexts.csv cut mid-row": ("contexts.csv", lambda t: t[: len(t) - len(t.splitlines(True)[-1]) // 2 - 1])}
    for i, (case, (name, cut)) in enumerate(cuts.items()):
        folder = copy_of(abl, f"cut{i}")
        (folder / name).write_text(cut((folder / name).read_text()))
        cli_case(case, ["report", folder, "--no-figures"], name)


def run_records(abl: Path, root: Path) -> None:
    edits = {"evals.jsonl: a line duplicated": lambda ls: [ls[0], *ls],
             "evals.jsonl: a line deleted": lambda ls: ls[:1] + ls[2:],
             "evals.jsonl: two lines swapped": lambda ls: [ls[1], ls[0], *ls[2:]],
             "evals.jsonl: a finished run's last lines deleted": lambda ls: ls[:-2]}
    for i, (case, edit) in enumerate(edits.items()):
        folder = copy_of(abl, f"evals{i}")
        run = next(folder.glob("runs/map/default/rec*/seed*"))
        lines = (run / "evals.jsonl").read_text().splitlines()
        (run / "evals.jsonl").write_text("\n".join(edit(lines)) + "\n")
        cli_case(case + " (ablate resumes)", ["ablate", "--preset", root / "tiny.toml", "--data", root / "world",
                                              "--methods", "map", "--seeds", "1", "--out", folder, "--no-zoo",
                                              "--no-figures"], "evals.jsonl", env={"UEVAVD_CACHE": str(root / "cache")})


def policy_formats(abl: Path, root: Path) -> None:
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from uevavd.presets import ZOO

    run = next(abl.glob("runs/map/default/rec*/seed*"))
    src = run / "policy.safetensors"
    table = table_of(root)
    with safe_open(str(src), framework="pt") as fh:
        meta = dict(fh.metadata())
    settings = json.loads(meta["settings"])
    settings["env"]["thre"] = 0.1
    legacy = root / "legacy.safetensors"
    save_file(load_file(str(src)), str(legacy), metadata={"format": "uevavd-policy/1", "method_toml": meta["method_toml"],
                                                          "settings": json.dumps(settings)})
    env = {"UEVAVD_CACHE": str(root / "cache")}
    cli_case("policy rewritten as format 1 with env.thre edited", ["evaluate", legacy, "--table", table], "legacy",
             env=env)
    weights = load_file(str(src))
    key = next(iter(weights))
    weights[key] = weights[key] + 1e-3
    edited = root / "weight.safetensors"
    save_file(weights, str(edited), metadata=meta)
    cli_case("policy with one weight edited", ["evaluate", edited, "--table", table], "weight.safetensors", env=env)
    shipped = ZOO / "pretrained" / "quick" / "map.safetensors"
    with safe_open(str(shipped), framework="pt") as fh:
        header = dict(fh.metadata())
    copy = root / "zoo_copy.safetensors"
    save_file(load_file(str(shipped)), str(copy), metadata={**header, "method_toml": header["method_toml"] + "\n"})
    cli_case("the zoo's format-1 policy, header edited", ["evaluate", copy, "--table", table], "zoo_copy", env=env)


def offline(root: Path) -> None:
    try:
        import h5py
        import minari  # noqa: F401
    except ImportError:
        record("Minari datasets", "skipped", "minari is not installed (the clients extra)")
        return
    import numpy as np

    from uevavd.env.offline import flat_dataset
    from uevavd.paths import tables_dir
    from uevavd.policy.minari_export import export_minari
    from uevavd.testing.policy import toy_table

    os.environ["UEVAVD_CACHE"] = str(root / "mcache")
    os.environ["MINARI_DATASETS_PATH"] = str(root / "datasets")
    table = toy_table(n_train=3, n_hard=2, feature_dim=8)
    folder = table.save(tables_dir() / table.key)
    data = export_minari(folder, "train", "random", "uevavd/audit-v0", episodes=20, progress=False)
    path = Path(data.storage.data_path) / "main_data.hdf5"
    pristine = path.read_bytes()

    def damaged(edit: Callable[[h5py.File], None]) -> Callable[[], object]:
        def call():
            path.write_bytes(pristine)
            with h5py.File(path, "r+") as f:
                edit(f)
            return flat_dataset(minari.load_dataset("uevavd/audit-v0"))
        return call

    def replace(f, key, value):
        del f[key]
        f[key] = value

    import minari

    ep = "episode_3"
    cases = {
        "actions stored as floats": (lambda f: replace(f, f"{ep}/actions", f[f"{ep}/actions"][()] - 0.3), "actions"),
        "an action type 9 of 7": (lambda f: f[f"{ep}/actions"].__setitem__((0, 0), 9), "actions"),
        "an action range -3": (lambda f: f[f"{ep}/actions"].__setitem__((0, 1), -3), "actions"),
        "actions one shorter than the steps": (lambda f: replace(f, f"{ep}/actions", f[f"{ep}/actions"][:-1]),
                                               "actions"),
        "observations stored as int8": (lambda f: replace(f, f"{ep}/observations/box",
                                                          f[f"{ep}/observations/box"][()].astype(np.int8)), "box"),
        "a NaN reward": (lambda f: f[f"{ep}/rewards"].__setitem__(0, np.nan), "rewards"),
        "a missing episode group": (lambda f: f.__delitem__(ep), ep),
    }
    for case, (edit, key) in cases.items():
        api_case(f"Minari: {case}", damaged(edit), key)
    path.write_bytes(pristine[: len(pristine) // 2])
    api_case("Minari: a truncated file", lambda: flat_dataset(minari.load_dataset("uevavd/audit-v0")), "main_data")
    path.write_bytes(b"")
    api_case("Minari: an emptied file", lambda: flat_dataset(minari.load_dataset("uevavd/audit-v0")), "main_data")
    path.write_bytes(pristine)
    loaded = minari.load_dataset("uevavd/audit-v0")
    holder = subprocess.Popen([sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r+'); "
                               "print('held', flush=True); time.sleep(60)", str(path)], stdout=subprocess.PIPE, text=True)
    try:  # another process writing the file holds HDF5's lock
        holder.stdout.readline()
        api_case("Minari: a file another process holds open for writing", lambda: flat_dataset(loaded), "main_data")
    finally:
        holder.kill()
        holder.wait()
    other = export_minari(folder, "train", "passive", "uevavd/audit-other-v0", episodes=3, progress=False)
    shutil.copyfile(Path(other.storage.data_path) / "main_data.hdf5", path)  # swapped under the loaded dataset
    api_case("Minari: the file swapped under a loaded dataset", lambda: flat_dataset(loaded), "main_data")
    path.write_bytes(pristine)
    for workers in ("2", 2.5, 0, -1):
        api_case(f"flat_dataset(workers={workers!r})", lambda w=workers: flat_dataset(loaded, workers=w), "workers")
    api_case("flat_dataset([{'a': 1}])", lambda: flat_dataset([{"a": 1}]), "episode")


def stopping(root: Path) -> None:
    from uevavd.testing.worlds import tiny_preset

    (root / "long.toml").write_text(tiny_preset(episodes=200_000))
    env = {**os.environ, "UEVAVD_CACHE": str(root / "cache")}
    proc = subprocess.Popen([*ENTRY, "ablate", "--preset", str(root / "long.toml"), "--data", str(root / "world"),
                             "--methods", "map", "--seeds", "1", "--out", str(root / "long"), "--no-zoo",
                             "--no-figures"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 300
    while not list((root / "long").glob("runs/*/*/*/*/evals.jsonl")) and time.monotonic() < deadline:
        time.sleep(0.5)
    start = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    took = time.monotonic() - start
    kept = list((root / "long").glob("runs/*/*/*/*/evals.jsonl"))
    ok = proc.returncode == 143 and "Traceback" not in err and took < 10 and kept
    record(f"SIGTERM to a training ablation (stopped in {took:.1f} s)", "right" if ok else "wrong",
           err.strip() or f"exit {proc.returncode}")


def mistakes(root: Path) -> None:
    tmp = root / "scratch"
    tmp.mkdir()
    for args, names in [(["train", "--method", "map", "--table", "/nonexistent/table", "--out", tmp / "o"], "table"),
                        (["train-classifier", tmp, "--imagenet", "/nonexistent/r18.pth"], "r18.pth"),
                        (["prepare", tmp, "--method", "map", "--classifier", "/nonexistent/c.safetensors"],
                         "c.safetensors"),
                        (["ablate", "--seeds", "0", "--out", tmp / "o"], "--seeds")]:
        start = time.monotonic()
        out = uevavd(*args)
        took = time.monotonic() - start
        one = out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and names in out.stderr
        record(f"{' '.join(map(str, args[:2]))} ... refused in {took:.1f} s", "right" if one and took < 3 else "wrong",
               out.stderr)
    for key, value in (("train.stop_threshold", "0.7"), ("train.imitation_fraction", "0.5")):
        cli_case(f"--set {key} that nothing reads", ["train", "--method", "map", "--preset", root / "tiny.toml",
                                                     "--table", table_of(root), "--out", tmp / "r", "--set",
                                                     f"{key}={value}"], key,
                 env={"UEVAVD_CACHE": str(root / "cache")})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, default=None, help="keep the artefacts in this folder")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="uevavd-audit-")) if args.keep is None else args.keep
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        abl = ablation(root)
        results = (abl / "results.csv").read_bytes()
        report_inputs(abl)
        run_records(abl, root)
        policy_formats(abl, root)
        offline(root)
        mistakes(root)
        stopping(root)
        lost = (abl / "results.csv").read_bytes() != results
        record("the ablation's own files after every case", "lost" if lost else "right", "unchanged")
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    tally = {o: sum(1 for _, x, _ in ROWS if x == o) for o in ("right", "wrong", "silent", "lost", "skipped")}
    print(f"\n{len(ROWS)} cases in {time.monotonic() - t0:.0f} s: " + ", ".join(f"{n} {o}" for o, n in tally.items()))
    return 0 if tally["right"] + tally["skipped"] == len(ROWS) else 1


if __name__ == "__main__":
    raise SystemExit(main())

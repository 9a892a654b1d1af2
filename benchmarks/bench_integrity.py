"""What the integrity checks cost: each artefact the library reads back, read with
its digest check and without it, in one process, beside the work that reads it.

On a stand-in table (`uevavd.testing.policy.toy_table`) of the quick preset's size (20 train,
5 simple, 5 hard contexts, 160-d features; ``--paper``: 100 / 25 / 25 and 2048-d) and a run
trained on it with the preset's training settings for ``--episodes``:

* the table: ``ObservationTable.load`` (its meta digest, the small arrays' sha256 in full, the
  features by size and times) against ``np.load`` of the four arrays, memory-mapped;
* the checkpoint: ``load_checkpoint`` (the zip records' CRCs, then ``torch.load``) against
  ``torch.load`` alone;
* the policy file: ``read_policy_file`` (the weights hash) against safetensors' ``load_file``;
* ``final_eval.json``: ``read_sealed_json`` against ``json.load``;
* ``evals.jsonl`` and ``done.json``: ``read_evals`` / ``read_done`` (each record's seal, its run's
  mark against the run's settings, the seal of the records beside it) against ``json.loads``;
* a per-scene cache: ``load_sealed_arrays`` (the arrays' digest bound to the file's place)
  against ``np.load``;

and, for scale, the run's training time and one exhaustive evaluation of its policy on the
hard split (what ``uevavd evaluate`` and an ablation's final evaluation run after the reads):
the last column is each check's extra time as a share of those.

Run: ``python benchmarks/bench_integrity.py [--paper] [--episodes 2000] [--repeat 5]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paper", action="store_true", help="the paper's sizes (100/25/25 contexts, 2048-d)")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    import numpy as np
    import torch
    from safetensors.torch import load_file

    from uevavd.atomic import read_sealed_json, write_sealed_json
    from uevavd.config import load_method
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.perception.shards import load_sealed_arrays, save_sealed_arrays
    from uevavd.policy.acting import load_policy
    from uevavd.policy.checkpoint import load_checkpoint, read_policy_file
    from uevavd.policy.rundir import RunDir, read_done, read_evals
    from uevavd.policy.trainer import train
    from uevavd.presets import load_preset
    from uevavd.table import ARRAYS, ObservationTable
    from uevavd.testing.policy import toy_table

    torch.set_num_threads(1)
    preset = "paper" if args.paper else "quick"
    n_train, n_test, dim = (100, 25, 2048) if args.paper else (20, 5, 160)
    overrides = {k: v for k, v in load_preset(preset).get("overrides", {}).items() if not k.startswith("perception.")}
    overrides.update({"train.episodes": args.episodes, "train.epoch_episodes": args.episodes,
                      "train.eval_contexts": 1, "state.input_dim": overrides.get("state.input_dim", 544)})
    with tempfile.TemporaryDirectory() as tmp:
        folder = toy_table(n_train=n_train, n_hard=n_test, n_simple=n_test, feature_dim=dim).save(Path(tmp) / "table")
        spec = load_method("map", overrides=overrides)
        run = Path(tmp) / "run"
        t0 = time.perf_counter()
        train(spec, folder, out=run, device="cpu", progress=False)
        train_s = time.perf_counter() - t0
        rd = RunDir(run)
        table = ObservationTable.load(folder)
        policy = load_policy(run)
        t0 = time.perf_counter()
        result = evaluate_policy(table, "hard", policy)
        eval_s = time.perf_counter() - t0
        write_sealed_json(Path(tmp) / "final_eval.json", {"hard": result.summary()})
        cache = Path(tmp) / "probs" / "0123456789abcdef" / "001-scene.npz"  # a scene's probabilities
        cache.parent.mkdir(parents=True)
        save_sealed_arrays(cache, {"array": np.asarray(table.probs[0])})
        shape = {"array": (np.asarray(table.probs[0]).shape, np.dtype(np.float32))}
        rows = [
            ("table load", lambda: ObservationTable.load(folder),
             lambda: [np.load(folder / f"{n}.npy", mmap_mode="r") for n in ARRAYS], folder),
            ("checkpoint load", lambda: load_checkpoint(rd.checkpoint),
             lambda: torch.load(rd.checkpoint, map_location="cpu", weights_only=True), rd.checkpoint),
            ("policy file read", lambda: read_policy_file(rd.policy), lambda: load_file(str(rd.policy)), rd.policy),
            ("final_eval.json read", lambda: read_sealed_json(Path(tmp) / "final_eval.json"),
             lambda: json.loads((Path(tmp) / "final_eval.json").read_text()), Path(tmp) / "final_eval.json"),
            ("evals.jsonl read", lambda: read_evals(run),
             lambda: [json.loads(line) for line in rd.evals.read_text().splitlines()], rd.evals),
            ("done.json read", lambda: read_done(run), lambda: json.loads(rd.done.read_text()), rd.done),
            ("scene cache read", lambda: load_sealed_arrays(cache, shape),
             lambda: np.load(cache)["array"], cache),
        ]
        print(f"{preset} sizes: {n_train}/{n_test}/{n_test} contexts, {dim}-d features; MAP trained "
              f"{args.episodes} episodes in {train_s:.1f} s; one exhaustive evaluation on hard {eval_s:.2f} s")
        print(f"{'artefact':<22}{'MB':>8}{'checked s':>12}{'bare s':>10}{'extra s':>10}{'x bare':>8}"
              f"{'% of run':>10}")
        for name, checked, bare, path in rows:
            size = sum(p.stat().st_size for p in Path(path).glob("*")) if Path(path).is_dir() else path.stat().st_size
            c, b = _best(checked, args.repeat), _best(bare, args.repeat)
            print(f"{name:<22}{size / 2**20:>8.1f}{c:>12.4f}{b:>10.4f}{c - b:>10.4f}{c / b:>8.1f}"
                  f"{100 * (c - b) / (train_s + eval_s):>9.2f}%")
        print(f"(best of {args.repeat}; % of run: of the training and one evaluation above, "
              f"{train_s + eval_s:.1f} s; the run's epochs took "
              f"{statistics.mean(json.loads(line)['wall_s'] for line in rd.evals.read_text().splitlines()):.2f} s each)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

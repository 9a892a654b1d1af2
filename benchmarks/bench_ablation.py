"""Wall time of an ablation's training runs (methods x seeds), side by side on one device.

    python benchmarks/bench_ablation.py [--device cuda] [--workers 15] [--seeds 5]
        [--methods map,memo_map,ibe_map] [--preset paper] [--episodes N] [--out runs/bench_ablation]

The runs `uevavd ablate --preset PRESET` trains (the paper preset: 300,000 episodes each, an
exhaustive evaluation on train, simple and hard every 10,000, then the final evaluation),
through the ablation's own runner (`uevavd.experiments.backends.run_jobs`: ``--workers``
spawned processes, each run on its method's `train.threads`, 1), on a stand-in table with the
paper's sizes: 2048-d features, 100 train, 25 simple and 25 hard contexts
(`uevavd.testing.policy.toy_table`). A run's time depends on the sizes, not on the
features' content, so this times the training part of an ablation without its world,
recognizer and tables (`bench_prepare.py` and `uevavd ablate` time those). The returns it
prints are a stand-in's: timings only, never results.

Resumes: run the same command again after an interruption (Ctrl-C, `timeout -s INT`) and
the runs go on from their checkpoints. Each call's wall time is added to OUT/timing.json,
so the total printed is the time the runs took over however many calls (the calls'
start-up, a few seconds each, included).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--workers", type=int, default=None, help="runs side by side (default: all of them)")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--methods", default="map,memo_map,ibe_map")
    ap.add_argument("--preset", default="paper", help="whose training settings (`overrides`) the runs take")
    ap.add_argument("--episodes", type=int, default=None, help="episodes per run (default: the preset's)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_ablation"))
    args = ap.parse_args()

    from uevavd.atomic import atomic_write
    from uevavd.config import load_method
    from uevavd.experiments.backends import run_jobs
    from uevavd.experiments.jobs import Job, save_spec
    from uevavd.experiments.results import is_done
    from uevavd.presets import load_preset, preset_overrides
    from uevavd.runtime import resolve_device, tune_malloc
    from uevavd.table import ObservationTable

    try:  # before any work: a CUDA device that is not there would otherwise fail in every worker
        resolve_device(args.device)
    except ValueError as e:
        print(f"bench_ablation: --device: {e}", file=sys.stderr)
        return 2
    tune_malloc()
    over = preset_overrides(load_preset(args.preset))
    if args.episodes is not None:
        over["train.episodes"] = args.episodes
    workers = args.workers or args.seeds * len(args.methods.split(","))
    # the timings of one configuration only: a call with another would add up unlike times
    # (and retrain runs whose settings changed)
    config = {"preset": args.preset, "episodes": over.get("train.episodes"), "methods": args.methods,
              "seeds": args.seeds, "device": args.device, "workers": workers}
    timing_path = args.out / "timing.json"
    timing = json.loads(timing_path.read_text()) if timing_path.is_file() else {"config": config, "calls": []}
    if timing.get("config") != config:
        print(f"bench_ablation: {args.out} holds the timings of {timing.get('config')}, not of {config}; "
              "use another --out", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    table = args.out / "table"
    if not table.is_dir():
        from uevavd.testing.policy import toy_table

        print("writing the stand-in table (150 contexts x 605 views x 2048-d) ...", flush=True)
        toy_table(n_train=100, n_hard=25, n_simple=25, feature_dim=2048).save(table)
    print(ObservationTable.load(table).describe())

    jobs = []
    for method in args.methods.split(","):
        try:
            spec = load_method(method, overrides=over)
            spec.train_config()  # the settings' own checks, before any run starts
        except ValueError as e:  # ConfigError, an unknown method
            print(f"bench_ablation: {method}: {e}", file=sys.stderr)
            return 2
        spec_path = save_spec(spec, args.out / "specs" / f"{method}.toml")
        jobs += [Job(method, "default", seed, str(spec_path), str(table), str(args.out / "runs" / method / f"seed{seed}"),
                     device=args.device) for seed in range(args.seeds)]
    todo = [j for j in jobs if not is_done(j)]
    print(f"{len(jobs)} runs ({over.get('train.episodes', 'the method default')} episodes each, preset "
          f"{args.preset}), {len(jobs) - len(todo)} finished already; {workers} side by side on {args.device}",
          flush=True)
    t0 = time.perf_counter()
    interrupted = False
    try:
        run_jobs(todo, workers=workers)
    except KeyboardInterrupt:
        interrupted = True
    wall = time.perf_counter() - t0
    if todo:  # a call with nothing left to run adds no time
        timing["calls"].append({"wall_s": round(wall, 1), "runs": len(todo), "interrupted": interrupted})
        atomic_write(timing_path, json.dumps(timing, indent=1).encode())
    _summary(jobs, timing)
    return 130 if interrupted else 0


def _summary(jobs, timing) -> None:
    from uevavd.experiments.backends import last_evaluation
    from uevavd.experiments.results import is_done

    per_method: dict[str, list[float]] = {}
    done = 0
    for job in jobs:
        last, finished = last_evaluation(job), is_done(job)
        train_s = float(last.get("wall_s", 0.0))
        if finished:
            per_method.setdefault(job.method, []).append(train_s)
            done += 1
        print(f"  {job.method:>9} seed {job.seed}: {int(last.get('episodes', 0)):>7} episodes, training {train_s:6.0f} s"
              f"{'' if finished else ' (not finished)'}")
    for method, secs in per_method.items():
        print(f"  {method:>9}: {len(secs)} runs finished, training {statistics.median(secs):.0f} s per run (median)")
    total = sum(c["wall_s"] for c in timing["calls"])
    print(f"{done}/{len(jobs)} runs finished; wall time over {len(timing['calls'])} call(s): {total:.0f} s "
          f"({total / 60:.1f} min)")


if __name__ == "__main__":
    sys.exit(main())

"""``uevavd train`` and ``uevavd evaluate``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_train(p: argparse.ArgumentParser):
    p.add_argument("--method", required=True, help="registered method (map, memo_map, ibe_map) or a TOML path")
    p.add_argument("--table", required=True, type=Path, help="observation table folder (from `uevavd prepare`)")
    p.add_argument("--out", required=True, type=Path, help="run directory (resumed when it holds this run)")
    p.add_argument("--episodes", type=int, default=None, help="training episodes (default: the method's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:i]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a method key, e.g. --set train.batch_size=128 --set head.td_target=indep")
    p.add_argument("--max-epochs", type=int, default=None, help="stop after this many epochs (resume later)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from ..config import ConfigError, load_method, parse_override
        from .trainer import RunDirError, train

        try:
            overrides = dict(parse_override(s) for s in args.set)
            spec = load_method(args.method, overrides)
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if (args.out / "done.json").is_file():
            print(f"error: {args.out} holds a finished run (done.json); evaluate it with "
                  f"`uevavd evaluate {args.out}` or train into another --out", file=sys.stderr)
            return 1
        try:
            out = train(spec, args.table, out=args.out, episodes=args.episodes, seed=args.seed,
                        device=args.device, progress=not args.no_progress, max_epochs=args.max_epochs)
        except (RunDirError, ValueError, FileNotFoundError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        status = "finished" if (out / "done.json").is_file() else "paused (rerun the same command to resume)"
        print(f"run {status}: {out}")
        return 0

    return run


def add_evaluate(p: argparse.ArgumentParser):
    p.add_argument("run_dir", type=Path, help="training run directory")
    p.add_argument("--split", default="hard", help="train, simple, hard, test (simple + hard) or all")
    p.add_argument("--table", type=Path, default=None, help="observation table (default: the run's)")
    p.add_argument("--json", type=Path, default=None, help="output JSON (default RUN_DIR/eval_<split>.json)")
    p.add_argument("--device", default="cpu")

    def run(args: argparse.Namespace) -> int:
        from ..env.aod_env import load_table
        from ..env.baselines import PassivePolicy, RandomPolicy
        from ..env.config import EnvConfig
        from ..env.evaluate import evaluate_policy
        from ..env.oracle import OraclePolicy
        from .agent import load_policy

        settings_path = args.run_dir / "settings.json"
        if not settings_path.is_file():
            print(f"error: {args.run_dir} is not a training run (no settings.json)", file=sys.stderr)
            return 1
        settings = json.loads(settings_path.read_text(encoding="utf-8"))
        table_path = args.table or settings.get("table_path")
        if not table_path:
            print("error: the run names no table folder; pass --table", file=sys.stderr)
            return 1
        table = load_table(table_path)
        if table.key != settings["table_key"]:
            print(f"error: table {table_path} has key {table.key} but the run was trained on "
                  f"{settings['table_key']}; pass the run's table with --table", file=sys.stderr)
            return 1
        cfg = EnvConfig().replace(**settings["env"])
        policies = {
            settings["method"]: load_policy(args.run_dir, device=args.device),
            "random": RandomPolicy(0), "passive": PassivePolicy(), "oracle": OraclePolicy(table, cfg),
        }
        results = {name: evaluate_policy(table, args.split, pol, cfg, device=args.device)
                    for name, pol in policies.items()}
        cols = ["mean_return", "accuracy", "recognition_rate", "path_m", "path_steps", "stop_rate"]
        print(f"{args.run_dir} on split {args.split!r} ({len(next(iter(results.values())))} episodes)")
        print(f"{'policy':<12}" + "".join(f"{c:>18}" for c in cols))
        for name, res in results.items():
            s = res.summary()
            print(f"{name:<12}" + "".join(f"{s[c]:>18.4f}" for c in cols))
        path = args.json or args.run_dir / f"eval_{args.split}.json"
        from .trainer import _write_json

        _write_json(path, {name: res.to_dict() for name, res in results.items()})
        print(f"wrote {path}")
        return 0

    return run

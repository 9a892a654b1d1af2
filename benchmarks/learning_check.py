"""Learning check: each method's greedy policy against random, passive and oracle.

    python benchmarks/learning_check.py --table MAP_TABLE [--ibe-table IBE_TABLE] [--episodes 20000]
    python benchmarks/learning_check.py --table T --ibe-table I --preset quick --episodes 40000
    python benchmarks/learning_check.py --toy            # development stand-in, not the real check

MAP and Memo-MAP train on ``--table`` (no decomposition); IBE-MAP on ``--ibe-table``
(its decomposed table; ``--table`` when not given, which then tests the GRU agent only).
Prints the mean return on the training contexts (every context x every start view) of
random, passive, each method and the oracle, and the fraction of the passive -> oracle gap
each method closes: (method - passive) / (oracle - passive). The goal: every method beats
random and passive and closes at least half of the gap.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", type=Path)
    ap.add_argument("--ibe-table", type=Path)
    ap.add_argument("--toy", action="store_true", help="use uevavd.testing.policy.toy_table (dev only)")
    ap.add_argument("--episodes", type=int, default=20_000)
    ap.add_argument("--methods", default="map,memo_map,ibe_map")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temp folder)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--preset", default=None,
                    help="apply this preset's [overrides] first (e.g. quick), then --set; --episodes still wins")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does (and every side measured here); UEVAVD_MALLOC_TUNING=0 turns it off

    from uevavd.config import load_method, parse_override
    from uevavd.env.baselines import PassivePolicy, RandomPolicy
    from uevavd.env.config import EnvConfig
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.env.oracle import OraclePolicy
    from uevavd.policy.acting import load_policy
    from uevavd.policy.trainer import train
    from uevavd.table import load_table

    if args.toy:
        from uevavd.testing.policy import toy_table

        base = ibe = toy_table(n_train=20, n_hard=5, feature_dim=64)
        print("WARNING: toy stand-in table, not a synthetic-world table")
    elif args.table:
        base = load_table(args.table)
        ibe = load_table(args.ibe_table) if args.ibe_table else base
    else:
        ap.error("pass --table (and --ibe-table) or --toy")
    out = args.out or Path(tempfile.mkdtemp(prefix="learning_check_"))
    cfg = EnvConfig()
    rows: dict[str, float] = {}

    def score(table, policy) -> float:
        return evaluate_policy(table, "train", policy, cfg).summary()["mean_return"]

    rows["random"] = score(base, RandomPolicy(0))
    rows["passive"] = score(base, PassivePolicy())
    rows["oracle"] = score(base, OraclePolicy(base, cfg))
    over = {}
    if args.preset:
        from uevavd.presets import load_preset, preset_overrides

        over.update(preset_overrides(load_preset(args.preset)))
        print(f"preset {args.preset} overrides: {over}")
    over.update({"train.threads": args.threads, **dict(parse_override(s) for s in args.set)})
    for method in args.methods.split(","):
        table = ibe if method == "ibe_map" else base
        spec = load_method(method, over)
        t0 = time.perf_counter()
        run = train(spec, table, out=out / method, episodes=args.episodes, seed=args.seed, progress=True)
        wall = time.perf_counter() - t0
        policy = load_policy(run)
        if table.path is None:  # an in-memory table: give the policy its features directly
            policy = type(policy)(policy.net, features=torch.from_numpy(table.features))
        rows[method] = score(table, policy)
        if method == "ibe_map" and table is not base:
            rows["passive (ibe table)"] = score(table, PassivePolicy())
            rows["oracle (ibe table)"] = score(table, OraclePolicy(table, cfg))
        print(f"trained {method} in {wall:.0f} s ({args.episodes / wall:.0f} episodes/s): {run}")

    print(f"\nmean return on the training contexts ({args.episodes} training episodes, seed {args.seed}"
          f"{', preset ' + args.preset if args.preset else ''}"
          f"{', overrides ' + ' '.join(args.set) if args.set else ''})")
    gap = rows["oracle"] - rows["passive"]
    ok = True
    for name, value in rows.items():
        line = f"{name:<22}{value:>9.4f}"
        if name in args.methods.split(","):
            closed = (value - rows["passive"]) / gap if gap > 0 else float("nan")
            good = value > rows["random"] and value > rows["passive"] and closed >= 0.5
            ok &= good
            line += f"   gap closed {closed:6.1%}   {'PASS' if good else 'FAIL'}"
        print(line)
    (out / "learning_check.json").write_text(json.dumps(rows, indent=1))
    print(f"{'all methods pass' if ok else 'some methods fail'}; rows in {out / 'learning_check.json'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

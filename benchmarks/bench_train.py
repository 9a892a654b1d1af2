"""Training speed of MAP / Memo-MAP / IBE-MAP, and SB3's DQN on the same env as the peer.

    python benchmarks/bench_train.py [--table PATH] [--episodes 20000] [--threads 2] [--device cpu]

Without --table a stand-in table with paper-sized features (2048-d, 100 train + 25 hard
contexts; uevavd.testing.policy.toy_table) is used: speed depends on sizes, not content.
Each method trains ``--episodes`` episodes including its per-epoch evaluations (the
method's own settings), and the figures extrapolate to 300,000 episodes. Then SB3's DQN
(MultiInputPolicy) runs on ``DiscreteActions(AODEnv)`` for the same wall time as IBE-MAP;
env steps per second of both and their ratio are printed.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", type=Path, default=None)
    ap.add_argument("--episodes", type=int, default=20_000)
    ap.add_argument("--epoch-episodes", type=int, default=10_000)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared CPU)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--methods", default="map,memo_map,ibe_map")
    ap.add_argument("--sb3-seconds", type=float, default=None, help="default: IBE-MAP's wall time")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--progress", action="store_true", help="show each run's progress bar")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does (and every side measured here); UEVAVD_MALLOC_TUNING=0 turns it off

    from uevavd.config import load_method, parse_override
    from uevavd.policy.checkpoint import load_checkpoint
    from uevavd.policy.trainer import train
    from uevavd.table import load_table

    if args.table:
        table = load_table(args.table)
    else:
        from uevavd.testing.policy import toy_table

        table = toy_table(n_train=100, n_hard=25, feature_dim=2048)
    print(f"table: {table.describe()}")
    print(f"torch threads {torch.get_num_threads()}, device {args.device}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_train_"))
    steps_per_s = {}
    wall = {}
    try:
        for method in args.methods.split(","):
            over = {"train.epoch_episodes": args.epoch_episodes, "train.threads": args.threads,
                    **dict(parse_override(s) for s in args.set)}
            spec = load_method(method, over)
            t0 = time.perf_counter()
            run = train(spec, table, out=tmp / method, episodes=args.episodes, seed=0, device=args.device,
                        progress=args.progress)
            dt = time.perf_counter() - t0
            import json

            done = json.loads((run / "done.json").read_text())
            ck = load_checkpoint(run / "checkpoint.pt")
            eps = done["episodes"] / dt
            steps_per_s[method] = done["env_steps"] / dt
            wall[method] = dt
            print(f"{method:>9}: {done['episodes']} episodes, {done['env_steps']} env steps, "
                  f"{done['updates']} updates in {dt:.1f} s -> {eps:.0f} episodes/s, "
                  f"{steps_per_s[method]:.0f} env steps/s; 300k episodes ~ {300_000 / eps / 60:.1f} min")
            del ck
        sb3_s = args.sb3_seconds or wall.get("ibe_map") or next(iter(wall.values()))
        sb3 = _sb3_steps_per_s(table, sb3_s)
        print(f"SB3 DQN (MultiInputPolicy, DiscreteActions(AODEnv)): {sb3:.0f} env steps/s over {sb3_s:.0f} s")
        for method, sps in steps_per_s.items():
            print(f"ratio {method} / SB3 DQN env steps per second: {sps / sb3:.1f}x")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _sb3_steps_per_s(table, seconds: float) -> float:
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback

    from uevavd.env.aod_env import AODEnv
    from uevavd.env.wrappers import DiscreteActions

    class Stop(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.t0 = time.perf_counter()

        def _on_step(self) -> bool:
            return time.perf_counter() - self.t0 < seconds

    env = DiscreteActions(AODEnv(table, "train"))
    model = DQN("MultiInputPolicy", env, learning_rate=1e-4, gamma=0.9, buffer_size=50_000,
                learning_starts=1000, seed=0, device="cpu", verbose=0)
    from uevavd.env.sb3 import silent_logger

    model.set_logger(silent_logger())
    cb = Stop()
    model.learn(total_timesteps=10**9, callback=cb)
    return model.num_timesteps / (time.perf_counter() - cb.t0)


if __name__ == "__main__":
    main()

"""Cost of one DQN update at the paper's sizes, against the update path before 2026-11-23.

    python benchmarks/bench_update.py [--threads 2] [--methods ibe_map,map] [--repeats 4]

One double-DQN update (online forward and backward, target forward, Adam) over a batch of
64 replayed episodes on a stand-in table with the paper's sizes (2048-d features; g_t 544,
h_t 544, s_t 512, dueling head), episode lengths drawn like a trained policy's (1-5
decisions, mean 2.6). Three paths, interleaved in one process so the machine's load hits
them alike (median of ``--repeats`` rounds of 30 updates each):

* baseline - every observation o_0..o_L encoded, ``nn.GRU`` on packed sequences (the path
  before 2026-11-23);
* packed GRU - the hand-written unroll of ``uevavd.state.packed_gru`` (skips W_hh h_0);
* current - that, and the final observation of a terminated episode not encoded
  (``uevavd.policy.agent.needed_observations``).

All three compute the same loss (tests/policy/test_learner.py, tests/state/test_packed_gru.py).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--methods", default="ibe_map,map")
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--updates", type=int, default=30, help="updates per timed round")
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does (and every side measured here); UEVAVD_MALLOC_TUNING=0 turns it off

    import uevavd.policy.agent as agent
    import uevavd.state.packed_gru as packed
    from uevavd.config import load_method
    from uevavd.env.batched import EnvTensors
    from uevavd.env.config import EnvConfig
    from uevavd.policy.network import build_network
    from uevavd.testing.policy import toy_table

    table = toy_table(n_train=100, n_hard=25, feature_dim=2048)
    cfg = EnvConfig()
    tensors = EnvTensors(table, "train", cfg, features_dtype=torch.float16)
    lookup = agent.TableLookup(tensors)
    current_needed, current_supports = agent.needed_observations, packed.supports_packed
    paths = {
        "baseline (all o_t, nn.GRU)": (agent.observed, lambda gru: False),
        "packed GRU": (agent.observed, current_supports),
        "current (packed GRU, no final o_L)": (current_needed, current_supports),
    }
    print(f"torch threads {torch.get_num_threads()}; batch {args.batch} episodes; median of {args.repeats} "
          f"rounds x {args.updates} updates")
    try:
        for method in args.methods.split(","):
            torch.manual_seed(0)
            net = build_network(load_method(method), table.feature_dim, n_ranges=cfg.max_range)
            learner = agent.Learner(net, lr=1e-4, gamma=cfg.gamma, grad_clip=10.0)
            replay = _replay(tensors, cfg.t_max)
            times: dict[str, list[float]] = {name: [] for name in paths}
            for _ in range(args.repeats):
                for name, (needed, supports) in paths.items():
                    agent.needed_observations, packed.supports_packed = needed, supports
                    for _ in range(3):  # warm-up
                        learner.update(replay.sample(args.batch, 0.4), lookup)
                    t0 = time.perf_counter()
                    for _ in range(args.updates):
                        learner.update(replay.sample(args.batch, 0.4), lookup)
                    times[name].append(1000 * (time.perf_counter() - t0) / args.updates)
            base = statistics.median(times[next(iter(paths))])
            for name, ts in times.items():
                ms = statistics.median(ts)
                print(f"{method:>9}  {name:36s} {ms:7.1f} ms per update   x{base / ms:4.2f}")
    finally:
        agent.needed_observations, packed.supports_packed = current_needed, current_supports


def _replay(tensors, t_max: int, n: int = 5000):
    """n episodes of 1..5 decisions (15/35/30/12/8 %, mean 2.6) on random views."""
    from uevavd.policy.replay import EpisodeReplay

    g = torch.Generator().manual_seed(0)
    length = torch.multinomial(torch.tensor([0.0, 0.15, 0.35, 0.30, 0.12, 0.08]), n, replacement=True, generator=g)
    replay = EpisodeReplay(n, t_max, seed=1)
    replay.add(tensors.scenes[torch.randint(0, len(tensors.scenes), (n,), generator=g)],
               torch.randint(0, 605, (n, t_max + 1), generator=g), torch.randint(0, 6, (n, t_max), generator=g),
               torch.randint(0, 4, (n, t_max), generator=g), torch.randn(n, t_max, generator=g), length)
    return replay


if __name__ == "__main__":
    main()

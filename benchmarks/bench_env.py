"""Speed of the AOD environment layer, against the single gymnasium env as the baseline.

Measures, on a synthetic table of 25 contexts (one split, D = 544 float16 features):

* ``AODEnv`` steps/s (one episode at a time, random actions) - the baseline
* ``BatchedAODEnv`` env-steps/s for N = 1024 and 4096, features kept as float32 or as
  float16 (converted per gather), and the ratio to the baseline
* the time to evaluate all 25 x 605 = 15,125 (context, start) pairs with the passive,
  random and oracle policies (target: < 2 s on CPU), and the oracle's DP alone
* the same for a network policy: IBE-MAP's GRU agent at the paper's sizes (ResNet50's
  2048-d features -> g_t 544 -> GRU h_t 544 -> s_t 512 -> dueling head, untrained weights:
  speed does not depend on them) acting greedily, both with the table's features handed to
  the policy (each view projected once, what ``load_policy`` of a run does) and with the
  (N, 2048) features gathered every step; a fresh policy each repeat, so the projections count

Run: ``python benchmarks/bench_env.py [--device cpu|cuda] [--threads 1] [--steps 200] [--only network]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from uevavd.data.grid import N_VIEWS
from uevavd.env import AODEnv, BatchedAODEnv, EnvConfig, OraclePolicy, PassivePolicy, RandomPolicy
from uevavd.env.evaluate import evaluate_policy
from uevavd.env.oracle import oracle_values
from uevavd.perception.table import ObservationTable


def synthetic_table(n_contexts: int = 25, dim: int = 544, seed: int = 0) -> ObservationTable:
    rng = np.random.default_rng(seed)
    logits = rng.normal(0, 2.0, (n_contexts, N_VIEWS, 5)).astype(np.float32)
    probs = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    lo = rng.uniform(0, 0.5, (n_contexts, N_VIEWS, 2))
    boxes = np.concatenate([lo, lo + rng.uniform(0, 0.5, lo.shape)], -1)
    return ObservationTable.from_arrays(
        rng.normal(size=(n_contexts, N_VIEWS, dim)).astype(np.float16),
        probs,
        boxes,
        scenes=[f"{26 + i:03d}" for i in range(n_contexts)],
        contexts=[26 + i for i in range(n_contexts)],
        targets=[i % 5 for i in range(n_contexts)],
        splits=["hard"] * n_contexts,
    )


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_single(table: ObservationTable, seconds: float = 2.0) -> float:
    env = AODEnv(table, "hard")
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, term, _, _ = env.step(np.array([rng.integers(7), rng.integers(4)]))
        n += 1
        if term:
            env.reset()
    return n / (time.perf_counter() - t0)


def bench_batched(table: ObservationTable, n_envs: int, steps: int, device: str, dtype: torch.dtype) -> float:
    env = BatchedAODEnv(table, "hard", n_envs, device=device, seed=0, features_dtype=dtype)
    env.reset()
    g = torch.Generator(device=device).manual_seed(0)
    actions = [
        (torch.randint(0, 7, (n_envs,), generator=g, device=device),
         torch.randint(0, 4, (n_envs,), generator=g, device=device))
        for _ in range(16)
    ]
    for k in range(5):  # warm-up
        env.step(*actions[k % 16])
    sync(device)
    t0 = time.perf_counter()
    for k in range(steps):
        env.step(*actions[k % 16])
    sync(device)
    return n_envs * steps / (time.perf_counter() - t0)


def timed(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: shared machines)")
    ap.add_argument("--steps", type=int, default=200, help="batched steps per measurement")
    ap.add_argument("--only", choices=("network",), default=None,
                    help="run only the network-policy evaluation case")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.only == "network":
        bench_network_policy(args.device, EnvConfig())
        return
    table = synthetic_table()
    cfg = EnvConfig()
    print(f"table: {len(table)} contexts x {N_VIEWS} views, D={table.feature_dim}; device={args.device}, "
          f"torch threads={args.threads}")

    base = bench_single(table)
    print(f"AODEnv (gymnasium, 1 episode at a time): {base:12,.0f} steps/s   (baseline)")
    for n in (1024, 4096):
        for dtype in (torch.float32, torch.float16):
            sps = bench_batched(table, n, args.steps, args.device, dtype)
            name = str(dtype).replace("torch.", "")
            print(f"BatchedAODEnv N={n:5d} features {name:8s}: {sps:12,.0f} steps/s   x{sps / base:8.1f}")

    print(f"evaluate all {len(table) * N_VIEWS:,} (context, start) pairs, T_max={cfg.t_max} (target < 2 s):")
    dp = timed(lambda: oracle_values(table, cfg))
    print(f"  oracle DP alone            {dp:7.3f} s")
    oracle = OraclePolicy(table, cfg)
    for name, pol in (("passive", PassivePolicy()), ("random", RandomPolicy(0)), ("oracle", oracle)):
        sec = timed(lambda pol=pol: evaluate_policy(table, "hard", pol, cfg, device=args.device))
        res = evaluate_policy(table, "hard", pol, cfg, device=args.device).summary()
        print(f"  {name:8s} policy            {sec:7.3f} s   mean return {res['mean_return']:+.3f}, "
              f"accuracy {res['accuracy']:.3f}, path {res['path_m']:.1f} m")

    class FeatureReader(RandomPolicy):
        needs_features = True  # measures the harness with the (n, D) feature gathers a network needs

    sec = timed(lambda: evaluate_policy(table, "hard", FeatureReader(0), cfg, device=args.device))
    print(f"  random + feature gathers   {sec:7.3f} s   (what a network policy pays before its forward pass)")
    bench_network_policy(args.device, cfg)


def bench_network_policy(device: str, cfg: EnvConfig, feature_dim: int = 2048) -> None:
    """Exhaustive greedy evaluation of an IBE-MAP-sized GRU agent on a 25-context split."""
    from uevavd.config import load_method
    from uevavd.policy.agent import GreedyPolicy
    from uevavd.policy.network import build_network

    table = synthetic_table(dim=feature_dim, seed=1)
    torch.manual_seed(0)
    spec = load_method("ibe_map")
    net = build_network(spec, feature_dim, n_ranges=cfg.max_range)
    params = sum(p.numel() for p in net.parameters())
    features = torch.from_numpy(np.array(table.features))
    print(f"network policy: ibe_map ({spec.component('state')[0]} h={net.estimator.hidden_dim}, "
          f"s_t={net.estimator.state_dim}, head {spec.component('head')[0]}; {params / 1e6:.2f} M parameters, "
          f"untrained), D={feature_dim}, {len(table) * N_VIEWS:,} pairs:")
    cases = (("features handed over", lambda: GreedyPolicy(net, device=device, features=features)),
             ("features gathered per step", lambda: GreedyPolicy(net, device=device)))
    for name, make in cases:
        sec = timed(lambda make=make: evaluate_policy(table, "hard", make(), cfg, device=device))
        res = evaluate_policy(table, "hard", make(), cfg, device=device).summary()
        print(f"  ibe_map greedy, {name:27s} {sec:7.3f} s   mean return {res['mean_return']:+.3f}, "
              f"stop rate {res['stop_rate']:.3f}, steps/episode {res['steps_per_episode']:.2f}")


if __name__ == "__main__":
    main()

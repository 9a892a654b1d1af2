"""Speed of the AOD environment layer, against the single gymnasium env as the baseline.

Measures, on a synthetic table of 25 contexts (one split, D = 544 float16 features):

* ``AODEnv`` steps/s (one episode at a time, random actions) - the baseline
* ``BatchedAODEnv`` env-steps/s for N = 1024 and 4096, features kept as float32 or as
  float16 (converted per gather), and the ratio to the baseline
* the time to evaluate all 25 x 605 = 15,125 (context, start) pairs with the passive,
  random and oracle policies (target: < 2 s on CPU), and the oracle's DP alone
* the same for a network policy: IBE-MAP's GRU agent at the paper's sizes (ResNet50's
  2048-d features -> g_t 544 -> GRU h_t 544 -> s_t 512 -> dueling head) acting greedily,
  untrained (it almost never stops: the worst case, T_max decisions per episode) and with
  its stop advantage raised so that episodes end after about 2 decisions, as trained
  policies do. Each is run by the baseline (each view projected once, then nn.GRU and the
  head on all n episodes every step, the fast path before 2026-11-23), by GreedyPolicy on
  gathered features (live episodes only) and by GreedyPolicy with the table's features
  (input gates cached per view, live episodes only; what ``load_policy`` of a run does),
  with seconds, decisions per episode, GFLOP per evaluation and GFLOP/s achieved

Run: ``python benchmarks/bench_env.py [--device cpu|cuda] [--threads 1] [--steps 200] [--only network]
[--repeat 3]``.
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
from uevavd.table import ObservationTable


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
    ap.add_argument("--repeat", type=int, default=3, help="network-policy timings: best of this many runs")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does (and every side measured here); UEVAVD_MALLOC_TUNING=0 turns it off
    if args.only == "network":
        bench_network_policy(args.device, EnvConfig(), repeat=args.repeat)
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
    bench_network_policy(args.device, cfg, repeat=args.repeat)


class AllRowsPolicy:
    """The baseline: GreedyPolicy's fast path before 2026-11-23. Each (scene, view) is projected
    once (ReLU(W_img f)), then every step runs nn.GRU and the head on all n episodes, ended
    or not."""

    needs_features = False

    def __init__(self, net, features: torch.Tensor) -> None:
        self.net, self.features = net.eval(), features

    def reset(self, n: int) -> None:
        self.hidden = self.net.initial_hidden(n)
        enc = self.net.estimator.encoder
        f = self.features.reshape(-1, self.features.shape[-1])
        self.proj = torch.cat([enc.project(f[i:i + 4096].float()) for i in range(0, len(f), 4096)])

    @torch.no_grad()
    def act(self, obs):
        est = self.net.estimator
        img = self.proj.index_select(0, obs["scene"] * N_VIEWS + obs["view"])
        hidden = self.hidden * (obs["t"] != 0)[:, None].float()
        s, self.hidden = est.step_encoded(est.encoder.combine(img, obs["box"]), hidden)
        return self.net.head.greedy(self.net.head(s), obs["mask"])


def eval_gflop(net, decisions: np.ndarray, path: str) -> float:
    """GFLOP (2 x multiply-adds) of one exhaustive evaluation whose episodes took ``decisions``.

    ``"all rows"`` (the baseline): each (scene, view) projected once, then W_box, W_ih, W_hh,
    W_out and the head on all n rows for every step until the last episode ends.
    ``"live rows"`` (GreedyPolicy, features gathered): the whole network on live rows only.
    ``"cached gates"`` (GreedyPolicy with the table's features): projection and W_ih g + b_ih
    once per (scene, view), then W_out and the head on live rows, W_hh from the second
    decision on (h_0 = 0)."""
    est, n = net.estimator, len(decisions)
    head = sum(m.weight.numel() for m in net.head.modules() if isinstance(m, torch.nn.Linear))
    proj, box = est.encoder.image.weight.numel(), est.encoder.box.weight.numel()
    w_ih, w_hh, w_out = est.gru.weight_ih_l0.numel(), est.gru.weight_hh_l0.numel(), est.out.weight.numel()
    live = np.array([(decisions > k).sum() for k in range(int(decisions.max()))], dtype=np.float64)
    if path == "all rows":
        macs = n * proj + len(live) * n * (box + w_ih + w_hh + w_out + head)
    elif path == "live rows":
        macs = live.sum() * (proj + box + w_ih + w_hh + w_out + head)
    else:
        macs = n * (proj + box + w_ih) + live.sum() * (w_out + head) + live[1:].sum() * w_hh
    return 2 * macs / 1e9


#: added to the untrained network's stop advantage so that episodes end after 2.2 decisions
#: on average (1 to 5: 50 %, 17 %, 11 %, 9 %, 13 %), as trained policies do (1.5 to 2.7)
STOP_BIAS = 0.06


def bench_network_policy(device: str, cfg: EnvConfig, feature_dim: int = 2048, repeat: int = 3) -> None:
    """Exhaustive greedy evaluation of an IBE-MAP-sized GRU agent on a 25-context split: the
    baseline (AllRowsPolicy) against GreedyPolicy, for the untrained network, which almost
    never stops (worst case: T_max decisions per episode), and for the same network with its
    stop advantage raised by STOP_BIAS (about 2 decisions per episode)."""
    from uevavd.config import load_method
    from uevavd.data.grid import STOP
    from uevavd.policy.acting import GreedyPolicy
    from uevavd.policy.network import build_network

    table = synthetic_table(dim=feature_dim, seed=1)
    spec = load_method("ibe_map")
    features = torch.from_numpy(np.array(table.features))
    cases = (("baseline: nn.GRU + head on all rows", "all rows", lambda net: AllRowsPolicy(net, features)),
             ("GreedyPolicy, features gathered", "live rows", lambda net: GreedyPolicy(net, device=device)),
             ("GreedyPolicy, cached input gates", "cached gates",
              lambda net: GreedyPolicy(net, device=device, features=features)))
    for title, bias in (("untrained (worst case)", 0.0), (f"stop advantage +{STOP_BIAS}", STOP_BIAS)):
        torch.manual_seed(0)
        net = build_network(spec.state, spec.head, feature_dim, n_ranges=cfg.max_range).eval()
        with torch.no_grad():
            net.head.adv_type[2].bias[STOP] += bias
        params = sum(p.numel() for p in net.parameters())
        print(f"network policy, {title}: ibe_map ({spec.component('state')[0]} h={net.estimator.hidden_dim}, "
              f"s_t={net.estimator.state_dim}, head {spec.component('head')[0]}; {params / 1e6:.2f} M parameters), "
              f"D={feature_dim}, {len(table) * N_VIEWS:,} pairs, T_max={cfg.t_max}, torch threads="
              f"{torch.get_num_threads()}, best of {repeat}, a fresh policy each repeat (projections count):")
        # repeats interleaved (baseline, then each new path, then again), so that a change in
        # the shared machine's load hits every path alike
        best: dict[str, float] = {}
        results = {}
        for _ in range(repeat):
            for label, _path, make in cases:
                t0 = time.perf_counter()
                results[label] = evaluate_policy(table, "hard", make(net), cfg, device=device)
                best[label] = min(best.get(label, float("inf")), time.perf_counter() - t0)
        a, w = torch.randn(len(table) * N_VIEWS, 544, device=device), torch.randn(1632, 544, device=device)
        gemm = 2 * a.shape[0] * 544 * 1632 / 1e9 / timed(lambda a=a, w=w: (torch.nn.functional.linear(a, w), sync(device)), 5)
        print(f"  bare GEMM ({a.shape[0]:,} x 544) (544 x 1632), the GRU's shape: {gemm:.1f} GFLOP/s now; "
              f"floor = GFLOP / that rate")
        base_label = cases[0][0]
        for label, path, _make in cases:
            res, sec = results[label], best[label]
            same = "" if label == base_label else (
                ", same actions" if (res.trajectories == results[base_label].trajectories).all()
                else ", ACTIONS DIFFER")
            gflop = eval_gflop(net, res.decisions, path)
            print(f"  {label:36s} {sec:7.3f} s  x{best[base_label] / sec:4.1f}   {res.decisions.mean():.2f} "
                  f"decisions/episode, {gflop:4.0f} GFLOP, {gflop / sec:5.1f} GFLOP/s, floor {gflop / gemm:5.2f} s{same}")


if __name__ == "__main__":
    main()

"""Cost of one DQN update at the paper's sizes, against the update path before 2026-11-23.

    python benchmarks/bench_update.py [--threads 2] [--methods ibe_map,map] [--repeats 7]

One double-DQN update (online forward and backward, target forward, Adam) over a batch of
64 replayed episodes on a stand-in table with the paper's sizes (2048-d features; g_t 544,
h_t 544, s_t 512, dueling head), episode lengths drawn like a trained policy's (1-5
decisions, mean 2.6). Three paths, interleaved in one process so the machine's load hits
them alike (median of ``--repeats`` rounds of 30 updates each):

* baseline - every observation o_0..o_L encoded, ``nn.GRU`` on packed sequences (the path
  before 2026-11-23);
* packed GRU - the hand-written unroll of ``uevavd.state.packed_gru`` (skips W_hh h_0);
* current - that, and the final observation of a terminated episode not encoded
  (``uevavd.policy.learner.needed_observations``).

All three compute the same loss (tests/policy/test_learner.py, tests/state/test_packed_gru.py).

Beside each time it prints the floor: the matrix products of the timed updates (their
shapes and layouts recorded by a torch dispatch mode, forward and backward, on a second
pass over the same batches with the sampler rewound) run bare, back to back, on fresh
tensors of the same shapes and strides, right after the updates they come from, so a
change in the machine's speed (this VM's moves by a fifth from minute to minute) hits both
alike. The share of the floor an update reaches is floor / update within a round; the
median over rounds is printed with its range. (Before 2026-11-24 the floor came from one
batch's products, timed after all rounds, and its best round was set against the updates'
median: a batch's size and the machine's noise both moved the share, by up to a tenth.)
Last, the share of the rate of one large square product (2048^3) the update reaches (its
FLOPs at that rate / its time): the update's products are small, so the same-shape floor
is the one it can reach. The rest of an update is element-wise work, gathers, Adam and
Python.
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
    ap.add_argument("--repeats", type=int, default=7, help="rounds (each: the updates, then their floor)")
    ap.add_argument("--updates", type=int, default=30, help="updates per timed round")
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does (and every side measured here); UEVAVD_MALLOC_TUNING=0 turns it off

    import uevavd.policy.learner as learning
    import uevavd.state.gru as packed  # the estimator's module reads supports_packed from here
    from uevavd.config import load_method
    from uevavd.env.batched import EnvTensors
    from uevavd.env.config import EnvConfig
    from uevavd.policy.network import build_network
    from uevavd.testing.policy import toy_table

    table = toy_table(n_train=100, n_hard=25, feature_dim=2048)
    cfg = EnvConfig()
    tensors = EnvTensors(table, "train", cfg, features_dtype=torch.float16)
    lookup = learning.FeatureLookup(tensors)
    current_needed, current_supports = learning.needed_observations, packed.supports_packed
    paths = {
        "baseline (all o_t, nn.GRU)": (learning.observed, lambda gru: False),
        "packed GRU": (learning.observed, current_supports),
        "current (packed GRU, no final o_L)": (current_needed, current_supports),
    }
    peak = _square_gemm_rate()
    print(f"torch threads {torch.get_num_threads()}; batch {args.batch} episodes; median of {args.repeats} "
          f"rounds x {args.updates} updates, each followed by its floor; square 2048 GEMM {peak:.0f} GFLOP/s")
    try:
        for method in args.methods.split(","):
            torch.manual_seed(0)
            spec = load_method(method)
            net = build_network(spec.state, spec.head, table.feature_dim, n_ranges=cfg.max_range)
            learner = learning.Learner(net, lr=1e-4, gamma=cfg.gamma, grad_clip=10.0)
            replay = stand_in_replay(tensors, cfg.t_max)
            times: dict[str, list[float]] = {name: [] for name in paths}
            shares: dict[str, list[float]] = {name: [] for name in paths}
            floor_ms: dict[str, list[float]] = {name: [] for name in paths}
            gflops: dict[str, list[float]] = {name: [] for name in paths}
            for _ in range(args.repeats):
                for name, (needed, supports) in paths.items():
                    learning.needed_observations, packed.supports_packed = needed, supports
                    for _ in range(3):  # warm-up
                        learner.update(replay.sample(args.batch, 0.4), lookup)
                    rng = replay.generator.get_state()
                    t0 = time.perf_counter()
                    for _ in range(args.updates):
                        learner.update(replay.sample(args.batch, 0.4), lookup)
                    ms = 1000 * (time.perf_counter() - t0) / args.updates
                    # the same batches again (the sampler rewound), their products recorded
                    replay.generator.set_state(rng)
                    gemms = [_record_gemms(lambda lr=learner, rp=replay: lr.update(rp.sample(args.batch, 0.4), lookup))
                             for _ in range(args.updates)]
                    bare = _time_calls(_gemm_calls(gemms), 1) / args.updates
                    times[name].append(ms)
                    floor_ms[name].append(bare)
                    shares[name].append(bare / ms)
                    gflops[name].append(sum(_gflop(g) for g in gemms) / args.updates)
            base = statistics.median(times[next(iter(paths))])
            for name, ts in times.items():
                gflop, ms, share = statistics.median(gflops[name]), statistics.median(ts), shares[name]
                print(f"{method:>9}  {name:36s} {ms:7.1f} ms per update   x{base / ms:4.2f}   "
                      f"{gflop:5.2f} GFLOP, floor {statistics.median(floor_ms[name]):5.1f} ms, "
                      f"at {100 * statistics.median(share):3.0f} % of the floor "
                      f"(rounds {100 * min(share):.0f}-{100 * max(share):.0f} %), "
                      f"{100 * 1000 * gflop / peak / ms:3.0f} % of the square-GEMM rate")
    finally:
        learning.needed_observations, packed.supports_packed = current_needed, current_supports


def _record_gemms(fn) -> list[tuple[str, tuple, tuple]]:
    """(op, operand shapes, operand strides) of every matrix product ``fn`` runs."""
    from torch.utils._python_dispatch import TorchDispatchMode

    mm = {torch.ops.aten.mm.default: "mm", torch.ops.aten.addmm.default: "addmm",
          torch.ops.aten.bmm.default: "bmm", torch.ops.aten.baddbmm.default: "baddbmm"}
    seen: list[tuple[str, tuple, tuple]] = []

    class Record(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func in mm:
                ts = [a for a in args if isinstance(a, torch.Tensor)]
                seen.append((mm[func], tuple(tuple(t.shape) for t in ts), tuple(t.stride() for t in ts)))
            return func(*args, **(kwargs or {}))

    with Record():
        fn()
    return seen


def _square_gemm_rate() -> float:
    """GFLOP/s of a bare (2048 x 2048) @ (2048 x 2048) float32 product, best of 5."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    best = min(_timed(lambda: a @ b) for _ in range(5))
    return 2 * 2048**3 / best / 1e9


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _gemm_calls(updates: list[list]) -> list:
    """The products recorded in each update, as calls on fresh tensors of the same shapes and
    strides. The k-th product of every update reads the same weights, so its operands are
    shared between updates where their shapes agree (as the update reuses its parameters);
    different products never share (the online and the target network's weights are apart)."""
    made: dict[tuple, torch.Tensor] = {}

    def operand(key, shape, stride):
        if key not in made:
            size = 1 + sum((n - 1) * s for n, s in zip(shape, stride, strict=True))
            made[key] = torch.randn(size).as_strided(shape, stride)
        return made[key]

    ops = {"mm": torch.mm, "addmm": torch.addmm, "bmm": torch.bmm, "baddbmm": torch.baddbmm}
    return [(ops[op], [operand((k, j, sh, st), sh, st) for j, (sh, st) in enumerate(zip(shapes, strides, strict=True))])
            for gemms in updates for k, (op, shapes, strides) in enumerate(gemms)]


def _gflop(gemms) -> float:
    flop = 0
    for op, shapes, _ in gemms:
        a, b = shapes[-2], shapes[-1]
        flop += 2 * (a[0] if op.startswith("b") else 1) * a[-2] * a[-1] * b[-1]
    return flop / 1e9


def _time_calls(calls, n: int) -> float:
    """ms per pass over ``calls`` (one warm-up pass, then ``n`` timed)."""
    for f, xs in calls:
        f(*xs)
    t0 = time.perf_counter()
    for _ in range(n):
        for f, xs in calls:
            f(*xs)
    return 1000 * (time.perf_counter() - t0) / n


def stand_in_replay(tensors, t_max: int, n: int = 5000, device: str = "cpu"):
    """n episodes of 1..5 decisions (15/35/30/12/8 %, mean 2.6) on random views (also
    benchmarks/bench_crop_augmentation.py's)."""
    from uevavd.policy.replay import EpisodeReplay

    g = torch.Generator().manual_seed(0)
    length = torch.multinomial(torch.tensor([0.0, 0.15, 0.35, 0.30, 0.12, 0.08]), n, replacement=True, generator=g)
    replay = EpisodeReplay(n, t_max, seed=1, device=device)
    replay.add(tensors.scenes[torch.randint(0, len(tensors.scenes), (n,), generator=g)],
               torch.randint(0, 605, (n, t_max + 1), generator=g), torch.randint(0, 6, (n, t_max), generator=g),
               torch.randint(0, 4, (n, t_max), generator=g), torch.randn(n, t_max, generator=g), length)
    return replay


if __name__ == "__main__":
    main()

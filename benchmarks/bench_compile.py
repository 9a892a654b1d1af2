"""Would a compiled graph shorten a cold start's forwards? ``torch.compile`` (inductor) of the
quick preset's encoder and recognizer (EfficientNet-Lite0 at 64 px, as the tables run them:
batch norms folded, channels-last, inference mode) against the same modules run eagerly.

    python benchmarks/bench_compile.py [--threads 2] [--views 1024] [--rounds 5]

Per network: the seconds ``torch.compile`` and its first call take (what a cold start would
pay once per process), then ``--rounds`` passes over the same random views in the pipeline's
batches, eager and compiled taking turns, each pass's ms per view; prints the medians, their
ratio, the views a cold start would need to encode to win back the compile time, and whether
the outputs are the same bit for bit (a faster path that changed a byte would change every
table). Prints the machine-speed reference (``../shared/tools/refwork.py``) before and after.
Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import statistics
import time

from machine_speed import refwork


def _pass(f, x, batch: int):
    import torch

    out = []
    with torch.inference_mode():
        t0 = time.perf_counter()
        for i in range(0, len(x), batch):
            out.append(f(x[i:i + batch]))
        return time.perf_counter() - t0, torch.cat(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2: the machine's cores)")
    ap.add_argument("--views", type=int, default=1024, help="random 64 px views per pass (default 1024)")
    ap.add_argument("--rounds", type=int, default=5, help="eager / compiled passes each, alternating (default 5)")
    args = ap.parse_args()

    import torch

    from uevavd.config import load_method
    from uevavd.perception.prepare import build_components
    from uevavd.presets import ZOO, cli_layers

    torch.set_num_threads(args.threads)
    print(f"{refwork()} (before)")
    preset, overrides = cli_layers("quick", [])
    spec = load_method("map", overrides, preset=preset)
    _, encoder, classifier = build_components(spec.perception, None,
                                              str(ZOO / "pretrained" / "quick" / "recognizer.safetensors"))
    torch.manual_seed(0)
    x = torch.rand(args.views, 3, 64, 64).contiguous(memory_format=torch.channels_last)
    print(f"\n{args.views} views of 64 px, {args.threads} torch threads, {args.rounds} passes each, alternating\n")
    print("| network | batch | eager ms/view | compiled ms/view | ratio | compile + first call | views to pay it back | same bits |")
    print("|---|---|---|---|---|---|---|---|")
    for name, component in (("encoder", encoder), ("recognizer", classifier)):
        runner = component.runner
        module, batch = runner.model, runner.batch_of(x[:1].permute(0, 2, 3, 1).numpy())
        _pass(module, x[:batch], batch)  # warm the eager path too
        t0 = time.perf_counter()
        compiled = torch.compile(module, dynamic=False)
        _pass(compiled, x[:batch], batch)
        compile_s = time.perf_counter() - t0
        eager, fast, same = [], [], True
        for _ in range(args.rounds):
            te, ye = _pass(module, x, batch)
            tc, yc = _pass(compiled, x, batch)
            eager.append(1000 * te / len(x))
            fast.append(1000 * tc / len(x))
            same = same and torch.equal(ye, yc)
        me, mc = statistics.median(eager), statistics.median(fast)
        gain = (me - mc) / 1000
        payback = f"{compile_s / gain:,.0f}" if gain > 0 else "never"
        print(f"| {name} | {batch} | {me:.2f} | {mc:.2f} | {me / mc:.2f}x | {compile_s:.1f} s | {payback} | "
              f"{'yes' if same else 'no'} |", flush=True)
    print(f"\n{refwork()} (after)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

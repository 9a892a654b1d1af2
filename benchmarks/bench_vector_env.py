"""Speed of the Gymnasium vector env (``AODVectorEnv``, what ``gymnasium.make_vec`` returns),
against another checkout's in the same process.

    python benchmarks/bench_vector_env.py --against /tmp/old [--envs 1024] [--steps 200] [--repeat 5]

``--against DIR`` loads the ``uevavd`` package under DIR (e.g. ``mkdir /tmp/old && git archive
60955f2^ uevavd | tar -x -C /tmp/old``) beside this checkout's, and the two step the same
stand-in table (25 contexts, 544-d float features) with the same random actions, taking turns
round by round, so the machine's load hits both alike. Prints env-steps/s of each (best of
``--repeat`` rounds of ``--steps`` steps) and the ratio. Without ``--against``, this checkout only.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
from pathlib import Path

import numpy as np


def _package(root: Path | None):
    """``uevavd.env.vector`` and ``uevavd.testing.policy`` of the checkout under ``root`` (this
    one when None), loaded beside whatever is in ``sys.modules``."""
    ours = {k: sys.modules.pop(k) for k in list(sys.modules) if k == "uevavd" or k.startswith("uevavd.")}
    if root is not None:
        sys.path.insert(0, str(root))
    try:
        import uevavd.env.vector as vector
        import uevavd.testing.policy as testing

        if root is not None and not vector.__file__.startswith(str(root.resolve())):
            raise SystemExit(f"--against {root}: no uevavd package there")
        return vector, testing
    finally:
        if root is not None:
            sys.path.remove(str(root))
        for k in [k for k in sys.modules if k == "uevavd" or k.startswith("uevavd.")]:
            del sys.modules[k]
        sys.modules.update(ours)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", type=Path, default=None, help="another checkout holding a uevavd package")
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    checkouts = {"this": None} if args.against is None else {"this": None, "against": args.against}
    envs = {}
    for name, root in checkouts.items():
        vector, testing = _package(root)
        table = testing.toy_table(n_train=25, n_hard=2, feature_dim=544, seed=0)
        # same-step autoreset in both (the default of checkouts before next-step became it)
        same = {"autoreset_mode": "same_step"} if "autoreset_mode" in inspect.signature(
            vector.AODVectorEnv.__init__).parameters else {}
        envs[name] = vector.AODVectorEnv(table, "train", num_envs=args.envs, **same)
    rng = np.random.default_rng(0)
    actions = [np.stack([rng.integers(0, 7, args.envs), rng.integers(0, 4, args.envs)], 1) for _ in range(args.steps)]
    best = {name: float("inf") for name in envs}
    for _ in range(args.repeat):
        for name, env in envs.items():
            env.reset(seed=0)
            t = time.perf_counter()
            for a in actions:
                env.step(a)
            best[name] = min(best[name], time.perf_counter() - t)
    for name, secs in best.items():
        print(f"{name:<8} {args.envs * args.steps / secs:12,.0f} env-steps/s  ({secs * 1e3 / args.steps:.2f} ms/step, "
              f"{args.envs} envs)")
    if len(best) == 2:
        print(f"ratio this / against: {best['against'] / best['this']:.2f}x the speed")
    return 0


if __name__ == "__main__":
    sys.exit(main())

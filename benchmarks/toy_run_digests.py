"""Digests of small training runs of every shipped method that trains on a plain table: what a
structural change (a move, a rename, a refactor of the training path) must leave unchanged,
bit for bit. Run it before and after the change and compare the output.

    python benchmarks/toy_run_digests.py            # about a minute on 2 CPU cores
    python benchmarks/toy_run_digests.py > before.txt; ...; python benchmarks/toy_run_digests.py | diff before.txt -

Each line: the method, the sha256 of its trained network's tensors, of its per-epoch
evaluation rows (but their wall times) and of its exhaustive hard-split evaluation.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
from pathlib import Path

import torch

from uevavd.config import load_method
from uevavd.env import EnvConfig, evaluate_policy
from uevavd.perception.weights import state_dict_hash
from uevavd.policy.acting import load_policy
from uevavd.policy.rundir import read_evals
from uevavd.policy.trainer import train
from uevavd.testing.policy import small_run, toy_table

#: The shipped methods that train on a plain table (ibe_map_reco needs the recognizer's
#: probabilities in its table's features; ibe_map_sam a SAM table).
METHODS = ("map", "memo_map", "ibe_map", "ibe_map_aug", "ibe_map_aux", "ibe_map_ens", "ibe_map_plr", "ibe_map_pess",
           "ibe_map_gate", "ibe_map_gate_pess", "ibe_map_stop")


def digest(method: str, table, root: Path, episodes: int) -> str:
    spec = load_method(method, overrides={**small_run("map" if method == "map" else "memo_map"),
                                          "train.episodes": episodes})
    run = train(spec, table, out=root / method, device="cpu", progress=False)
    weights = state_dict_hash(load_policy(run).net.state_dict())
    rows = [{k: v for k, v in r.items() if k != "wall_s"} for r in read_evals(run)]  # not the clock
    evals = hashlib.sha256(json.dumps(rows, sort_keys=True).encode()).hexdigest()[:16]
    res = evaluate_policy(table, "hard", load_policy(run), EnvConfig(**spec.env.to_dict())).summary()
    final = hashlib.sha256(json.dumps(res, sort_keys=True).encode()).hexdigest()[:16]
    return f"{method:18s} weights {weights[:16]}  evals {evals}  hard {final}  return {res['mean_return']:.6f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=300, help="episodes per run (default 300)")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), help="methods to train (default: all)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    table = toy_table(n_train=3, n_hard=2, feature_dim=8)
    with tempfile.TemporaryDirectory(prefix="uevavd-digests-") as tmp:
        for method in args.methods:
            print(digest(method, table, Path(tmp), args.episodes), flush=True)


if __name__ == "__main__":
    main()

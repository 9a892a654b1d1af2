"""How much room there is past the pose rule: pose_seek's exact return beside the best policy
that follows it but may depart from it once or twice with the context's exact values (a
privileged ceiling of any rule-anchored method), the visibility oracle and the class-knowing
oracle, per split, on a preset's world with the model zoo's recognizer.

    python benchmarks/rule_ceiling.py [--preset quick] [--world-seed 0]

The world and the table come from the cache (`uevavd synth`, `uevavd prepare`; built here when
absent: a few minutes on 2 cores). The values are exact on the table (dynamic programming,
:mod:`uevavd.env.rule_values`); the baselines are evaluated as every report evaluates them,
from every (context, start view) of the split. `pose_seek`'s number of moves is chosen on the
training split, as the baseline chooses it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="quick", help="preset whose world and perception (default quick)")
    parser.add_argument("--world-seed", type=int, default=None, help="another world of the preset (default its seed)")
    args = parser.parse_args()

    import uevavd
    from uevavd.data.grid import STOP
    from uevavd.env import EnvConfig, evaluate_policy
    from uevavd.env.baselines import PassivePolicy, build_pose_seek, build_visibility_oracle
    from uevavd.env.oracle import oracle_values
    from uevavd.env.rule_values import departure_layers, rule_values
    from uevavd.experiments.plan import make_plan
    from uevavd.experiments.stages import stage_world
    from uevavd.presets import ZOO

    t0 = time.perf_counter()
    plan = make_plan(preset=args.preset, out="/tmp/uevavd-rule-ceiling-plan", methods=["map"],
                     world_seed=args.world_seed)
    data = stage_world(plan, print)
    recognizer = ZOO / "pretrained" / args.preset / "recognizer.safetensors"
    table = uevavd.build_table(data, "map", classifier=recognizer if recognizer.is_file() else None,
                               preset=args.preset)
    cfg = EnvConfig()
    rule = build_pose_seek(table=table, config=cfg)
    print(f"\n{args.preset} world (seed {args.world_seed if args.world_seed is not None else 'of the preset'}), table "
          f"{table.key}; pose_seek with {rule.moves} moves (chosen on train); {time.perf_counter() - t0:.0f} s\n")
    oracle = oracle_values(table, cfg)
    print("| split | passive | pose_seek | 1 departure | 2 departures | visibility oracle | oracle |")
    print("|---|---|---|---|---|---|---|")
    sols = {}
    for split in ("train", "simple", "hard"):
        sol = rule_values(table, split, rule, cfg)
        passive = evaluate_policy(table, split, PassivePolicy(), cfg).ret.mean()
        seek = evaluate_policy(table, split, rule, cfg).ret.mean()
        assert abs(seek - sol.value[:, cfg.t_max].mean()) < 1e-9  # the exact values are the rollouts'
        layers = sols[split] = (sol, departure_layers(sol, 2))
        one, two = (layer.value[:, cfg.t_max].mean() for layer in layers[1])
        vis = evaluate_policy(table, split, build_visibility_oracle(table=table, config=cfg), cfg).ret.mean()
        best = oracle.value[sol.scenes, cfg.t_max].mean()
        print(f"| {split} | {passive:.3f} | {seek:.3f} | {one:.3f} | {two:.3f} | {vis:.3f} | {best:.3f} |")
    print("\nWhere the one-departure ceiling departs at the first decision (share of starts), and where its "
          "first-decision moves land:\n")
    print("| split | departs at once | by stopping | by a move | the move lands on a recognised view | "
          "where the rule then stops |")
    print("|---|---|---|---|---|---|")
    k = cfg.t_max
    for split, (sol, (layer, _)) in sols.items():
        depart, a_type, a_range = layer.depart[:, k], layer.a_type[:, k], layer.a_range[:, k]
        move = depart & (a_type != STOP)
        scene, view = np.nonzero(move)
        lands = sol.next_view[view, a_type[move], a_range[move]]
        print(f"| {split} | {depart.mean():.0%} | {(depart & ~move).mean():.0%} | {move.mean():.0%} | "
              f"{sol.reco[scene, lands].mean():.0%} | {(sol.rule_type[scene, k - 1, lands] == STOP).mean():.0%} |")
    print(f"\n{time.perf_counter() - t0:.0f} s; numpy {np.__version__}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

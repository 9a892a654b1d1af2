"""Wall time to a good policy: uevavd's agents against off-the-shelf Stable-Baselines3 on one table.

    python benchmarks/time_to_quality.py [--seeds 3] [--budget 30] [--threads 2] [--recurrent]
        [--set train.lr=3e-3 ...] [--table PATH]

On the quick preset's MAP table (built, or found, in ``$UEVAVD_CACHE`` as ``uevavd ablate
--preset quick`` builds it; ``--table`` names another), in one process:

(a) uevavd's MAP with the quick preset's settings (``--set`` overrides any of them), trained
    by ``uevavd.policy.trainer.train``; its exploration keeps the preset's schedule in
    episodes (epsilon 1 -> 0.05 over the first 3,000) however long the budget;
(b) SB3's ``DQN("MultiInputPolicy")`` on ``DiscreteActions(AODEnv)`` (the library's Gymnasium
    env, the same table and reward), ``net_arch`` matched to MAP's widths (g_t, s_t, head
    hidden), MAP's learning rate and gamma, everything else SB3's defaults
    (``total_timesteps`` 50,000 sets its exploration schedule).

Both use the same torch thread count. uevavd trains for about ``--budget`` seconds of
training time (evaluation excluded), the peer for 20x the time uevavd needed to reach the
bar (at least ``--budget``, at most ``--peer-cap``), so "never reached within 20x" is seen. Each is evaluated exhaustively on the training contexts (every
context x 605 starts, ``uevavd.env.evaluate.evaluate_policy``, greedy) about every
``--eval-every`` seconds of its training time; the clock is paused while it evaluates.
Quality bar: passive + 0.3 x (class-knowing oracle - passive) on the training contexts.
Printed per seed: each agent's training time until its greedy return first reaches the bar
(resolution: one evaluation interval), the ratio SB3 / uevavd (above 1: uevavd is faster),
each one's best and final return, and the final returns on the simple and hard test
splits. The median ratio over seeds is printed last. ``--recurrent`` adds Memo-MAP against
sb3-contrib's RecurrentPPO (``MultiInputLstmPolicy``, LSTM width = Memo-MAP's h_t), the
recurrent peer that installs from the package index without network at run time.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

import torch

EVAL_SPLITS = ("train", "simple", "hard")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=float, default=30.0, help="training seconds per agent and seed")
    ap.add_argument("--peer-cap", type=float, default=120.0,
                    help="most training seconds for the peer (which gets 20x uevavd's time to the bar)")
    ap.add_argument("--eval-every", type=float, default=0.5, help="training seconds between evaluations")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--table", type=Path, default=None, help="default: the quick preset's MAP table")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="MAP / Memo-MAP override")
    ap.add_argument("--recurrent", action="store_true", help="also Memo-MAP against sb3-contrib's RecurrentPPO")
    ap.add_argument("--only", choices=["uevavd", "sb3"], default=None, help="train one side only")
    ap.add_argument("--curves", type=Path, default=None, help="write every learning curve here (JSON)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from uevavd.runtime import tune_malloc

    tune_malloc()  # as `uevavd train` does

    from uevavd.config import load_method, parse_override
    from uevavd.env.baselines import reference_policies
    from uevavd.env.config import make_config
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.experiments.plan import DEFAULT_SETTING, make_plan, method_layers
    from uevavd.table import load_table

    with tempfile.TemporaryDirectory(prefix="ttq-plan-") as out:  # the plan writes nothing there
        plan = make_plan(preset="quick", out=out, methods=["map", "memo_map"], seeds=1, recognizers=1)
        table = load_table(args.table or _quick_table(plan))
        user = dict(parse_override(s) for s in args.set)
        preset, explicit = method_layers(plan, DEFAULT_SETTING)
        specs = {m: load_method(m, preset=preset, overrides={**explicit, **user}) for m in ("map", "memo_map")}
    env_cfg = make_config(dict(specs["map"].get("env") or {}))
    base = {name: evaluate_policy(table, "train", pol, env_cfg).summary()["mean_return"]
            for name, pol in reference_policies(table, env_cfg).items() if name in ("passive", "oracle")}
    bar = base["passive"] + 0.3 * (base["oracle"] - base["passive"])
    print(f"table {table.path} (D = {table.feature_dim}); training contexts: passive {base['passive']:.3f}, "
          f"class-knowing oracle {base['oracle']:.3f}; bar = passive + 0.3 x gap = {bar:.3f}")
    print(f"torch threads {torch.get_num_threads()}; budget {args.budget:.0f} s training time per agent; "
          f"evaluated every ~{args.eval_every} s of training time")

    all_curves: dict[str, dict[str, list[dict]]] = {}
    pairs = [("MAP", "map", "SB3 DQN", _sb3_dqn)]
    if args.recurrent:
        pairs.append(("Memo-MAP", "memo_map", "SB3 RecurrentPPO", _sb3_recurrent_ppo))
    for ours_name, method, peer_name, peer in pairs:
        ratios = []
        print(f"\n== {ours_name} against {peer_name} ==")
        for seed in range(args.seeds):
            curves = {}
            if args.only != "sb3":
                curves[ours_name] = _uevavd(specs[method], table, seed, args.budget, args.eval_every)
            if args.only != "uevavd":
                # the peer gets 20x the time uevavd needed to the bar (at least --budget, at most --peer-cap)
                ours = _first(curves[ours_name], bar) if curves else math.inf
                peer_budget = args.budget if math.isinf(ours) else max(args.budget, min(20 * ours, args.peer_cap))
                curves[peer_name] = peer(specs[method], table, env_cfg, seed, peer_budget, args.eval_every)
            reach = {}
            for name, c in curves.items():
                all_curves.setdefault(name, {})[str(seed)] = c
                reach[name] = _first(c, bar)
                best = max(r["train"] for r in c)
                fin = c[-1]
                print(f"seed {seed}  {name:17s} bar at {_fmt(reach[name])}  best train {best:.3f}  "
                      f"final ({fin['wall']:.1f} s, {fin['steps']:,} env steps) train {fin['train']:.3f} "
                      f"simple {fin.get('simple', float('nan')):.3f} hard {fin.get('hard', float('nan')):.3f}")
            if len(curves) == 2:
                ratio = _ratio(reach[peer_name], reach[ours_name], args.budget)
                ratios.append(ratio)
                print(f"seed {seed}  time to the bar, {peer_name} / {ours_name}: {_fmt_ratio(ratio)}")
        if ratios:
            print(f"median ratio {peer_name} / {ours_name} over {len(ratios)} seeds: "
                  f"{_fmt_ratio(statistics.median(ratios))}")
    if args.curves:
        from uevavd.atomic import atomic_write

        atomic_write(args.curves, json.dumps({"bar": bar, **base, "curves": all_curves}))
        print(f"curves: {args.curves}")


def _quick_table(plan) -> Path:
    """The quick preset's MAP table, as `uevavd ablate --preset quick` builds it (recognizer 0)."""
    from uevavd.experiments.stages import stage_classifier, stage_tables, stage_world

    def log(msg: str) -> None:
        print(msg, flush=True)

    data = stage_world(plan, log)
    return stage_tables(plan, data, stage_classifier(plan, data, log), log)[0]["map"]


def _uevavd(spec, table, seed: int, budget: float, eval_every: float) -> list[dict]:
    """Train with the library's trainer; its per-epoch evaluations (wall time excluding
    them) give the curve. Epochs are sized so that one lasts about ``eval_every`` seconds."""
    from uevavd.policy.trainer import train

    probe = _episodes_per_s(spec, table)
    episodes = int(probe * budget)
    epoch = max(64, int(probe * eval_every))
    decay = float(spec.get("train.eps_fraction", 0.3)) * int(spec.get("train.episodes", 300_000))  # the preset's decay, in episodes
    over = {"train.episodes": episodes, "train.epoch_episodes": epoch, "train.eval_splits": ["train"],
            "train.eval_contexts": 0, "train.eps_fraction": min(1.0, decay / episodes),
            "train.checkpoint_every": 10**6, "train.threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory(prefix="ttq-") as tmp:
        run = train(spec, table, out=Path(tmp) / "run", seed=seed, device="cpu", progress=False, overrides=over)
        rows = [json.loads(line) for line in (run / "evals.jsonl").read_text().splitlines()]
        done = json.loads((run / "done.json").read_text())
        curve = [{"wall": r["wall_s"], "train": r["mean_return"], "steps": 0} for r in rows]
        from uevavd.policy.acting import load_policy

        policy = load_policy(run)
        final = {s: _eval(table, s, policy, spec) for s in EVAL_SPLITS}
    curve[-1].update(final, steps=int(done["env_steps"]))
    return curve


def _episodes_per_s(spec, table) -> float:
    """MAP's training speed on this machine, from a short run past learning_starts."""
    from uevavd.policy.trainer import train

    start = int(spec.get("train.learning_starts", 2000))
    times = []
    with tempfile.TemporaryDirectory(prefix="ttq-probe-") as tmp:
        for i, n in enumerate((start + 500, start + 2500)):
            over = {"train.episodes": n, "train.epoch_episodes": n, "train.eval_splits": [],
                    "train.threads": torch.get_num_threads()}
            run = train(spec, table, out=Path(tmp) / str(i), seed=0, device="cpu", progress=False, overrides=over)
            times.append(json.loads((run / "done.json").read_text())["wall_s"])
    return 2000 / max(times[1] - times[0], 1e-3)


def _eval(table, split: str, policy, spec) -> float:
    from uevavd.env.config import make_config
    from uevavd.env.evaluate import evaluate_policy

    return evaluate_policy(table, split, policy, make_config(dict(spec.get("env") or {}))).summary()["mean_return"]


def _sb3_loop(model, table, env_cfg, budget: float, eval_every: float, recurrent: bool) -> list[dict]:
    """model.learn with a callback that pauses the clock every ``eval_every`` training
    seconds to evaluate, and stops after ``budget`` training seconds."""
    from stable_baselines3.common.callbacks import BaseCallback

    curve: list[dict] = []
    from uevavd.env.sb3 import SB3Policy, silent_logger

    greedy = SB3Policy(model, env_cfg.max_range, recurrent=recurrent)

    class Clock(BaseCallback):
        def _on_training_start(self) -> None:
            self.t0 = time.perf_counter()
            self.next = eval_every

        def _on_step(self) -> bool:
            wall = time.perf_counter() - self.t0
            if wall >= self.next or wall >= budget:
                pause = time.perf_counter()
                model.policy.set_training_mode(False)
                curve.append({"wall": wall, "steps": self.num_timesteps,
                              "train": _eval(table, "train", greedy, {"env": env_cfg.to_dict()})})
                self.next = wall + eval_every
                self.t0 += time.perf_counter() - pause
            return wall < budget

    model.set_logger(silent_logger())
    model.learn(total_timesteps=10**9 if recurrent else 50_000, callback=Clock())
    if not curve or curve[-1]["steps"] != model.num_timesteps:  # 50,000 steps before the budget
        curve.append({"wall": curve[-1]["wall"] if curve else 0.0, "steps": model.num_timesteps,
                      "train": _eval(table, "train", greedy, {"env": env_cfg.to_dict()})})
    spec = {"env": env_cfg.to_dict()}
    curve[-1].update({s: _eval(table, s, greedy, spec) for s in ("simple", "hard")})
    return curve


def _sb3_dqn(spec, table, env_cfg, seed: int, budget: float, eval_every: float) -> list[dict]:
    from stable_baselines3 import DQN

    from uevavd.env.aod_env import AODEnv
    from uevavd.env.wrappers import DiscreteActions
    from uevavd.experiments.references import sb3_widths

    env = DiscreteActions(AODEnv(table, "train", env_cfg))
    model = DQN("MultiInputPolicy", env, learning_rate=float(spec["train.lr"]), gamma=env_cfg.gamma,
                policy_kwargs={"net_arch": sb3_widths(spec)}, seed=seed, device="cpu", verbose=0)
    return _sb3_loop(model, table, env_cfg, budget, eval_every, recurrent=False)


def _sb3_recurrent_ppo(spec, table, env_cfg, seed: int, budget: float, eval_every: float) -> list[dict]:
    from sb3_contrib import RecurrentPPO

    from uevavd.env.aod_env import AODEnv
    from uevavd.env.wrappers import DiscreteActions
    from uevavd.experiments.references import sb3_widths

    env = DiscreteActions(AODEnv(table, "train", env_cfg))
    g, s, h = sb3_widths(spec)
    model = RecurrentPPO("MultiInputLstmPolicy", env, learning_rate=float(spec["train.lr"]), gamma=env_cfg.gamma,
                         policy_kwargs={"lstm_hidden_size": g, "net_arch": [s, h]}, seed=seed, device="cpu",
                         verbose=0)
    return _sb3_loop(model, table, env_cfg, budget, eval_every, recurrent=True)


def _first(curve: list[dict], bar: float) -> float:
    return next((r["wall"] for r in curve if r["train"] >= bar), math.inf)


def _ratio(peer: float, ours: float, budget: float) -> float:
    if math.isinf(peer) and math.isinf(ours):
        return math.nan
    return peer / ours  # inf: only uevavd reached it; 0: only the peer did


def _fmt(t: float) -> str:
    return "not reached" if math.isinf(t) else f"{t:5.1f} s"


def _fmt_ratio(r: float) -> str:
    if math.isnan(r):
        return "neither reached the bar"
    if math.isinf(r):
        return "only uevavd reached the bar"
    if r == 0:
        return "only the peer reached the bar"
    return f"{r:.2f}x"


if __name__ == "__main__":
    main()

"""``uevavd train`` and ``uevavd evaluate``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from ..atomic import atomic_write_json
from ..cli import error as _error
from ..cli import stopped
from ..config_rules import check_count, did_you_mean, parse_override
from ..presets import PRESET_HELP, cli_layers, known_presets
from ..runtime import usable_cores
from .rundir import RunDir

#: What bad input raises (ConfigError, TableError, RunDirError, CheckpointError are ValueErrors).
BAD_INPUT = (ValueError, FileNotFoundError, NotADirectoryError)


def split_problem(table: Any, split: str, where: str) -> str | None:
    """Why ``split`` cannot be evaluated on ``table`` (an unknown name, or no contexts of it
    in the table), naming the splits the table has; None when it can."""
    from ..data.splits import SPLIT_ALIASES, VALIDATION, resolve_split

    if split == VALIDATION:
        return None  # the run's held-out training contexts: its env config says which (ObservationTable.select)
    present = {s: int(sum(1 for x in table.splits if x == s)) for s in dict.fromkeys(table.splits)}
    have = ", ".join(f"{s} ({n} contexts)" for s, n in present.items()) or "none"
    try:
        resolve_split(split)
    except ValueError:
        return (f"unknown split {split!r}: expected one of {sorted([*SPLIT_ALIASES, VALIDATION])}; "
                f"{where} has the splits {have}")
    if table.scene_indices(split).size == 0:
        return f"{where} has no contexts of split {split!r}; its splits: {have}"
    return None


def _table_problem(path: Path) -> str | None:
    if not path.exists():
        return f"table folder {path} does not exist; build one with `uevavd prepare` or pass its path"
    if not path.is_dir():
        return f"--table {path} is a file, not an observation table folder (from `uevavd prepare`)"
    return None


def _with_preset_hint(args: argparse.Namespace, exc: BaseException) -> BaseException:
    """``exc``; for a table built for another perception config than the method's, with the
    name of a preset whose overrides (with the command's --set) make the method fit it."""
    from ..config import load_method
    from ..table import ObservationTable
    from .trainer import PerceptionMismatch, check_table_perception

    if not isinstance(exc, PerceptionMismatch):
        return exc
    try:
        table = ObservationTable.load(args.table)
        fits = []
        for name in known_presets():
            if name == args.preset:
                continue
            try:
                preset, sets = cli_layers(name, args.set)
                spec = load_method(args.method, sets, preset=preset)
                check_table_perception(spec.perception, table, args.method)
            except (PerceptionMismatch, ValueError):
                continue
            fits.append(name)
    except (OSError, ValueError):
        return exc
    if not fits:
        return exc
    if len(fits) == 1:
        return PerceptionMismatch(f"{exc}; the preset {fits[0]!r} fits this table: pass --preset {fits[0]}")
    # several share the perception (quick and paper64): name them all, so the user picks the
    # one whose training settings they meant
    names = ", ".join(repr(f) for f in fits)
    return PerceptionMismatch(f"{exc}; the presets {names} fit this table: pass --preset with one of them")


def add_train(p: argparse.ArgumentParser):
    from ..config import known_methods

    p.add_argument("--method", required=True,
                   help=f"a registered method (one of {known_methods()}: plugins' included) or a TOML path")
    p.add_argument("--preset", default=None, help=PRESET_HELP)
    p.add_argument("--table", required=True, type=Path, help="observation table folder (from `uevavd prepare`)")
    p.add_argument("--out", required=True, type=Path, help="run directory (resumed when it holds this run)")
    p.add_argument("--episodes", type=int, default=None, help="training episodes (default: the method's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:i]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a method key, e.g. --set train.batch_size=128 --set head.td_target=indep")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads, i.e. --set train.threads=N (default: the method's, 1: the same weights "
                        "on every machine; 0: torch's default, the cores, faster at the paper's sizes)")
    p.add_argument("--max-epochs", type=int, default=None, help="stop after this many epochs (resume later)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from ..config import load_method
        from ..config_rules import ConfigError
        from .rundir import RunDirError

        problem = _table_problem(args.table)  # before the method, whose components import torch (about 3 s)
        if problem:
            return _error("train", problem)
        try:
            sets = [*args.set, *([f"train.threads={args.threads}"] if args.threads is not None else [])]
            preset, overrides = cli_layers(args.preset, sets)
            spec = load_method(args.method, overrides, preset=preset)
            for note in spec.preset_notes:
                print(f"{spec.name}: the preset's {note}", file=sys.stderr)
        except (ConfigError, *BAD_INPUT) as exc:
            return _error("train", exc)
        was_done = RunDir(args.out).finished  # the same run again: nothing to do, not an error
        from .trainer import train  # torch: after the checks, so a mistake is refused at once

        try:
            out = train(spec, args.table, out=args.out, episodes=args.episodes, seed=args.seed,
                        device=args.device, progress=not args.no_progress, max_epochs=args.max_epochs)
        except (RunDirError, *BAD_INPUT) as exc:
            return _error("train", _with_preset_hint(args, exc))
        if was_done:
            print(f"run already finished: {out} (evaluate it with `uevavd evaluate {out}`; another --out trains anew)")
            return 0
        status = "finished" if RunDir(out).finished else "paused (rerun the same command to resume)"
        print(f"run {status}: {out}")
        return 0

    return run


def add_evaluate(p: argparse.ArgumentParser):
    p.add_argument("run_dir", type=Path, nargs="?", default=None, metavar="RUN_DIR_OR_POLICY",
                   help="training run directory, or a policy file (.safetensors: a finished run's "
                        "policy.safetensors, or one written by uevavd.save_network) with --table")
    p.add_argument("--pretrained", default=None, metavar="METHOD",
                   help="evaluate the model zoo's policy of METHOD (map, memo_map, ibe_map) instead of a run: "
                        "generates the quick world's contexts of --split, builds their table with the shipped "
                        "recognizer and prints the result beside the numbers published with the zoo")
    p.add_argument("--split", default="hard",
                   help="train, simple, hard or test (simple + hard); the table must hold contexts of it")
    p.add_argument("--workers", type=int, default=None, help="--pretrained: processes for world generation "
                                                              "(default: the number of cores)")
    p.add_argument("--table", type=Path, default=None,
                   help="observation table (default: the run's; a policy file needs one of its perception config)")
    p.add_argument("--json", type=Path, default=None,
                   help="output JSON (default RUN_DIR/eval_<split>.json, or POLICY.eval_<split>.json)")
    p.add_argument("--device", default="cpu")

    def run(args: argparse.Namespace) -> int:
        if (args.run_dir is None) == (args.pretrained is None):
            return _error("evaluate", "give a training run directory or --pretrained METHOD (one of the two)")
        try:
            return _evaluate_pretrained(args) if args.pretrained else _evaluate(args)
        except BAD_INPUT as exc:
            return _error("evaluate", exc)

    return run


def _evaluate_pretrained(args: argparse.Namespace) -> int:
    import time

    import pandas as pd

    from ..pretrained import evaluate_pretrained
    from ..zoo import PUBLISHED

    problem = refuse_foreign_json(args.json) if args.json else None
    if problem:  # before the evaluation, not after it
        return _error("evaluate", problem)
    t0 = time.perf_counter()
    frame, published, _ = evaluate_pretrained(args.pretrained, args.split, workers=args.workers or usable_cores(),
                                           device=args.device)
    print(f"model zoo {args.pretrained} on split {args.split!r} ({time.perf_counter() - t0:.0f} s)")
    with pd.option_context("display.width", 160, "display.max_columns", 12, "display.precision", 4):
        print(frame[["mean_return", "accuracy", "recognition_rate", "path_m", "path_steps", "stop_rate"]])
    if published is None:
        print(f"no published numbers for split {args.split!r} (the zoo publishes train, simple and hard)")
        return 0
    got = frame.loc[args.pretrained]
    diff = max(abs(float(got[k]) - published[k]) for k in PUBLISHED)
    print("published: " + ", ".join(f"{k} {published[k]:.4f}" for k in PUBLISHED))
    print("reproduced exactly" if diff == 0 else f"differs from the published numbers by up to {diff:.2e}")
    if args.json:
        atomic_write_json(args.json, {"split": args.split, "results": frame.reset_index().to_dict("records"),
                                      "published": published}, sort_keys=True)
        print(f"wrote {args.json}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from .rundir import read_settings

    if args.run_dir.is_file():
        return _evaluate_file(args)
    if not RunDir(args.run_dir).settings.is_file():
        return _error("evaluate", f"{args.run_dir} is not a training run (no settings.json) nor a policy file")
    try:
        settings = read_settings(args.run_dir)
    except ValueError as exc:
        return _error("evaluate", exc)
    table_path = args.table or settings.get("table_path")
    if not table_path:
        return _error("evaluate", "the run names no table folder; pass --table")
    table = _split_table(Path(table_path), args.split)
    if isinstance(table, str):
        return _error("evaluate", table)
    if table.key != settings["table_key"]:
        return _error("evaluate", f"table {table_path} has key {table.key} but the run was trained on "
                                  f"{settings['table_key']}; pass the run's table with --table")
    out = _json_path(args, args.run_dir / f"eval_{args.split}.json")
    if isinstance(out, str):
        return _error("evaluate", out)
    from ..env.config import make_config
    from .acting import load_policy

    policy = load_policy(args.run_dir, device=args.device)
    return _print_beside_baselines(args, table, settings["method"], policy, make_config(settings["env"]), out)


def _evaluate_file(args: argparse.Namespace) -> int:
    """A policy file (``save_network``'s, a run's ``policy.safetensors``) on ``--table``."""
    from .acting import load_policy_file

    if args.table is None:
        return _error("evaluate", f"{args.run_dir} is a policy file, which names no table folder: pass --table (a "
                                  "table of the perception config it was trained for)")
    table = _split_table(args.table, args.split)
    if isinstance(table, str):
        return _error("evaluate", table)
    out = _json_path(args, args.run_dir.with_name(f"{args.run_dir.stem}.eval_{args.split}.json"))
    if isinstance(out, str):
        return _error("evaluate", out)
    policy, cfg = load_policy_file(args.run_dir, table=table, device=args.device)
    return _print_beside_baselines(args, table, args.run_dir.stem, policy, cfg, out)


#: The installed uevavd package: ``evaluate`` never writes its JSON there by default.
PACKAGE_DIR = Path(__file__).parents[1]


def _json_path(args: argparse.Namespace, default: Path) -> Path | str:
    """Where ``evaluate`` writes its JSON: ``--json``, else ``default`` beside the run or policy
    file, except beside a policy shipped inside the installed package (then the current
    folder); a str saying why not where ``--json`` would replace the evaluated run's own files
    or the policy file itself."""
    out = args.json if args.json else default
    # never into the installed package, nor where its model_zoo link points (a git checkout's model_zoo/)
    inside = {PACKAGE_DIR.resolve(), (PACKAGE_DIR / "model_zoo").resolve()}
    if not args.json and inside & ({*default.parents, *default.resolve().parents} | {default.resolve().parent}):
        out = Path.cwd() / default.name
    try:  # a name the file system refuses (too long, say) is an OS fault now, not after the evaluation
        os.stat(Path(out).parent / f".{Path(out).name}.xxxxxxxx.tmp")  # the longest name the write uses
    except FileNotFoundError:
        pass
    target = Path(out).resolve()
    run = args.run_dir if args.run_dir.is_dir() else args.run_dir.parent
    if target == args.run_dir.resolve() or RunDir(run).owns(target):
        return (f"--json {out}: that is the evaluated run's own file, which the evaluation would replace; "
                "choose another path")
    return refuse_foreign_json(Path(out)) or Path(out)


def refuse_foreign_json(path: Path) -> str | None:
    """Why ``evaluate`` must not write ``path`` (None where it may): it writes a new file, or over
    an earlier evaluation JSON of its own (a run's, a policy file's or a pretrained one's); a
    folder, a table's ``meta.json``, another run's ``settings.json`` or any other file is refused
    before anything is evaluated."""
    if not path.exists() and not path.is_symlink():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
    except (OSError, UnicodeDecodeError, ValueError):
        data = None
    ours = isinstance(data, dict) and data and (
        set(data) == {"split", "results", "published"}  # evaluate --pretrained
        or all(isinstance(v, dict) and {"split", "summary"} <= set(v) for v in data.values()))  # a run's, a file's
    if ours:
        return None
    what = "a folder" if path.is_dir() else "a file that is not an evaluation JSON of uevavd evaluate"
    return f"--json {path}: {what} is there, and the evaluation would replace it; choose a new path (nothing was evaluated)"


def _split_table(path: Path, split: str) -> Any:
    """The table at ``path`` when ``split`` can be evaluated on it, else why not (a str)."""
    from ..table import load_table

    problem = _table_problem(path)
    if problem:
        return problem
    table = load_table(path)
    return split_problem(table, split, f"table {path}") or table


def _print_beside_baselines(args: argparse.Namespace, table: Any, name: str, policy: Any, cfg: Any, out: Path) -> int:
    from ..env.baselines import evaluate_with_baselines, summary_row

    results = evaluate_with_baselines(table, args.split, policy, name, cfg, device=args.device)
    rows = {n: summary_row(*r) for n, r in results.items()}
    print(f"{args.run_dir} on split {args.split!r} ({len(results[name][0])} episodes)")
    _print_rows(rows, ["mean_return", "accuracy", "recognition_rate", "path_m", "path_steps", "stop_rate"])
    print("stopping: box_start = starts with the target's box in view; moved_if_box = of those, the policy moves; "
          "box_lost = starts with the box in view, moves, ends unrecognised; reco_lost = starts recognised, ends "
          "not; gated_return = the policy behind the stop gate (stop wherever the box is non-empty)")
    _print_rows(rows, ["box_start", "moved_if_box", "box_lost", "reco_lost", "gated_return"])
    atomic_write_json(out, {n: {**res.to_dict(), "gated_return": rows[n]["gated_return"]}
                            for n, (res, _) in results.items()}, sort_keys=True)
    print(f"wrote {out}")
    return 0


def _print_rows(rows: dict[str, dict[str, float]], cols: list[str]) -> None:
    """One line per policy; '-' where a figure does not apply (a baseline's gated return)."""
    print(f"{'policy':<18}" + "".join(f"{c:>18}" for c in cols))
    for n, row in rows.items():
        print(f"{n:<18}" + "".join(f"{row[c]:>18.4f}" if row[c] == row[c] else f"{'-':>18}" for c in cols))


def add_export_minari(p: argparse.ArgumentParser):
    p.add_argument("table", help="an observation table's folder (`uevavd prepare` writes it)")
    p.add_argument("--split", default="hard", help="train, simple, hard or test (default: hard)")
    p.add_argument("--policy", default="oracle",
                   help="a baseline's name (any that `uevavd evaluate` shows beside a run: random, passive, box_gate, "
                        "pose_seek, the oracles, a plugin's) or a trained run's folder (default: oracle)")
    p.add_argument("--episodes", type=int, default=1000, help="episodes to record (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts (and of the random policy)")
    p.add_argument("--id", required=True, dest="dataset_id", help="Minari dataset id, e.g. uevavd/quick-hard-oracle-v0")
    p.add_argument("--out", default=None, help="datasets folder (default: $MINARI_DATASETS_PATH or ~/.minari/datasets)")
    p.add_argument("--set", action="append", default=[], metavar="env.KEY=VALUE",
                   help="an env setting the episodes are recorded under, e.g. env.thre=0.4 or env.C=0 (default: a "
                        "trained run's own env config, the paper's for a baseline)")

    def run(args) -> int:
        check_count("--episodes", args.episodes)
        check_count("--seed", args.seed, low=0)
        try:
            import minari  # noqa: F401
        except ImportError:
            raise ValueError("export-minari needs minari: pip install \"uevavd[clients]\"") from None
        env = {}
        for text in args.set:
            key, value = parse_override(text)
            if not key.startswith("env."):
                raise ValueError(f"--set {text}: export-minari takes env settings only (env.thre=0.4, env.C=0, ...)"
                                 + did_you_mean(key.split(".", 1)[0], ["env"]))
            env[key[len("env."):]] = value
        from .minari_export import export_minari, policy_env_config  # torch: after the checks

        config = policy_env_config(args.policy, env)
        try:
            ds = export_minari(args.table, args.split, args.policy, args.dataset_id, episodes=args.episodes,
                               seed=args.seed, out=args.out, config=config)
        except KeyboardInterrupt as exc:  # the dataset is put in place whole or not at all
            how, code = stopped(exc)
            print(f"{how}; no dataset was written under that id: a rerun starts the export over", file=sys.stderr)
            return code
        print(f"wrote {ds.spec.dataset_id}: {ds.total_episodes} episodes, {ds.total_steps} steps")
        return 0

    return run

"""``uevavd ablate`` and ``uevavd demo``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..cli import error as _error
from ..config_rules import check_count
from ..plugins.registry import UnknownComponentError
from ..runtime import usable_cores


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, default=None,
                        help="parallel processes for world generation, image decoding and runs "
                             "(default: the number of cores)")
    parser.add_argument("--device", default="cpu", help="training device: cpu, cuda, cuda:1, auto")
    parser.add_argument("--no-zoo", dest="use_zoo", action="store_false",
                        help="train recognizer 0 here even when the model zoo ships the one this preset would "
                             "train (same train_605 images and recipe, sha256-checked; about 100 s saved)")


def _no_figures(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-figures", dest="figures", action="store_false",
                        help="write the report's text and tables only, not its figures (PNG and PDF), which take "
                             "most of its time")


def add_ablate(parser: argparse.ArgumentParser):
    from ..presets import known_presets

    parser.add_argument("--preset", default="quick", help=f"one of {known_presets()} or a TOML path")
    parser.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                        help="methods to compare, by registered name or method-file path (my_ibe.toml; its `name` "
                             "names its rows): default the preset's, map memo_map ibe_map")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per method and setting (default: the preset's)")
    parser.add_argument("--recognizers", type=int, default=None,
                        help="recognizers (seeds of the classifier, each with its own tables) crossed with the "
                             "seeds (default: the preset's)")
    parser.add_argument("--sweep", action="append", default=None, metavar="KEY=V1,V2,...",
                        help="sweep one key from the default: thre, C (the paper's) or any dotted key of a method's "
                             "env/train/state/head/perception section, e.g. --sweep thre=0.2,0.4,0.6,0.8 --sweep "
                             "env.xi2=0.05,0.2 --sweep perception.encoder.name=efficientnet_lite0,resnet18 --sweep "
                             "perception.decompose=true,false. A component's name switches its arguments with it (the "
                             "new builder's defaults); give a component whole to set them: --sweep 'perception.encoder="
                             "{name=\"resnet18\",weights=\"random\"},{name=\"resnet50\",weights=\"file:/w/r50.pth\"}'. "
                             "A perception value builds its own observation table once (cached). --sweep "
                             "env.train_per_block=4,10,20 varies the number of training contexts per target block for "
                             "every method, on a world holding the most asked and every test context")
    parser.add_argument("--cross", action="store_true", default=None,
                        help="cross the --sweep axes (a factorial: every combination of their values, e.g. --sweep "
                             "state.name=single_view,gru --sweep perception.decompose=false,true --cross) instead of "
                             "varying one key at a time from the default")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="set a method key for every method of the ablation, like `uevavd train --set`, e.g. "
                             "--set perception.encoder.weights=random. Precedence, later wins: uevavd's method files, "
                             "the preset's [overrides], your method files (the keys they set), --set, --sweep")
    parser.add_argument("--sweep-methods", nargs="+", default=None, metavar="METHOD",
                        help="methods the sweeps run on (default: the preset's [ablation] sweep_methods among "
                             "--methods, else the last of --methods); env.train_per_block runs on every method")
    parser.add_argument("--episodes", type=int, default=None, help="training episodes per run (default: the preset's)")
    parser.add_argument("--backend", choices=("local", "ray"), default="local",
                        help="local processes, or Ray tasks (a local Ray instance, or RAY_ADDRESS)")
    parser.add_argument("--gpus-per-run", type=float, default=0.0,
                        help="Ray: GPUs each run reserves, fractional to share one (e.g. 0.25 with --device cuda)")
    parser.add_argument("--data", default=None, help="a UEVAVD-layout dataset root (default: the preset's synthetic world)")
    parser.add_argument("--world-seed", type=int, default=None, metavar="N",
                        help="draw the preset's synthetic world from seed N instead of its [world] seed: the same "
                             "comparison on another world of the same kind")
    parser.add_argument("--out", required=True, help="results directory (resumes if it holds this ablation)")
    parser.add_argument("--sb3", default=None, metavar="AGENTS",
                        help="also train Stable-Baselines3 agents (dqn, ppo; comma-separated) on the first method's "
                             "table for as many env steps as its runs, as reference rows")
    _no_figures(parser)
    _common(parser)
    return run_ablate


def run_ablate(args: argparse.Namespace) -> int:
    from ..config_rules import parse_override
    from .axes import parse_sweeps
    from .plan import make_plan  # the arguments are checked before the runner's heavy imports

    try:
        sets = dict(parse_override(s) for s in args.sets)
        plan = make_plan(preset=args.preset, out=args.out, methods=args.methods, seeds=args.seeds,
                         sweeps=parse_sweeps(args.sweep) if args.sweep else None,
                         sweep_methods=args.sweep_methods, data=args.data, workers=args.workers,
                         backend=args.backend, device=args.device, episodes=args.episodes,
                         gpus_per_run=args.gpus_per_run, recognizers=args.recognizers, sb3=args.sb3,
                         use_zoo=args.use_zoo, world_seed=args.world_seed, figures=args.figures, sets=sets,
                         cross=args.cross)
        for m in plan.methods:  # what a method file kept out of the preset, said before any work
            for note in plan.spec(m).preset_notes:
                print(f"{m}: the preset's {note}")
        from .runner import run_ablation

        results = run_ablation(plan)
    except (ValueError, FileNotFoundError, UnknownComponentError) as exc:
        return _error("ablate", exc)
    print_results(results)
    print(f"\nresults: {results}\nreport:  {results.parent / 'report' / 'report.md'}")
    return 0


def print_results(results: Path) -> None:
    import pandas as pd

    df = pd.read_csv(results)
    final = df[df["final"] & (df["setting"] == "default")]
    cols = ["return", "accuracy", "recognition", "path_m", "steps"]
    if "recognizer" not in final:
        final = final.assign(recognizer=0)
    several = final.groupby("method")[["recognizer", "seed"]].apply(lambda g: len(g.drop_duplicates())).max() > 1
    table = final.groupby(["split", "method"], sort=False)[cols].agg(["mean", "std"] if several else "mean")
    table = table.rename(columns={"steps": "decisions"})  # decisions per episode (path_m is the flight)
    with pd.option_context("display.width", 160, "display.max_columns", 20, "display.precision", 3):
        for split in [s for s in ("train", "simple", "hard") if s in set(final["split"])]:
            how = ("one run" if not several else "mean / std over recognizers x seeds"
                   if final["recognizer"].nunique() > 1 else "mean / std over seeds")
            print(f"\n{split} contexts (final evaluation, {how}):")
            print(table.loc[split].to_string(float_format=lambda v: f"{v:.3f}", na_rep="-"))


def add_demo(parser: argparse.ArgumentParser):
    parser.add_argument("--out", default="uevavd-demo", help="results directory (default: ./uevavd-demo)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per method (default: the quick preset's)")
    parser.add_argument("--recognizers", type=int, default=1,
                        help="recognizers crossed with the seeds (default 1, to keep the demo short; the quick "
                             "preset's ablation uses 2, so that intervals include recognizer variance)")
    _common(parser)
    return run_demo


def run_demo(args: argparse.Namespace) -> int:
    """The quick preset end to end on the embedded synthetic world."""
    from .plan import make_plan  # the arguments are checked before the runner's heavy imports

    t0 = time.perf_counter()
    try:
        plan = make_plan(preset="quick", out=args.out, seeds=args.seeds, workers=args.workers,
                         device=args.device, recognizers=args.recognizers, use_zoo=args.use_zoo)
        from .runner import run_ablation

        results = run_ablation(plan)
    except (ValueError, FileNotFoundError, UnknownComponentError) as exc:
        return _error("demo", exc)
    print_results(results)
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in plan.stages.items())
    print(f"\ndemo finished in {time.perf_counter() - t0:.0f} s ({stages}) on {usable_cores()} cores")
    print(f"results: {results}\nreport:  {results.parent / 'report' / 'report.md'}")
    return 0


def add_report(parser: argparse.ArgumentParser):
    """``uevavd report DIR``: (re)write DIR/report/report.md from the ablation's files;
    ``uevavd report DIR1 DIR2 ... --out DIR``: one report for several ablations."""
    parser.add_argument("dir", type=Path, nargs="+", metavar="DIR", help="ablation directory holding results.csv; "
                        "several with --out to merge them")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="merge the ablations DIR1 DIR2 ... (the same world, recognizers and evaluation: "
                             "checked) into DIR and write one report there: one table, one set of paired "
                             "intervals and one figure set for arms run on two days or two machines")
    parser.add_argument("--window", type=int, default=None,
                        help="sliding-window length (evaluation points) for the curves; default min(5, points/3)")
    _no_figures(parser)

    def handler(args: argparse.Namespace) -> int:
        from .io import ABLATION_FILE, ablation_folder, read_ablation_meta

        for folder in args.dir:  # before the report's imports (torch, matplotlib: seconds)
            ablation_folder(folder)
        from .claims import check_claims
        from .merge import merge_ablations
        from .report import write_report
        from .report_data import load_results

        if len(args.dir) > 1 and args.out is None:
            return _error("report", f"{len(args.dir)} folders given: merge them into one report with --out DIR")
        folder = merge_ablations(args.dir, args.out) if args.out is not None else args.dir[0]
        path = write_report(folder, window=args.window, figures=args.figures)
        print(path)
        meta = read_ablation_meta(folder / ABLATION_FILE) if (folder / ABLATION_FILE).is_file() else {}
        for c in check_claims(load_results(folder / "results.csv"), meta.get("lineage")):
            print(f"({c.id}) {c.verdict}: {c.text}")
        return 0

    return handler


def add_zoo(parser: argparse.ArgumentParser):
    sub = parser.add_subparsers(dest="zoo_command", metavar="ACTION", required=True)
    listing = sub.add_parser("list", help="the shipped models, their sizes and published numbers (sha256 checked)")
    check = sub.add_parser("check", help="exit 1 when the shipped models no longer match the world, preset or "
                                         "methods (or, with --render, when this machine renders the world otherwise)")
    check.add_argument("--render", nargs="?", const="all", default=None, metavar="SCENES",
                       help="also render the zoo's world here and compare every scene's files with the zoo's "
                            "records (all 32 scenes: about 30 s on 2 cores), or only SCENES, e.g. 026,056")
    check.add_argument("--recognizer", action="store_true",
                       help="also render the zoo's train_605 and train the shipped recognizer's recipe here on the "
                            "CPU, and compare its weights with the shipped file's (about 75 s on 2 cores)")
    check.add_argument("--workers", type=int, default=None, help="processes rendering (default: the number of cores)")
    for p in (listing, check):
        p.add_argument("--zoo", type=Path, default=None, metavar="DIR",
                       help="a zoo folder, as `zoo build --out` writes (default: the package's)")
    build = sub.add_parser("build", help="retrain the shipped models with the quick preset's pipeline and rewrite "
                                         "model_zoo/pretrained/quick (about 5 minutes on 2 cores)")
    build.add_argument("--out", default=None, help="zoo folder to write (default: the package's)")
    build.add_argument("--workers", type=int, default=None, help="parallel processes (default: the number of cores)")
    return run_zoo


def _check_workers(args: argparse.Namespace) -> int:
    return check_count("--workers", usable_cores() if args.workers is None else args.workers)


def _render_check(zoo, args: argparse.Namespace) -> int:
    """``zoo check --render``: exit 1 when a scene rendered here differs from the zoo's record."""
    scenes = None if args.render == "all" else [s.strip() for s in args.render.split(",") if s.strip()]
    same = zoo.rendered_here(scenes, workers=_check_workers(args), progress=True)
    differ = [n for n, ok in same.items() if not ok]
    if not differ:
        print(f"{len(same)} of {len(same)} scenes render here byte for byte as the zoo's records")
        return 0
    print(f"{len(differ)} of {len(same)} scenes render otherwise here than the zoo's records: {', '.join(differ)}. "
          "This machine's numpy computes some pixels otherwise (docs/synthetic_world.md, \"The same bytes on every "
          "machine\"); numbers trained or evaluated here may differ from the published ones in the last digits")
    return 1


def _recognizer_check(zoo, args: argparse.Namespace) -> int:
    """``zoo check --recognizer``: exit 1 when the recognizer trained here differs from the shipped one."""
    here, shipped = zoo.recognizer_trained_here(workers=_check_workers(args), progress=True)
    if here is None:
        print("train_605 renders otherwise here than the zoo's recognizer was trained on (see `zoo check --render "
              "train_605`): the recognizer was not trained")
        return 1
    if here == shipped:
        print(f"the recognizer trained here has the shipped recognizer's weights, bit for bit ({here})")
        return 0
    print(f"the recognizer trained here ({here}) differs from the shipped one ({shipped}): this machine's torch "
          "computes training otherwise (its CPU: `uevavd info`); numbers after `--no-zoo` may differ from the "
          "published ones")
    return 1


def run_zoo(args: argparse.Namespace) -> int:
    from ..zoo import PUBLISHED, Zoo, ZooError
    from .zoo_build import build_zoo

    try:
        if args.zoo_command == "build":
            build_zoo(args.out, workers=args.workers)
            return 0
        zoo = Zoo.load(root=args.zoo)
        problems = zoo.problems()
        if args.zoo_command == "check":
            print("\n".join(f"stale: {p}" for p in problems) or f"{zoo.root}: the shipped models match the world, "
                                                                  "the preset and the methods")
            if problems:
                return 1
            rc = _render_check(zoo, args) if args.render is not None else 0
            return max(rc, _recognizer_check(zoo, args)) if args.recognizer else rc
        for name, rec in sorted(zoo.manifest["files"].items()):
            zoo.verified(name)
            print(f"{name:<26} {rec['bytes'] / 1e6:5.1f} MB  sha256 {rec['sha256'][:16]}... ok")
        print(f"\npublished numbers (exhaustive evaluation; {', '.join(PUBLISHED)}):")
        for m in zoo.methods:
            published = zoo.manifest["policies"][m]["published"]
            for split, row in sorted(published.items(), key=lambda kv: ("train", "simple", "hard").index(kv[0])):
                print(f"  {m:<9} {split:<7} " + "  ".join(f"{row[k]:8.4f}" for k in PUBLISHED))
        for p in problems:
            print(f"stale: {p} (rebuild with `uevavd zoo build`)")
        return 0
    except (ZooError, ValueError, FileNotFoundError) as exc:
        return _error("zoo", exc)

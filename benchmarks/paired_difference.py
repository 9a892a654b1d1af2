"""The paired difference of two methods of one or more ablations, per split and terrain.

    python benchmarks/paired_difference.py DIR [DIR ...] --a METHOD_A --b METHOD_B [--split hard] [--by-recognizer]
        [--by-world]

Reads each DIR/contexts.csv (the final evaluation of every run on every context) and prints,
for each split asked for and each terrain in it, the mean return of A, of B and A - B, paired
by recognizer and seed: each run's mean over the split's (or terrain's) contexts, minus B's run
of the same recognizer and seed, or, where B is a baseline (one run per recognizer), B's run
of that recognizer; then the report's two-stage bootstrap over recognizers, then runs
(:func:`uevavd.experiments.stats.nested_bootstrap`), with its 95 % interval. Several folders
(ablations of one world with different recognizers) pool their recognizers, each folder's
counted apart. Default setting rows only. ``--by-recognizer`` adds each recognizer's own
difference (a bootstrap over its seeds): a pooled gain that only some recognizers give shows there.
``--by-world`` groups the folders by the world each ran on (its preset and world seed, from
DIR/ablation.json), prints each world's difference, and the mean over worlds with a Student-t
interval over them: the world is then the unit, as it is for a claim about unfamiliar terrain in
general (a gain that some worlds give and others do not has a wide interval there, however
many seeds each world ran).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections import defaultdict
from pathlib import Path

from uevavd.experiments.stats import Estimate, nested_bootstrap


def run_means(rows: list[dict], method: str, split: str, terrain: str | None) -> dict[tuple[str, str], float]:
    """{(folder:recognizer, seed): mean return over the contexts of ``split`` (and ``terrain``)}."""
    acc: dict[tuple[str, str], list[float]] = defaultdict(list)
    for r in rows:
        if r["method"] == method and r["split"] == split and r["setting"] == "default" and \
                (terrain is None or r["terrain"] == terrain):
            acc[(r["recognizer"], r["seed"])].append(float(r["return"]))
    return {k: sum(v) / len(v) for k, v in acc.items()}


def pair(a: dict, b: dict) -> dict[tuple[str, str], float] | None:
    """A - B per run of A: B's run of the same (recognizer, seed), or B's one run of that
    recognizer; None when B has neither for some run of A."""
    per_recognizer = defaultdict(list)
    for (rec, _), v in b.items():
        per_recognizer[rec].append(v)
    out = {}
    for (rec, seed), v in a.items():
        if (rec, seed) in b:
            out[(rec, seed)] = v - b[(rec, seed)]
        elif len(per_recognizer.get(rec, ())) == 1:
            out[(rec, seed)] = v - per_recognizer[rec][0]
        else:
            return None
    return out


def world_of(folder: Path) -> tuple[str, int] | None:
    """(preset name, world seed) of the ablation in ``folder`` (its ablation.json), None when unreadable."""
    try:
        preset = json.loads((folder / "ablation.json").read_text(encoding="utf-8"))["fingerprint"]["preset"]
        return str(preset["name"]), int(preset["world"]["seed"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def by_world(split: str, d: dict[tuple[str, str], float], world: dict[str, tuple[str, int]]) -> list[str]:
    """Rows of each world's A - B (the two-stage bootstrap over its recognizers and seeds) and
    of their mean over worlds (a Student-t interval over the worlds' differences)."""
    lines, means = [], []
    for w in sorted(set(world.values())):
        keys = sorted(k for k in d if world[k[0]] == w)
        if not keys:
            continue
        est = nested_bootstrap([d[k] for k in keys], [k[0] for k in keys])
        means.append(est.mean)
        lines.append(f"| {split} | {w[0]} world {w[1]} | {len({k[0] for k in keys})} | {len(keys)} | "
                     f"{est.mean:+.3f} [{est.lo:+.3f}, {est.hi:+.3f}] |")
    over = Estimate.of(means)
    interval = f"[{over.lo:+.3f}, {over.hi:+.3f}]" if over.defined else "(one world: no interval)"
    lines.append(f"| {split} | mean over {len(means)} worlds | | | {over.mean:+.3f} {interval} |")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", type=Path, nargs="+", help="ablation output folders (each holding contexts.csv)")
    ap.add_argument("--a", required=True, help="method A (the difference's first term)")
    ap.add_argument("--b", required=True, help="method or baseline B (subtracted)")
    ap.add_argument("--split", action="append", help="split(s) to report (default: every split of the files)")
    ap.add_argument("--by-recognizer", action="store_true",
                    help="also print each recognizer's own difference, all terrains together")
    ap.add_argument("--by-world", action="store_true",
                    help="also print each world's difference and their mean over worlds (t interval over worlds)")
    args = ap.parse_args()
    rows, world = [], {}  # world: {folder:recognizer: (preset, world seed)} for --by-world
    for folder in args.folders:
        path = folder / "contexts.csv"
        if not path.is_file():
            print(f"paired_difference: {path} not found: expected an ablation's output folder "
                  "(uevavd ablate --out DIR)", file=sys.stderr)
            return 2
        with path.open(encoding="utf-8") as f:
            own_rows = [{**r, "recognizer": f"{folder}:{r['recognizer']}"} for r in csv.DictReader(f)]
        rows += own_rows
        if args.by_world:
            w = world_of(folder)
            if w is None:
                print(f"paired_difference: {folder / 'ablation.json'} has no readable preset and world seed: "
                      "--by-world needs each folder's ablation.json as `uevavd ablate` wrote it", file=sys.stderr)
                return 2
            world.update({r["recognizer"]: w for r in own_rows})
    for m in (args.a, args.b):
        if not any(r["method"] == m for r in rows):
            print(f"paired_difference: no method {m!r} in {[str(f) for f in args.folders]}: expected one of "
                  f"{sorted({r['method'] for r in rows})}", file=sys.stderr)
            return 2
    splits = args.split or sorted({r["split"] for r in rows})
    lines = ["| split | terrain | recognizers | runs | A | B | A - B [95 %] |", "|---|---|---|---|---|---|---|"]
    own: list[tuple[str, dict, dict]] = []  # (split, A's run means, A - B per run) for --by-recognizer
    worlds: list[str] = []  # rows for --by-world
    for split in splits:
        terrains = sorted({r["terrain"] for r in rows if r["split"] == split})
        for terrain in (None, *terrains) if len(terrains) > 1 else (None,):
            a, b = run_means(rows, args.a, split, terrain), run_means(rows, args.b, split, terrain)
            d = pair(a, b)
            if d is None:
                print(f"paired_difference: {args.b} has neither a run of each seed of {args.a} nor one run per "
                      f"recognizer on {split}: expected a method of the same seeds or a baseline", file=sys.stderr)
                return 2
            if not d:
                continue
            keys = sorted(d)
            groups = [k[0] for k in keys]
            ea = nested_bootstrap([a[k] for k in keys], groups)
            est = nested_bootstrap([d[k] for k in keys], groups)
            lines.append(f"| {split} | {terrain or 'all'} | {len(set(groups))} | {len(keys)} | {ea.mean:.3f} | "
                         f"{ea.mean - est.mean:.3f} | {est.mean:+.3f} [{est.lo:+.3f}, {est.hi:+.3f}] |")
            if args.by_recognizer and terrain is None:
                own.append((split, a, d))
            if args.by_world and terrain is None:
                worlds += by_world(split, d, world)
    if args.by_recognizer:
        lines += ["", "| split | recognizer | runs | A | B | A - B [95 %] |", "|---|---|---|---|---|---|"]
        for split, a, d in own:
            for rec in sorted({k[0] for k in d}):
                keys = sorted(k for k in d if k[0] == rec)
                ea, est = (nested_bootstrap([x[k] for k in keys], [rec] * len(keys)) for x in (a, d))
                lines.append(f"| {split} | {rec} | {len(keys)} | {ea.mean:.3f} | {ea.mean - est.mean:.3f} | "
                             f"{est.mean:+.3f} [{est.lo:+.3f}, {est.hi:+.3f}] |")
    if args.by_world:
        lines += ["", "| split | world | recognizers | runs | A - B [95 %] |", "|---|---|---|---|---|", *worlds]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

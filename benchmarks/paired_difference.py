"""The paired difference of two learned methods of one ablation, per split and terrain.

    python benchmarks/paired_difference.py DIR METHOD_A METHOD_B [--split hard]

Reads DIR/contexts.csv (the final evaluation of every run on every context) and prints, for
each split asked for and each terrain in it, mean return of A, of B and A - B, paired by
(recognizer, seed): each run's mean over the split's (or terrain's) contexts, A's minus B's of
the same recognizer and seed, then the report's two-stage bootstrap over recognizers, then
seeds (:func:`uevavd.experiments.stats.nested_bootstrap`), with its 95 % interval. The report
pairs each method with the baselines; this pairs two methods with each other. Default
setting rows only.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

from uevavd.experiments.stats import nested_bootstrap


def run_means(rows: list[dict], method: str, split: str, terrain: str | None) -> dict[tuple[str, str], float]:
    """{(recognizer, seed): mean return over the contexts of ``split`` (and ``terrain``)}."""
    acc: dict[tuple[str, str], list[float]] = defaultdict(list)
    for r in rows:
        if r["method"] == method and r["split"] == split and r["setting"] == "default" and \
                (terrain is None or r["terrain"] == terrain):
            acc[(r["recognizer"], r["seed"])].append(float(r["return"]))
    return {k: sum(v) / len(v) for k, v in acc.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="an ablation's output folder (holding contexts.csv)")
    ap.add_argument("a", help="method A (the row's first term)")
    ap.add_argument("b", help="method B (subtracted)")
    ap.add_argument("--split", action="append", help="split(s) to report (default: every split of the file)")
    args = ap.parse_args()
    path = args.folder / "contexts.csv"
    if not path.is_file():
        print(f"paired_difference: {path} not found: expected an ablation's output folder "
              "(uevavd ablate --out DIR)", file=sys.stderr)
        return 2
    with path.open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    for m in (args.a, args.b):
        if not any(r["method"] == m for r in rows):
            have = sorted({r["method"] for r in rows})
            print(f"paired_difference: no method {m!r} in {path}: expected one of {have}", file=sys.stderr)
            return 2
    splits = args.split or sorted({r["split"] for r in rows})
    lines = ["| split | terrain | runs | A | B | A - B [95 %] |", "|---|---|---|---|---|---|"]
    for split in splits:
        terrains = sorted({r["terrain"] for r in rows if r["split"] == split})
        for terrain in (None, *terrains) if len(terrains) > 1 else (None,):
            a, b = run_means(rows, args.a, split, terrain), run_means(rows, args.b, split, terrain)
            if a.keys() != b.keys():
                print(f"paired_difference: {args.a} has runs {sorted(a)} and {args.b} {sorted(b)} on {split}: expected "
                      "two learned methods of the same recognizers and seeds (the report pairs each method with the "
                      "baselines)", file=sys.stderr)
                return 2
            keys = sorted(a)
            if not keys:
                continue
            ea = nested_bootstrap([a[k] for k in keys], [k[0] for k in keys])
            eb = nested_bootstrap([b[k] for k in keys], [k[0] for k in keys])
            d = nested_bootstrap([a[k] - b[k] for k in keys], [k[0] for k in keys])
            lines.append(f"| {split} | {terrain or 'all'} | {len(keys)} | {ea.mean:.3f} | {eb.mean:.3f} | "
                         f"{d.mean:+.3f} [{d.lo:+.3f}, {d.hi:+.3f}] |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

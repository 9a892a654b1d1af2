"""``uevavd synth``: generate the synthetic world in the UEVAVD layout."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ...cli import error
from ...config_rules import check_count
from ..splits import N_CONTEXTS, check_context


def parse_contexts(text: str) -> list[int]:
    """Context ids from a list with ranges, e.g. ``"1-4,21,26"`` -> [1, 2, 3, 4, 21, 26]."""
    out: set[int] = set()
    for item in str(text).replace(" ", "").split(","):
        if not item:
            continue
        try:
            if "-" in item:
                lo, hi = (int(p) for p in item.split("-", 1))
                if lo > hi:
                    raise ValueError
                out.update(range(lo, hi + 1))
            else:
                out.add(int(item))
        except ValueError:
            raise ValueError(
                f"--contexts: cannot read {item!r} in {text!r}: expected ids or ranges like 1-4,21,26"
            ) from None
    if not out:
        raise ValueError(f"--contexts {text!r} names no context: expected ids 1..{N_CONTEXTS}")
    return sorted(check_context(c) for c in out)


def add_synth(parser: argparse.ArgumentParser):
    parser.add_argument("--out", type=Path, required=True, help="output folder (resumed if it exists)")
    from ...presets import known_presets

    parser.add_argument("--preset", default="quick",
                        help=f"preset naming seed, size and contexts: one of {known_presets()} or a TOML path")
    parser.add_argument("--contexts", help="context ids, e.g. 1-4,21,26 (default: the preset's)")
    parser.add_argument("--size", type=int, help="crop size in pixels (default: the preset's)")
    parser.add_argument("--seed", type=int, help="world seed (default: the preset's)")
    parser.add_argument("--workers", type=int, default=1, help="processes rendering scenes in parallel")
    parser.add_argument("--no-unoccluded", action="store_true", help="skip the scenes 00 and train_605")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return _run


def _run(args: argparse.Namespace) -> int:
    from ...presets import load_preset
    from ..splits import subset
    from .writer import write_world

    try:
        world = load_preset(args.preset).get("world", {})
        # --contexts '' names no context (it used to mean the preset's 30): only an absent option does
        contexts = parse_contexts(args.contexts) if args.contexts is not None else list(subset(world["per_block"]))
        size = int(args.size or world["size"])
        seed = int(world.get("seed", 0) if args.seed is None else args.seed)
        if seed < 0:  # refused before the folder is made (numpy's seeding refused it after)
            raise ValueError(f"--seed {seed}: expected a world seed >= 0")
        check_count("--workers", args.workers)
        # never more processes than scenes to render (1000 workers forked 1000 processes for 2 scenes)
        workers = min(args.workers, len(contexts) + (0 if args.no_unoccluded else 2))
        t0 = time.perf_counter()
        out = write_world(
            args.out, contexts=contexts, size=size, seed=seed, workers=workers,
            include_unoccluded=not args.no_unoccluded, progress=not args.quiet,
        )
    except (ValueError, FileNotFoundError) as err:
        return error("synth", err)
    print(f"wrote {len(contexts)} contexts at {size} px (seed {seed}) to {out} in {time.perf_counter() - t0:.1f} s")
    from .quality import format_rows, read_visible, split_rows
    from .world import VALIDITY

    print(f"\nvisibility per split (validity rule: {VALIDITY.describe()}):")
    print(format_rows(split_rows(read_visible(out))))
    return 0

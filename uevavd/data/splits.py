"""Contexts and splits of UEVAVD (paper Table I with its typos corrected, as below).

150 contexts, ids 1..150, in five blocks of 30, one block per target. Within block k
(``base = 30 * k``): train = base+1..base+20, simple test = base+21..base+25, hard test
= base+26..base+30. The paper's table prints "120, ..., 140" and "56, ..., 80"; the
counts it gives (100 / 25 / 25 contexts, 60500 / 15125 / 15125 images) prove the
intended ranges are 121..140 and 56..60.

Which target owns which block is read from the data (file names), never assumed here.
Scene ``"00"`` holds unoccluded views; ``"train_605"`` holds unoccluded crops of the five
targets from all 605 viewpoints and is used only to train the classifier.
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import accumulate

from .grid import N_VIEWS

N_CONTEXTS = 150
BLOCK = 30
N_BLOCKS = N_CONTEXTS // BLOCK
#: Contexts of each split within a block (Table 1: 20 / 5 / 5), in block order.
PER_BLOCK: dict[str, int] = {"train": 20, "simple": 5, "hard": 5}
TRAIN_PER_BLOCK = PER_BLOCK["train"]
#: The three context splits, in report order.
SPLITS: tuple[str, ...] = ("train", "simple", "hard")
#: Names accepted for a split, mapped to the canonical one(s). "test" means both tests.
SPLIT_ALIASES: dict[str, tuple[str, ...]] = {
    "train": ("train",),
    "simple": ("simple",),
    "simple_test": ("simple",),
    "hard": ("hard",),
    "hard_test": ("hard",),
    "test": ("simple", "hard"),
}
#: The training contexts a run leaves out of its training (those past ``env.train_per_block`` in
#: each block): not a split of the data but of a run, to choose recipes on training data only
#: (never on a test split). Evaluated like a split (``train.eval_splits``, ``uevavd evaluate
#: --split validation``) wherever the run's ``env.train_per_block`` is set.
VALIDATION = "validation"
#: The scene of unoccluded views, and the classifier's training crops.
UNOCCLUDED_SCENE = "00"
CLASSIFIER_SCENE = "train_605"
#: The five target classes in canonical (alphabetical) order; class index = position.
TARGETS: tuple[str, ...] = ("hatchback", "pickup", "sedan", "sportscar", "suv")


def check_context(context_id: int) -> int:
    """Return ``context_id`` as int, or raise ``ValueError`` unless it is in 1..150."""
    try:
        cid = int(context_id)
    except (TypeError, ValueError):
        raise ValueError(f"context id {context_id!r} is not an integer in 1..{N_CONTEXTS}") from None
    if not 1 <= cid <= N_CONTEXTS or cid != context_id:
        raise ValueError(f"context id {context_id!r} is out of range: expected 1..{N_CONTEXTS}")
    return cid


def split_of(context_id: int) -> str:
    """The split ("train", "simple" or "hard") that owns a context id."""
    offset = (check_context(context_id) - 1) % BLOCK  # 0..29
    for split, n in PER_BLOCK.items():
        if offset < n:
            return split
        offset -= n
    raise AssertionError("PER_BLOCK covers a block")


def block_of(context_id: int) -> int:
    """Block 0..4 of a context (one block per target; which target is read from data)."""
    return (check_context(context_id) - 1) // BLOCK


def resolve_split(name: str) -> tuple[str, ...]:
    """Canonical split names for a split name or alias; an unknown name lists the known."""
    key = str(name).strip().lower()
    if key not in SPLIT_ALIASES:
        raise ValueError(f"unknown split {name!r}: expected one of {sorted(SPLIT_ALIASES)}")
    return SPLIT_ALIASES[key]


def contexts(split: str) -> tuple[int, ...]:
    """Sorted context ids of a split or alias (e.g. ``contexts("hard")``)."""
    wanted = set(resolve_split(split))
    return tuple(c for c in range(1, N_CONTEXTS + 1) if split_of(c) in wanted)


def counts() -> dict[str, dict[str, int]]:
    """Contexts and views per split: train 100 / 60500, simple 25 / 15125, hard 25 / 15125."""
    return {s: {"contexts": len(contexts(s)), "views": len(contexts(s)) * N_VIEWS} for s in SPLITS}


def scene_name(context_id: int) -> str:
    """Canonical folder name of a context ("001".."150")."""
    return f"{check_context(context_id):03d}"


def first_per_block(contexts: Iterable[int], n: int) -> list[int]:
    """The first ``n`` of ``contexts`` (by id) in each block that holds any; a block holding
    fewer than ``n`` is a ValueError naming it and what it holds."""
    by_block: dict[int, list[int]] = {}
    for c in sorted({int(c) for c in contexts}):
        by_block.setdefault(block_of(c), []).append(c)
    short = {b: cs for b, cs in by_block.items() if len(cs) < n}
    if short:
        b, cs = min(short.items())
        raise ValueError(f"{n} contexts per block asked, but block {b} (contexts {b * BLOCK + 1}-{(b + 1) * BLOCK}) "
                         f"holds only {len(cs)} here: {cs}")
    return sorted(c for cs in by_block.values() for c in cs[:n])


def subset(per_block: dict[str, int]) -> tuple[int, ...]:
    """A smaller world that keeps the block structure: the first ``n`` contexts of each
    split within every block, e.g. ``subset({"train": 4, "simple": 1, "hard": 1})``.
    """
    limits = PER_BLOCK
    unknown = set(per_block) - set(limits)
    if unknown:
        raise ValueError(f"unknown split(s) {sorted(unknown)}: expected keys among {list(limits)}")
    out = []
    for k in range(N_BLOCKS):
        base = BLOCK * k
        starts = dict(zip(limits, accumulate(limits.values(), initial=base + 1), strict=False))
        for split, n in per_block.items():
            if not 0 <= n <= limits[split]:
                raise ValueError(f"{split}={n} per block: expected 0..{limits[split]}")
            out.extend(range(starts[split], starts[split] + n))
    return tuple(sorted(out))

"""Quality of the synthetic world: visible-fraction statistics per split,
from a written world or rendered in memory, and the contact sheets of
``docs/synthetic_world.md``.

    python benchmarks/synthetic_quality.py --world DIR [--figures docs/img]
    python benchmarks/synthetic_quality.py --contexts all --size 48 --workers 2
    python benchmarks/synthetic_quality.py --contexts 1,2,21,26 --size 48 --compare-sizes 64,128

``--world`` reads each scene's ``scene.json`` (visible fraction per view); ``--contexts``
("all" = 1..150, or ids and ranges like 1-20,26) renders those contexts in memory instead
(``render_context``, world seed ``--seed``, ``--size`` px; the visible fraction hardly
depends on the size, so a small one keeps this fast). Prints per split: mean visible
fraction, the share of views with visible >= 0.9, < 0.5 and == 0 (per terrain too); then
PASS or FAIL for each stated property: every context of every split passes the validity rule
(``uevavd.data.synthetic.world.VALIDITY``); hard-test contexts are more occluded on average
than training ones; fully occluded views occur; and the ids of the contexts that fail.
Exits 1 when a property fails. ``--compare-sizes`` also renders the contexts at other
sizes and prints their per-context statistics side by side. With ``--figures`` it also
renders the contact sheets.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from uevavd.data.grid import NX, NY, view_index  # noqa: E402
from uevavd.data.splits import N_CONTEXTS, SPLITS, TARGETS, split_of  # noqa: E402
from uevavd.data.synthetic import build_context, build_unoccluded, render_context, render_view  # noqa: E402
from uevavd.data.synthetic.cli import parse_contexts  # noqa: E402
from uevavd.data.synthetic.render import PreparedScene  # noqa: E402


def visible_by_context(world: Path) -> dict[int, np.ndarray]:
    out = {}
    for meta_path in sorted(world.glob("[0-9][0-9][0-9]/scene.json")):
        meta = json.loads(meta_path.read_text())
        out[int(meta["context"])] = np.array(list(meta["visible"].values()), np.float32)
    if not out:
        raise SystemExit(f"{world}: no context folders with scene.json; write a world with `uevavd synth` first")
    return out


def _visible(job: tuple[int, int, int]) -> tuple[int, np.ndarray]:
    cid, size, seed = job
    return cid, render_context(cid, size=size, seed=seed).visible


def render_visible(contexts: list[int], *, size: int, seed: int, workers: int) -> dict[int, np.ndarray]:
    """Visible fraction (605,) float32 of every view of ``contexts``, rendered in memory."""
    jobs = [(c, size, seed) for c in contexts]
    out = {}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=workers) if workers > 1 else _Serial() as pool:
        for i, (cid, vis) in enumerate(pool.map(_visible, jobs), 1):
            out[cid] = vis
            if i % 10 == 0 or i == len(jobs):
                print(f"  {i}/{len(jobs)} contexts at {size} px, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return out


class _Serial:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def map(self, fn, jobs):
        return map(fn, jobs)


def _stats(v: np.ndarray) -> tuple[float, float, float, float]:
    """mean visible, share >= 0.9, share < 0.5, share == 0."""
    return float(v.mean()), float(np.mean(v >= 0.9)), float(np.mean(v < 0.5)), float(np.mean(v == 0))


def report(vis: dict[int, np.ndarray]) -> tuple[str, bool]:
    """The per-split (and per-terrain) table of :mod:`uevavd.data.synthetic.quality`, then
    PASS/FAIL for: every context of every split passes the validity rule; hard-test
    contexts are more occluded on average than training ones; fully occluded views occur."""
    from uevavd.data.synthetic.quality import format_rows, split_rows
    from uevavd.data.synthetic.world import VALIDITY

    rows = split_rows(vis)
    lines = [format_rows(rows), ""]
    means = {r["split"]: r["mean"] for r in rows if r["terrain"] == "all"}
    bad = [c for c in sorted(vis) if not VALIDITY.passes(vis[c])]
    checks = [(f"every context ({len(vis)}) passes the validity rule: {VALIDITY.describe()}", not bad)]
    if "hard" in means and "train" in means:
        checks.append((f"hard test more occluded than train (mean visible {means['hard']:.3f} < "
                       f"{means['train']:.3f})", means["hard"] < means["train"]))
    n_zero = int(sum((v == 0).sum() for v in vis.values()))
    n_all = int(sum(len(v) for v in vis.values()))
    with_zero = sum(bool((v == 0).any()) for v in vis.values())
    checks.append((f"fully occluded views occur ({n_zero:,} of {n_all:,} views, in {with_zero} of {len(vis)} contexts)",
                   n_zero > 0))
    ok = True
    for text, good in checks:
        ok &= good
        lines.append(f"- {'PASS' if good else 'FAIL'}: {text}")
    lines.append("")
    lines.append("failing contexts: " + ("none" if not bad else ", ".join(f"{c:03d} ({split_of(c)})" for c in bad)))
    return "\n".join(lines), ok


def compare_sizes(contexts: list[int], sizes: list[int], *, seed: int, workers: int,
                  first: dict[int, np.ndarray]) -> str:
    """Per-context statistics at several sizes side by side (``first``: at ``sizes[0]``)."""
    by_size = {sizes[0]: first}
    for size in sizes[1:]:
        by_size[size] = render_visible(contexts, size=size, seed=seed, workers=workers)
    lines = ["| context | split | size | mean visible | >= 0.9 | < 0.5 | = 0 | mean abs diff per view |",
             "|---|---|---|---|---|---|---|---|"]
    worst = np.zeros(4)
    for c in contexts:
        ref = _stats(by_size[sizes[0]][c])
        for size in sizes:
            st = _stats(by_size[size][c])
            worst = np.maximum(worst, np.abs(np.subtract(st, ref)))
            diff = float(np.abs(by_size[size][c] - by_size[sizes[0]][c]).mean())
            lines.append(f"| {c:03d} | {split_of(c)} | {size} | {st[0]:.3f} | {st[1]:.1%} | {st[2]:.1%} | {st[3]:.1%} | "
                         f"{diff:.3f} |")
    lines.append("")
    lines.append(f"largest difference from {sizes[0]} px over these contexts: mean visible {worst[0]:.3f}, "
                 f">= 0.9 {worst[1]:.1%}, < 0.5 {worst[2]:.1%}, = 0 {worst[3]:.1%}")
    return "\n".join(lines)


def _sheet(tiles: list[np.ndarray], cols: int, pad: int = 2) -> np.ndarray:
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + cols - 1) // cols
    out = np.full((rows * (h + pad) + pad, cols * (w + pad) + pad, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        out[pad + r * (h + pad):pad + r * (h + pad) + h, pad + c * (w + pad):pad + c * (w + pad) + w] = t
    return out


def _with_box(view) -> np.ndarray:
    img = view.rgb.copy()
    x1, y1, x2, y2 = view.box.tolist()
    if x2 > x1:
        cv2.rectangle(img, (x1, y1), (x2 - 1, y2 - 1), (255, 40, 40), 1)
    return img


def figures(out_dir: Path, seed: int, size: int) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    iz = 2  # z = 80 m
    for cid, name in ((1, "train"), (26, "hard"), (56, "hard")):
        scene = build_context(cid, seed=seed)
        prep = PreparedScene(scene)
        # rows: north (y = +50) at the top; columns: west (x = -50) on the left
        tiles = [_with_box(render_view(scene, view_index(ix, iy, iz), size, prep))
                 for iy in reversed(range(NY)) for ix in range(NX)]
        path = out_dir / f"synthetic_context_{cid:03d}_{name}.png"
        cv2.imwrite(str(path), cv2.cvtColor(_sheet(tiles, NX), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        print("wrote", path)
    picks = [(5, 5, 4), (5, 5, 0), (0, 5, 0), (10, 5, 0), (5, 0, 0), (5, 10, 0), (0, 0, 2), (10, 10, 2)]
    tiles = []
    for t in TARGETS:
        scene = build_unoccluded(t, seed=seed)
        prep = PreparedScene(scene)
        tiles += [render_view(scene, view_index(*p), 96, prep).rgb for p in picks]
    path = out_dir / "synthetic_classes.png"
    cv2.imwrite(str(path), cv2.cvtColor(_sheet(tiles, len(picks)), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print("wrote", path)


def histogram(vis: dict[int, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=110)
    from uevavd.data.synthetic.world import terrain_of

    bins = np.linspace(0, 1, 21)
    groups = [(s, None) for s in SPLITS if s != "hard"] + [("hard", t) for t in (("urban", "shifted"),
                                                                               ("woodland", "training"))]
    for split, terrain in groups:
        cs = [c for c in vis if split_of(c) == split and (terrain is None or terrain_of(c) == terrain)]
        if cs:
            v = np.concatenate([vis[c] for c in cs])
            name = split if terrain is None else f"hard, {terrain[0]}" + (" (shifted)" if terrain[1] == "shifted" else "")
            ax.hist(v, bins=bins, histtype="step", density=True, lw=1.6, label=f"{name} ({len(cs)} contexts)")
    ax.set_xlabel("visible fraction of the target")
    ax.set_ylabel("density of views")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    print("wrote", path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--world", type=Path, help="a written world (reads scene.json of each context)")
    src.add_argument("--contexts", help="render these contexts in memory instead: all, or ids like 1-20,26")
    ap.add_argument("--figures", type=Path, help="folder for the contact sheets and the histogram")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=64, help="crop size of --contexts and of the figures")
    ap.add_argument("--workers", type=int, default=1, help="processes rendering contexts (--contexts)")
    ap.add_argument("--compare-sizes", help="with --contexts: also these sizes, per context, e.g. 64,128")
    args = ap.parse_args()
    t0, c0 = time.perf_counter(), time.process_time()
    if args.world:
        vis = visible_by_context(args.world)
        print(f"{len(vis)} contexts read from {args.world}")
    else:
        contexts = list(range(1, N_CONTEXTS + 1)) if args.contexts == "all" else parse_contexts(args.contexts)
        vis = render_visible(contexts, size=args.size, seed=args.seed, workers=args.workers)
        print(f"{len(vis)} contexts rendered in memory at {args.size} px, seed {args.seed}")
    text, ok = report(vis)
    print(text)
    if args.compare_sizes and not args.world:
        sizes = [args.size] + [int(x) for x in args.compare_sizes.split(",")]
        print()
        print(compare_sizes(sorted(vis), sizes, seed=args.seed, workers=args.workers, first=vis))
    if args.figures:
        histogram(vis, args.figures / "synthetic_visible_hist.png")
        figures(args.figures, args.seed, args.size)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"\n{time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0 + kids.ru_utime + kids.ru_stime:.0f} s CPU "
          f"(this process and its workers)")
    raise SystemExit(0 if ok else 1)


if __name__ == "__main__":
    main()

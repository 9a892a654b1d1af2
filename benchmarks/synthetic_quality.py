"""Quality of the synthetic world (issue 3, part 6): visible-fraction statistics per split
from a written world, and the contact sheets of ``docs/synthetic_world.md``.

    python benchmarks/synthetic_quality.py --world DIR [--figures docs/img]

Reads each scene's ``scene.json`` (visible fraction per view), prints per split: mean
visible fraction, the share of views with visible >= 0.9, < 0.5 and == 0, and checks the
stated properties: every training context has >= 10 % of views with visible >= 0.9 and
>= 10 % with < 0.5; hard-test contexts are more occluded on average than training ones;
fully occluded views occur. With ``--figures`` it also renders the contact sheets.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from uevavd.data.grid import NX, NY, view_index  # noqa: E402
from uevavd.data.splits import SPLITS, TARGETS, split_of  # noqa: E402
from uevavd.data.synthetic import build_context, build_unoccluded, render_view  # noqa: E402
from uevavd.data.synthetic.render import _Prep  # noqa: E402


def visible_by_context(world: Path) -> dict[int, np.ndarray]:
    out = {}
    for meta_path in sorted(world.glob("[0-9][0-9][0-9]/scene.json")):
        meta = json.loads(meta_path.read_text())
        out[int(meta["context"])] = np.array(list(meta["visible"].values()), np.float32)
    if not out:
        raise SystemExit(f"{world}: no context folders with scene.json; write a world with `uevavd synth` first")
    return out


def report(vis: dict[int, np.ndarray]) -> tuple[str, bool]:
    lines = ["| split | contexts | views | mean visible | >= 0.9 | < 0.5 | = 0 (fully occluded) |",
             "|---|---|---|---|---|---|---|"]
    means = {}
    for split in SPLITS:
        cs = [c for c in vis if split_of(c) == split]
        if not cs:
            continue
        v = np.concatenate([vis[c] for c in cs])
        means[split] = float(v.mean())
        lines.append(f"| {split} | {len(cs)} | {len(v)} | {v.mean():.3f} | {np.mean(v >= 0.9):.1%} | "
                     f"{np.mean(v < 0.5):.1%} | {np.mean(v == 0):.1%} |")
    ok = True
    checks = []
    train = [c for c in vis if split_of(c) == "train"]
    hi = min(float(np.mean(vis[c] >= 0.9)) for c in train) if train else float("nan")
    lo = min(float(np.mean(vis[c] < 0.5)) for c in train) if train else float("nan")
    checks.append((f"every training context: >= 10% views visible >= 0.9 (lowest {hi:.1%})", hi >= 0.1))
    checks.append((f"every training context: >= 10% views visible < 0.5 (lowest {lo:.1%})", lo >= 0.1))
    if "hard" in means and "train" in means:
        checks.append((f"hard test more occluded than train (mean visible {means['hard']:.3f} < "
                       f"{means['train']:.3f})", means["hard"] < means["train"]))
    n_zero = int(sum((v == 0).sum() for v in vis.values()))
    checks.append((f"fully occluded views occur ({n_zero})", n_zero > 0))
    lines.append("")
    for text, good in checks:
        ok &= good
        lines.append(f"- [{'x' if good else ' '}] {text}")
    return "\n".join(lines), ok


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
    for cid, name in ((1, "train"), (26, "hard")):
        scene = build_context(cid, seed=seed)
        prep = _Prep(scene)
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
        prep = _Prep(scene)
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
    bins = np.linspace(0, 1, 21)
    for split in SPLITS:
        cs = [c for c in vis if split_of(c) == split]
        if cs:
            v = np.concatenate([vis[c] for c in cs])
            ax.hist(v, bins=bins, histtype="step", density=True, lw=1.6, label=f"{split} ({len(cs)} contexts)")
    ax.set_xlabel("visible fraction of the target")
    ax.set_ylabel("density of views")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    print("wrote", path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", type=Path, required=True)
    ap.add_argument("--figures", type=Path, help="folder for the contact sheets and the histogram")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    vis = visible_by_context(args.world)
    text, ok = report(vis)
    print(text)
    if args.figures:
        histogram(vis, args.figures / "synthetic_visible_hist.png")
        figures(args.figures, args.seed, args.size)
    raise SystemExit(0 if ok else 1)


if __name__ == "__main__":
    main()

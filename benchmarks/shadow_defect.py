"""How much world version 4's shadow defect changes the images (docs/synthetic_world.md, "Known
defect"): every context of a preset's world rendered as written (only ellipsoids cast
shadows) and with the hulls' shadows too (``_ShadowMap.HULL_SHADOWS``, the fix meant for
world version 5), and the share of pixels, and of the target's pixels, that differ.

    OMP_NUM_THREADS=1 python benchmarks/shadow_defect.py [--preset quick] [--size 64] [--every 20]

Prints one row per context (terrain, split, pixels changed, target pixels changed, the
target's mean brightness with the fix over without it, views whose target darkens by a
fifth or more), then the mean over contexts per split.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--every", type=int, default=20, help="render every N-th of the 605 views")
    args = ap.parse_args()

    from uevavd.data.grid import N_VIEWS
    from uevavd.data.synthetic import build_context, render_view
    from uevavd.data.synthetic.render import _Prep
    from uevavd.data.synthetic.scenes import TARGET_ID
    from uevavd.data.synthetic.shading import _ShadowMap
    from uevavd.presets import load_preset, world_contexts

    views = range(0, N_VIEWS, args.every)
    rows = []
    print(f"{'context':>7} {'terrain':8} {'split':6} {'pixels changed':>14} {'target changed':>14} "
          f"{'target brightness':>17} {'target darker by 1/5+':>21}")
    for c in world_contexts(load_preset(args.preset)):
        scene = build_context(c, seed=0)
        renders = {}
        for hull_shadows in (False, True):
            _ShadowMap.HULL_SHADOWS = hull_shadows
            prep = _Prep(scene)
            renders[hull_shadows] = [render_view(scene, v, args.size, prep) for v in views]
        _ShadowMap.HULL_SHADOWS = False
        changed, target_changed, ratio, darker = [], [], [], []
        for now, fixed in zip(renders[False], renders[True], strict=True):
            diff = (now.rgb != fixed.rgb).any(-1)
            changed.append(diff.mean())
            target = now.seg == TARGET_ID
            if target.any():
                target_changed.append(diff[target].mean())
                r = fixed.rgb[target].mean() / max(now.rgb[target].mean(), 1e-9)
                ratio.append(r)
                darker.append(r <= 0.8)
        row = (c, scene.terrain, scene.split, np.mean(changed), np.mean(target_changed), np.mean(ratio), np.mean(darker))
        rows.append(row)
        print(f"{c:7d} {row[1]:8} {row[2]:6} {100 * row[3]:13.1f}% {100 * row[4]:13.1f}% {row[5]:17.2f} {100 * row[6]:20.0f}%")
    for split in dict.fromkeys(r[2] for r in rows):
        sel = [r for r in rows if r[2] == split]
        print(f"{split:>7} mean over {len(sel)} contexts: pixels changed {100 * np.mean([r[3] for r in sel]):.1f} %, "
              f"target pixels changed {100 * np.mean([r[4] for r in sel]):.1f} %, target brightness "
              f"{np.mean([r[5] for r in sel]):.2f}, views whose target darkens by 1/5+ {100 * np.mean([r[6] for r in sel]):.0f} %")


if __name__ == "__main__":
    main()

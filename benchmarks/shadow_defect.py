"""How much world version 4's shadow defect changes the images (docs/synthetic_world.md, "Known
defect"): every context of a preset's world rendered as written (only ellipsoids cast
shadows) and with the hulls' shadows too (``_ShadowMap.HULL_SHADOWS``, the fix meant for
world version 5), and the share of pixels, and of the target's pixels, that differ.

    OMP_NUM_THREADS=1 python benchmarks/shadow_defect.py [--preset quick] [--size 64] [--every 20]
    python benchmarks/shadow_defect.py --recognizer [--workers 2] [--threads 2]

Prints one row per context (terrain, split, pixels changed, target pixels changed, the
target's mean brightness with the fix over without it, views whose target darkens by a
fifth or more), then the mean over contexts per split.

``--recognizer`` instead writes the preset's world both ways (in a temporary folder, with a
temporary ``UEVAVD_CACHE``), trains the preset's recognizer on each world's ``train_605``
and builds its MAP table, and prints the recognizer's held-out accuracy (``train_605``
viewpoints) and its accuracy on each split's views, all and clear (visible >= 0.9): what the
defect does to the perception every method reads (about 7 minutes for the quick preset).
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
    ap.add_argument("--recognizer", action="store_true", help="compare the recognizer trained on each world")
    ap.add_argument("--workers", type=int, default=2, help="processes for --recognizer")
    ap.add_argument("--threads", type=int, default=2,
                    help="torch threads for --recognizer (the recognizer's float sums depend on it; the zoo's was "
                         "trained with 2)")
    args = ap.parse_args()
    if args.recognizer:
        _recognizer(args.preset, args.workers, args.threads)
        return

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


def _recognizer(preset_name: str, workers: int, threads: int) -> None:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(prefix="uevavd-shadows-") as tmp:
        os.environ["UEVAVD_CACHE"] = str(Path(tmp) / "cache")  # nothing of these worlds outlives the run
        from uevavd import api
        from uevavd.data.synthetic.shading import _ShadowMap
        from uevavd.data.synthetic.writer import write_world
        from uevavd.experiments.audit import audit_table, classifier_summary
        from uevavd.presets import load_preset, preset_overrides, world_contexts

        preset = load_preset(preset_name)
        world = preset["world"]
        rows = []
        for hull_shadows in (False, True):
            name = "hull shadows (world version 5)" if hull_shadows else "as written (version 4)"
            _ShadowMap.HULL_SHADOWS = hull_shadows  # the world's worker processes are forked after this
            try:
                data = write_world(Path(tmp) / f"world-{hull_shadows}", contexts=world_contexts(preset),
                                   size=world["size"], seed=world["seed"], workers=workers)
            finally:
                _ShadowMap.HULL_SHADOWS = False
            clf = api.train_classifier(data, Path(tmp) / f"recognizer-{hull_shadows}.safetensors", workers=workers,
                                       threads=threads, **preset.get("classifier", {}))
            table = api.build_table(data, "map", classifier=clf, overrides=preset_overrides(preset),
                                    out_dir=Path(tmp) / f"table-{hull_shadows}", workers=workers)
            rows.append((name, classifier_summary(clf)["val_accuracy"], audit_table(table)))
        print(f"recognizer of preset {preset_name!r} ({preset.get('classifier', {})}), MAP table's views:")
        for name, held_out, audit in rows:
            splits = ", ".join(f"{split} {a['accuracy']:.3f} (clear {a['clear_accuracy']:.3f})" for split, a in audit.items())
            print(f"  {name:32s} held-out train_605 {held_out:.3f}; accuracy {splits}")


if __name__ == "__main__":
    main()

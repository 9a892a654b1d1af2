"""Stage times of a paper64 ablation, and what the paper preset (256 px) would take on this machine.

    python benchmarks/paper_projection.py --ablation DIR [--stage-from STAGE=DIR2 ...] [--threads 2]

DIR is a finished ``uevavd ablate --preset paper64`` folder: its ``ablation.json`` holds the
wall time of each stage (world, classifier, tables, training, evaluation, report). Each stage
is then projected to the ``paper`` preset (256 px crops, ResNet50 encoder, ResNet18
recognizer trained 30 epochs, the paper's network sizes, 300,000 episodes) by the ratio of a
unit of its work, both units timed here in the same run, one after the other:

* world       one view rendered at 64 px and at 256 px (one training context, one thread,
              as each world-generation worker renders);
* tables      one crop through the table's models: Lite0 encoder + Lite0 recognizer at 64 px
              against the ResNet50 encoder + ResNet18 recognizer at 256 px;
* classifier  one training step (batch 64, forward and backward) of a Lite0 at 64 px against
              a ResNet18 at 256 px, times the epochs (30 against paper64's);
* training    one training episode in the learning phase, each preset's networks and update
              schedule on a stand-in table of its feature size (1280-d, 2048-d), on one
              thread as each of an ablation's runs: the
              difference of two short runs (``--short`` and ``--long`` episodes) over the
              difference of their lengths, times the episodes (300,000 against paper64's);
* evaluation, report: as measured (the same contexts and runs).

``--stage-from world=DIR2`` takes a stage's measured time from another ablation's
``ablation.json`` (an ablation that found the world or tables cached measured a few seconds
for them: take those stages from one that built them, on the same world).

Weights are random: speed does not depend on them. The projection assumes the paper preset
runs as paper64 did (same workers, same number of runs); it is a projection, printed beside
the measured figures, not a measurement of the paper preset.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def _best(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def render_unit(size: int, views: int = 12) -> float:
    from uevavd.data.grid import N_VIEWS
    from uevavd.data.synthetic import build_context, render_view
    from uevavd.data.synthetic.render import PreparedScene

    scene = build_context(1, seed=0)  # a training context
    prep = PreparedScene(scene)
    picks = np.linspace(0, N_VIEWS - 1, views).astype(int)
    for v in picks:  # shadow tiles and caches built before timing
        render_view(scene, int(v), size, prep)
    return _best(lambda: [render_view(scene, int(v), size, prep) for v in picks], 2) / views


def _model(arch: str, n_out: int) -> torch.nn.Module:
    import torchvision

    if arch == "efficientnet_lite0":
        from uevavd.perception.training.classifier import initial_model

        return initial_model(None, n_out, 0, arch=arch, init="random")[0]
    return getattr(torchvision.models, arch)(weights=None, num_classes=n_out)


def forward_unit(arch: str, size: int, batch: int = 32) -> float:
    model = _model(arch, 5).eval().to(memory_format=torch.channels_last)
    x = torch.rand(batch, 3, size, size).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        return _best(lambda: model(x), 3) / batch


def train_step_unit(arch: str, size: int, batch: int = 64) -> float:
    model = _model(arch, 5).train().to(memory_format=torch.channels_last)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3)
    x = torch.rand(batch, 3, size, size).contiguous(memory_format=torch.channels_last)
    y = torch.randint(0, 5, (batch,))

    def step():
        opt.zero_grad()
        torch.nn.functional.cross_entropy(model(x), y).backward()
        opt.step()

    return _best(step, 2)


def episode_unit(preset: str, feature_dim: int, short: int, long: int) -> float:
    from uevavd import api
    from uevavd.presets import load_preset, preset_overrides
    from uevavd.testing.policy import toy_table

    over = preset_overrides(load_preset(preset))
    over.update({"train.eval_splits": ["train"], "train.eval_contexts": 4, "train.threads": 1,  # as an ablation's runs
                 "train.learning_starts": 500, "train.eps_fraction": 0.05})
    with tempfile.TemporaryDirectory() as tmp:
        table = toy_table(n_train=20, n_hard=2, feature_dim=feature_dim)
        walls = {}
        for n in (short, long):
            over["train.epoch_episodes"] = n
            t = time.perf_counter()
            api.train("ibe_map", table, out=Path(tmp) / f"{n}", episodes=n, overrides=over, device="cpu", progress=False)
            walls[n] = time.perf_counter() - t
    return (walls[long] - walls[short]) / (long - short)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ablation", required=True, type=Path, help="a finished `uevavd ablate --preset paper64` folder")
    ap.add_argument("--stage-from", action="append", default=[], metavar="STAGE=DIR",
                    help="a stage's measured time from another ablation's ablation.json (repeatable)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads for the model units (default 2)")
    ap.add_argument("--short", type=int, default=1_000, help="episodes of the short training run")
    ap.add_argument("--long", type=int, default=2_500, help="episodes of the long training run")
    args = ap.parse_args()
    meta_path = args.ablation / "ablation.json"
    try:
        meta = json.loads(meta_path.read_text())
        stages = meta["stages"]
    except (OSError, ValueError, KeyError) as e:
        print(f"paper_projection: {meta_path}: expected a finished ablation's ablation.json ({e}); "
              "run `uevavd ablate --preset paper64 --out DIR` first", file=sys.stderr)
        return 2
    source = {stage: "" for stage in stages}
    for item in args.stage_from:
        stage, _, other = item.partition("=")
        try:
            stages[stage] = json.loads((Path(other) / "ablation.json").read_text())["stages"][stage]
        except (OSError, ValueError, KeyError) as e:
            print(f"paper_projection: --stage-from {item}: expected STAGE=DIR of an ablation recording that stage "
                  f"({e})", file=sys.stderr)
            return 2
        source[stage] = f" ({Path(other).name})"
    from uevavd.presets import load_preset

    p64, paper = load_preset(meta.get("preset", "paper64")), load_preset("paper")
    episodes64 = int(p64["overrides"]["train.episodes"])
    episodes256 = int(paper["overrides"]["train.episodes"])
    epochs64 = int(p64.get("classifier", {}).get("epochs", 8))
    epochs256 = int(paper.get("classifier", {}).get("epochs", 30))
    torch.set_num_threads(args.threads)

    print("timing the units of work (a few minutes) ...", flush=True)
    units = {}
    units["world"] = (render_unit(64), render_unit(256), 1.0)
    print(f"  render: {units['world'][0] * 1e3:.1f} ms / view at 64 px, {units['world'][1] * 1e3:.1f} at 256", flush=True)
    units["tables"] = (forward_unit("efficientnet_lite0", 64) * 2,
                       forward_unit("resnet50", 256) + forward_unit("resnet18", 256), 1.0)
    print(f"  tables: {units['tables'][0] * 1e3:.2f} ms / crop at 64 px, {units['tables'][1] * 1e3:.2f} at 256", flush=True)
    units["classifier"] = (train_step_unit("efficientnet_lite0", 64), train_step_unit("resnet18", 256),
                           epochs256 / epochs64)
    print(f"  classifier: {units['classifier'][0]:.3f} s / step at 64 px, {units['classifier'][1]:.3f} at 256", flush=True)
    units["training"] = (episode_unit(meta.get("preset", "paper64"), 1280, args.short, args.long),
                         episode_unit("paper", 2048, args.short, args.long), episodes256 / episodes64)
    print(f"  training: {units['training'][0] * 1e3:.2f} ms / episode (paper64), "
          f"{units['training'][1] * 1e3:.2f} (paper sizes)", flush=True)

    print(f"\n{'stage':<12}{'paper64 (measured)':>20}{'unit ratio':>12}{'count ratio':>13}{'paper, projected':>18}")
    total64 = total256 = 0.0
    for stage, secs in stages.items():
        unit64, unit256, count = units.get(stage, (1.0, 1.0, 1.0))
        ratio = unit256 / unit64
        proj = secs * ratio * count
        total64, total256 = total64 + secs, total256 + proj
        print(f"{stage:<12}{secs / 60:>17.1f} min{ratio:>12.1f}{count:>13.1f}{proj / 3600:>16.1f} h"
              f"{source.get(stage, '')}")
    print(f"{'total':<12}{total64 / 60:>17.1f} min{'':>25}{total256 / 3600:>16.1f} h")
    return 0


if __name__ == "__main__":
    sys.exit(main())

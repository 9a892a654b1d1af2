"""Where a cold start's time goes: the world's rendering and writing, and the tables' encoding.

The demo's two stages before any learning (the world, the tables) took about 60 % of a cold
`uevavd demo`. This script splits each into its parts, in one process on one core so that each
part's time is its own (the stages run on two cores; the last lines compare), and prints each
part's rate beside a floor measured in the same run:

- world: `write_scene` of ``--contexts`` under cProfile, its time by part (ray casting,
  shading, the rest of the renderer, the scene's construction, PNG encoding, file writes,
  sha256, other); floors: the renderer's pure numpy work on a 64 px frame (one ray-plane pass
  per visible primitive) and `cv2.imencode` alone;
- tables: decoding the PNGs, the quick preset's encoder (EfficientNet-Lite0, ImageNet) and
  recognizer forwards on those views, IBE-MAP's decomposition, and writing the sealed shards;
  floor of a forward: the same network on a random batch of the same shape (torch's rate here,
  without the pipeline around it).

    python benchmarks/cold_start_profile.py [--contexts 1,26] [--size 64]

Prints a table per stage and the machine-speed reference (`../shared/tools/refwork.py`) where
it exists.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from machine_speed import refwork

#: The parts of the world's time, by the file (or function) cProfile charges it to, first match wins.
WORLD_PARTS = (
    ("PNG encoding", ("imencode",)),
    ("sha256", ("sha256", "openssl_sha256")),
    ("file writes", ("write_bytes", "'write' of '_io", "open>", "mkdir")),
    ("ray casting", ("raycast.py",)),
    ("shading", ("shading.py",)),
    ("the rest of the renderer", ("render.py",)),
    ("the scene's construction", ("scenes.py", "world.py", "ground.py", "vehicles.py", "geometry.py", "draws.py")),
)


def _part(key: tuple) -> str:
    filename, _, func = key
    where = f"{filename}:{func}"
    for name, needles in WORLD_PARTS:
        if any(n in where for n in needles):
            return name
    return "other"


def world(root: Path, contexts: list[int], size: int) -> tuple[float, int]:
    from uevavd.data.synthetic.writer import write_scene

    names = [f"{c:03d}" for c in contexts]
    profile = cProfile.Profile()
    t0 = time.perf_counter()
    profile.enable()
    for name in names:
        write_scene(root, name, size=size, seed=0)
    profile.disable()
    wall = time.perf_counter() - t0
    views = 605 * len(names)
    stats = pstats.Stats(profile)
    own: dict[str, float] = {}
    for key, (_, _, tottime, _, _) in stats.stats.items():  # self time: each second counted once
        own[_part(key)] = own.get(_part(key), 0.0) + tottime
    total = sum(own.values())
    print(f"\n## World: write_scene of contexts {names} at {size} px, one process ({views} views)\n")
    print("| part | ms per view | share |")
    print("|---|---|---|")
    labels = {"other": "numpy's own functions (take, put, reductions) and the rest: mostly the renderer's"}
    for name, _ in (*WORLD_PARTS, ("other", ())):
        t = own.get(name, 0.0)
        print(f"| {labels.get(name, name)} | {1000 * t / views:.2f} | {100 * t / total:.0f} % |")
    print(f"| all (profiled; {wall:.1f} s wall with the profiler) | {1000 * total / views:.2f} | 100 % |")
    return wall, views


def world_floors(root: Path, size: int) -> None:
    import cv2

    from uevavd.data.synthetic import build_context, render_view
    from uevavd.data.synthetic.render import PreparedScene

    scene = build_context(1, seed=0)
    prep = PreparedScene(scene)
    views = np.linspace(0, 604, 121).astype(int)
    render_view(scene, int(views[0]), size, prep)
    t0 = time.perf_counter()
    frames = [render_view(scene, int(v), size, prep) for v in views]
    render_ms = 1000 * (time.perf_counter() - t0) / len(views)
    level = [cv2.IMWRITE_PNG_COMPRESSION, 3]  # the writer's
    t0 = time.perf_counter()
    for f in frames:
        cv2.imencode(".png", cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR), level)
        cv2.imencode(".png", f.seg.astype(np.uint16), level)
    enc_ms = 1000 * (time.perf_counter() - t0) / len(frames)
    # the floor of the arithmetic: one ray-plane pass per plane of the visible primitives over
    # the frame's rays, as float32 numpy (4 multiply-adds and a compare per ray and plane)
    rays = np.random.default_rng(0).normal(size=(size * size, 3)).astype(np.float32)
    planes = np.random.default_rng(1).normal(size=(60, 4)).astype(np.float32)  # ~10 boxes of 6 faces
    t0 = time.perf_counter()
    for _ in range(20):
        d = rays @ planes[:, :3].T
        _ = (planes[:, 3] / np.where(d == 0, 1, d)) > 0
    floor_ms = 1000 * (time.perf_counter() - t0) / 20
    print(f"\n## World floors, {size} px, one core\n")
    print("| what | ms per view |")
    print("|---|---|")
    print(f"| render_view alone (121 views of context 001) | {render_ms:.2f} |")
    print(f"| one ray-plane pass over 60 planes (numpy float32): the arithmetic's floor | {floor_ms:.3f} |")
    print(f"| cv2.imencode of a view's two PNGs (RGB and uint16 segmentation, level 3), alone | {enc_ms:.3f} |")


def tables(root: Path, contexts: list[int], workers: int) -> None:
    import torch

    from uevavd.config import load_method
    from uevavd.data.reader import read_dataset
    from uevavd.perception.decompose import decompose, view_seed
    from uevavd.perception.images import Decoder
    from uevavd.perception.prepare import build_components, ground_truth_categories
    from uevavd.perception.shards import write_shard
    from uevavd.presets import ZOO, cli_layers

    torch.set_num_threads(1)
    manifest = read_dataset(root)
    preset, overrides = cli_layers("quick", [])
    recognizer = ZOO / "pretrained" / "quick" / "recognizer.safetensors"
    map_spec = load_method("map", overrides, preset=preset)
    ibe_spec = load_method("ibe_map", overrides, preset=preset)
    _, encoder, classifier = build_components(map_spec.perception, root, str(recognizer))
    segmenter, *_ = build_components(ibe_spec.perception, root, str(recognizer))
    gray_seed = ibe_spec.perception.gray_seed
    rows = []
    for c in contexts:
        scene = f"{c:03d}"
        recs = [r for r in manifest.records if r.scene == scene]
        dec = Decoder(workers)
        t0 = time.perf_counter()
        images = dec.images([r.image for r in recs])
        rows.append(("decode the PNGs", time.perf_counter() - t0, len(recs)))
        t0 = time.perf_counter()
        maps = dec.instance_maps([r.seg for r in recs])
        rows.append(("decode the segmentation PNGs (IBE-MAP)", time.perf_counter() - t0, len(recs)))
        t0 = time.perf_counter()
        feats = encoder.encode(images)
        rows.append(("encoder forward (EfficientNet-Lite0)", time.perf_counter() - t0, len(recs)))
        t0 = time.perf_counter()
        classifier.predict_proba(images)
        rows.append(("recognizer forward", time.perf_counter() - t0, len(recs)))
        cats = [ground_truth_categories(manifest, scene, recs)] * len(recs)
        t0 = time.perf_counter()
        if hasattr(segmenter, "decompose_views"):
            segmenter.decompose_views(images, maps, cats, [view_seed(gray_seed, scene, r.view, r.target) for r in recs])
        else:
            boxes = np.array([r.box for r in recs], np.int64)
            segs = segmenter.segment(images, boxes, instance_maps=maps, categories=cats)
            [decompose(i, s.target, s.segments, seed=0) for i, s in zip(images, segs, strict=True)]
        rows.append(("IBE-MAP's decomposition (gt segmenter)", time.perf_counter() - t0, len(recs)))
        t0 = time.perf_counter()
        write_shard(root / f".shard-{scene}.npz", {"features": feats.astype(np.float16)})
        rows.append(("write a sealed shard (fsync)", time.perf_counter() - t0, len(recs)))
        dec.close()
    # floors: the networks alone (batch norms folded, channels-last, inference mode: what the
    # pipeline runs) on a random batch of the same shape, and the work of one forward
    x = torch.rand(len(recs), 3, images.shape[1], images.shape[2]).contiguous(memory_format=torch.channels_last)
    floors = {}
    for name, runner in (("encoder", getattr(encoder, "runner", None)), ("recognizer", getattr(classifier, "runner", None))):
        if runner is None:
            continue
        module = runner.model
        with torch.inference_mode():
            module(x[:8])
            t0 = time.perf_counter()
            for i in range(0, len(x), runner.batch_size):
                module(x[i:i + runner.batch_size])
            floors[name] = (time.perf_counter() - t0, _macs(module, x[:1]))
    print(f"\n## Tables: contexts {[f'{c:03d}' for c in contexts]}, the quick preset's components, one torch thread\n")
    print("| part | views per s | ms per view |")
    print("|---|---|---|")
    agg: dict[str, list[float]] = {}
    for name, t, n in rows:
        agg.setdefault(name, [0.0, 0])
        agg[name][0] += t
        agg[name][1] += n
    for name, (t, n) in agg.items():
        print(f"| {name} | {n / t:.0f} | {1000 * t / n:.2f} |")
    for name, (t, macs) in floors.items():
        print(f"| floor: the {name}'s network alone on a random batch ({macs / 1e6:.0f} M multiply-adds a view, "
              f"{2 * macs * len(x) / t / 1e9:.1f} GFLOP/s) | {len(x) / t:.0f} | {1000 * t / len(x):.2f} |")


def _macs(module, x) -> float:
    """Multiply-adds of one forward of ``module`` on ``x``: its convolutions' and linear layers'."""
    import torch

    total = 0.0

    def hook(mod, inp, out):
        nonlocal total
        if isinstance(mod, torch.nn.Conv2d):
            total += out.numel() * (mod.in_channels // mod.groups) * mod.kernel_size[0] * mod.kernel_size[1]
        elif isinstance(mod, torch.nn.Linear):
            total += out.numel() * mod.in_features

    handles = [m.register_forward_hook(hook) for m in module.modules()]
    with torch.inference_mode():
        module(x)
    for h in handles:
        h.remove()
    return total


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--contexts", default="1,26", help="contexts to write and encode (default 1,26)")
    parser.add_argument("--size", type=int, default=64, help="crop size in px (default 64, the quick preset's)")
    parser.add_argument("--workers", type=int, default=1, help="decoding threads (default 1: one core)")
    args = parser.parse_args()
    contexts = [int(c) for c in args.contexts.split(",")]
    print(refwork())
    root = Path(tempfile.mkdtemp(prefix="uevavd-cold-"))
    try:
        world(root, contexts, args.size)
        world_floors(root, args.size)
        from uevavd.data.synthetic.writer import _write_card_and_manifest

        _write_card_and_manifest(root, [f"{c:03d}" for c in contexts], contexts, args.size, 0, False)
        tables(root, contexts, args.workers)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(refwork())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

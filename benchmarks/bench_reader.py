"""How fast does the dataset reader turn ~10^5 views into a manifest?

Builds a canonical-layout dataset of tiny PNGs (default: 150 context scenes, "00" and "train_605",
96,800 views) in a temporary folder, then times, in the same run:

* baseline: the I/O floor every reader pays - list every scene folder and read every
  annotation file (no parsing, no checks);
* ``read_dataset(root, check=True)``: names parsed, annotations parsed, counts, boxes and
  sizes checked;
* ``validate(root)`` on a subset of scenes: every image force-decoded (threads).

Run: ``python benchmarks/bench_reader.py [--scenes N] [--validate-scenes N] [--workers N]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from uevavd.data.grid import N_VIEWS, view_coords
from uevavd.data.layout import view_stem
from uevavd.data.reader import read_dataset
from uevavd.data.splits import TARGETS
from uevavd.data.validate import validate


def build(root: Path, n_scenes: int, size: int) -> None:
    """Contexts 1..n_scenes (one target per block of 30), plus "00" and "train_605" with
    all five targets: the full release (150) is 150 * 605 + 2 * 5 * 605 = 96,800 views."""
    img = np.random.default_rng(0).integers(0, 255, (size, size, 3), dtype=np.uint8)
    png = cv2.imencode(".png", img)[1].tobytes()
    coords = [tuple(int(c) for c in view_coords(v)) for v in range(N_VIEWS)]
    sets = [(f"{cid:03d}", TARGETS[(cid - 1) // 30]) for cid in range(1, n_scenes + 1)]
    sets += [(scene, t) for scene in ("00", "train_605") for t in TARGETS]
    for scene, target in sets:
        d = root / scene
        d.mkdir(parents=True, exist_ok=True)
        for v, (x, y, z) in enumerate(coords):
            stem = view_stem(x, y, z, target, scene)
            (d / f"{stem}.png").write_bytes(png)
            box = "0 0 0 0" if v % 7 == 0 else f"1 1 {size - 1} {size - 1}"
            (d / f"{stem}.txt").write_text(box)


def baseline(root: Path) -> int:
    n = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            if f.endswith(".txt"):
                with open(os.path.join(dirpath, f), "rb") as fh:
                    fh.read()
                n += 1
    return n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=150, help="context scenes (max 150)")
    ap.add_argument("--validate-scenes", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--size", type=int, default=32, help="image side in pixels")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_reader_") as tmp:
        root = Path(tmp) / "data"
        t = time.perf_counter()
        build(root, args.scenes, args.size)
        print(f"built {args.scenes} scenes x {N_VIEWS} views in {time.perf_counter() - t:.1f} s")
        timings = {}
        for name, fn in (("baseline (list + read annotations)", lambda: baseline(root)),
                         ("read_dataset(check=True)", lambda: len(read_dataset(root)))):
            best = float("inf")
            for _ in range(2):  # second run has a warm page cache, like the first after a build
                t = time.perf_counter()
                n = fn()
                best = min(best, time.perf_counter() - t)
            timings[name] = best
            print(f"{name:<40} {n:>7} views  {best:6.2f} s  {n / best:9.0f} views/s")
        ratio = timings["read_dataset(check=True)"] / timings["baseline (list + read annotations)"]
        print(f"read_dataset / baseline: {ratio:.2f}x")
        sub = Path(tmp) / "sub"
        sub.mkdir()
        for cid in range(1, min(args.validate_scenes, args.scenes) + 1):
            os.symlink(root / f"{cid:03d}", sub / f"{cid:03d}")
        for workers in sorted({1, args.workers}):
            t = time.perf_counter()
            report = validate(sub, workers=workers, progress=False)
            dt = time.perf_counter() - t
            print(f"validate (decode {args.size}px PNGs), {workers} thread(s): {report.decoded:>7} images  "
                  f"{dt:6.2f} s  {report.decoded / dt:9.0f} images/s  ok={report.ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

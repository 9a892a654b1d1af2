"""Validate a UEVAVD-layout root: every check of the reader plus a forced decode of every
image and segmentation, and the sha256 of every file where ``manifest.json`` lists one.

``uevavd validate ROOT`` prints the root, image size, scenes, the contexts each target
owns, split counts (against the paper's 100 / 25 / 25 when the release is complete),
the occluded-view fraction overall and per split, and every problem grouped by kind
(``--max-per-kind N`` to shorten the list; the report counts what it left out); it exits
1 when there are problems, including files the reader cannot use.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..hashing import sha256_hex
from .layout import CATEGORIES, MANIFEST
from .reader import UNUSED_FILE_KINDS, Problem, scan
from .records import Manifest
from .splits import CLASSIFIER_SCENE, N_CONTEXTS, SPLITS, UNOCCLUDED_SCENE, counts

_PNG_END = b"IEND\xaeB`\x82"


@dataclass
class ValidationReport:
    """What :func:`validate` found. ``problems`` holds every problem, each naming its
    file; ``manifest`` every record that parsed; ``decoded`` how many images were
    force-decoded; ``hashed`` how many files were checked against ``manifest.json``."""

    root: Path
    manifest: Manifest
    problems: list[Problem] = field(default_factory=list)
    decoded: int = 0
    hashed: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> dict:
        """Scenes, contexts per target, per-split counts and occluded fractions."""
        m = self.manifest
        by_target: dict[str, list[int]] = defaultdict(list)
        for cid, target in m.contexts().items():
            by_target[target].append(cid)
        occ = m.occluded()
        groups: dict[str, list[int]] = defaultdict(list)
        split_ctx: dict[str, set[int]] = defaultdict(set)
        for i, r in enumerate(m.records):
            groups[r.split or r.scene].append(i)
            if r.split is not None:
                split_ctx[r.split].add(r.context)
        splits = {s: {"contexts": len(split_ctx[s]), "views": len(groups.get(s, []))} for s in SPLITS}
        occluded = {k: float(occ[idx].mean()) for k, idx in groups.items()}
        return {
            "root": str(self.root),
            "image_size": list(m.image_size),
            "records": len(m),
            "scenes": m.scenes(),
            "targets": {t: sorted(c) for t, c in sorted(by_target.items())},
            "splits": splits,
            "complete": len(m.contexts()) == N_CONTEXTS,
            "occluded": {"all": float(occ.mean()) if len(m) else 0.0, **occluded},
            "problems": dict(sorted(Counter(p.kind for p in self.problems).items())),
        }

    def format(self, *, verbose: bool = False, per_kind: int | None = None) -> str:
        """Human-readable report listing every problem, or at most ``per_kind`` of each kind
        (the rest counted, and how to see them said); ``verbose`` lists all regardless."""
        s = self.summary()
        h, w = s["image_size"]
        scenes = s["scenes"]
        ctx = [n for n in scenes if n not in (UNOCCLUDED_SCENE, CLASSIFIER_SCENE)]
        lines = [
            f"root        {s['root']}",
            f"image size  {h} x {w} (H x W)",
            f"records     {s['records']} views",
            f"scenes      {len(scenes)}: {len(ctx)} context(s) {_ranges(self.manifest.contexts()) or '-'}"
            + "".join(f", {n!r}" for n in scenes if n not in ctx),
            "targets     (contexts each owns)",
        ]
        for t, cids in s["targets"].items():
            lines.append(f"  {t:<10} {len(cids):>3}: {_ranges(cids)}")
        paper = counts()
        lines.append("splits      contexts   views" + ("   (paper)" if s["complete"] else ""))
        for name, c in s["splits"].items():
            ref = f"   ({paper[name]['contexts']} / {paper[name]['views']})" if s["complete"] else ""
            lines.append(f"  {name:<8} {c['contexts']:>10} {c['views']:>7}{ref}")
        if not s["complete"]:
            n_ctx = sum(len(c) for c in s["targets"].values())
            lines.append(f"  (partial release: {n_ctx} of {N_CONTEXTS} contexts; the paper has 100 / 25 / 25)")
        lines.append("occluded    (fraction of views with box 0 0 0 0)")
        for k, v in s["occluded"].items():
            lines.append(f"  {k:<10} {v:.3f}")
        lines.append(f"decoded     {self.decoded} image(s); hashes checked for {self.hashed} file(s)")
        if self.ok:
            lines.append("no problems")
            return "\n".join(lines)
        by_kind: dict[str, list[Problem]] = defaultdict(list)
        for p in self.problems:
            by_kind[p.kind].append(p)
        cap = None if verbose or per_kind is None else max(0, int(per_kind))
        hidden = 0 if cap is None else sum(max(0, len(v) - cap) for v in by_kind.values())
        head = f"PROBLEMS    {len(self.problems)}"
        if hidden:
            head += f" ({hidden} not listed: at most {cap} per kind; omit --max-per-kind to list all)"
        lines.append(head)
        for kind in sorted(by_kind):
            items = by_kind[kind]
            note = " (files the reader cannot use; it reads the rest)" if kind in UNUSED_FILE_KINDS else ""
            lines.append(f"  {kind} ({len(items)}){note}")
            shown = items if cap is None else items[:cap]
            lines.extend(f"    {p}" for p in shown)
            if len(shown) < len(items):
                lines.append(f"    ... {len(items) - len(shown)} more {kind} not listed (omit --max-per-kind)")
        return "\n".join(lines)


def _ranges(ids: Iterable[int]) -> str:
    ids = sorted(ids)
    parts, start = [], None
    for i, c in enumerate(ids):
        if start is None:
            start = c
        if i + 1 == len(ids) or ids[i + 1] != c + 1:
            parts.append(f"{start}" if start == c else f"{start}-{c}")
            start = None
    return ", ".join(parts)


def segmentation_problem(manifest, scene: str, recs: list) -> str | None:
    """Why a scene's ground-truth segmentation cannot serve a ground-truth segmenter (IBE-MAP's
    ``gt``), or None: views without a segmentation PNG, no ``seg/categories.json``, or no
    instance of category ``target`` in it (every target pixel would then be grayed like the
    background). The one rule ``validate`` and ``prepare`` share."""
    missing = [r for r in recs if r.seg is None]
    if missing:
        return (f"scene {scene}: {len(missing)} of its {len(recs)} views have no ground-truth segmentation "
                f"(e.g. {missing[0].image}); the gt segmenter needs every view's")
    path = Path(recs[0].seg).parent / CATEGORIES
    cats = manifest.categories(scene)
    if cats is None:
        return (f"scene {scene}: {path} is missing; the ground-truth segmenter needs it to tell the target from "
                'other instances ({"<instance id>": "<category>", ...}, with a "target" entry)')
    if "target" not in cats.values():
        return (f"{path}: no instance has category 'target' (categories: {sorted(set(cats.values()))}); the "
                "ground-truth segmenter cannot tell the target from the background")
    return None


def container_problem(data: bytes) -> str | None:
    """What is wrong with an image file's bytes before decoding, or None: empty, an unknown
    signature, a PNG without its IEND chunk or a JPEG without its end-of-image marker at the
    end (a truncated file is an error even where the decoder would fill in the rest, as
    OpenCV fills a truncated JPEG with gray)."""
    if not data:
        return "empty file; expected a PNG or JPEG image"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if not data.rstrip(b"\x00").endswith(_PNG_END):
            return f"truncated PNG ({len(data)} bytes, no IEND chunk at the end); re-copy or regenerate it"
    elif data[:2] == b"\xff\xd8":
        if b"\xff\xd9" not in data[-16:]:
            return f"truncated JPEG ({len(data)} bytes, no end-of-image marker); re-copy or regenerate it"
    else:
        return "not a PNG or JPEG file (unknown signature)"
    return None


def decode_bytes(data: bytes, flags: int | None = None):
    """``(image, None)`` or ``(None, error message)``: :func:`container_problem`, then
    OpenCV's decode, whose own refusals (a header claiming 60000 x 60000 pixels, corrupt data)
    become a message instead of a ``cv2.error``."""
    import cv2

    problem = container_problem(data)
    if problem:
        return None, problem
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if flags is None else flags)
    except cv2.error as exc:
        text = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else "decoder error"
        return None, f"cannot be decoded ({text}); re-copy or regenerate it"
    if img is None or img.size == 0:
        return None, "cannot be decoded (corrupt image data); re-copy or regenerate it"
    return img, None


def check_image_bytes(data: bytes, path: Path, *, seg: bool = False) -> tuple[tuple[int, int] | None, str | None]:
    """Force-decode one image: ``((H, W), None)`` or ``(None, error message)``
    (:func:`decode_bytes`); segmentation PNGs must be single-channel."""
    img, err = decode_bytes(data)
    if err:
        return None, err
    if seg and img.ndim != 2:
        return None, f"segmentation has shape {img.shape}; expected a single-channel (H, W) uint16 PNG"
    if not seg and img.ndim == 3 and img.shape[2] not in (3, 4):
        return None, f"image has {img.shape[2]} channels; expected an RGB image"
    return (int(img.shape[0]), int(img.shape[1])), None


def _decode_task(item: tuple[Path, bool, bool]):
    path, seg, want_hash = item
    try:
        data = path.read_bytes()
    except OSError as e:
        return path, None, f"cannot read ({e})", None, 0
    size, err = check_image_bytes(data, path, seg=seg) if seg is not None else (None, None)
    digest = sha256_hex(data) if want_hash else None
    return path, size, err, digest, len(data)


def load_file_hashes(root: Path, problems: list[Problem]) -> dict[Path, tuple[str, int | None]]:
    """sha256 (and size) per file from ``ROOT/manifest.json`` where it exists.

    Accepts ``{"files": {REL: {"sha256": H, "size": N}}}``, ``{"files": [{"path": REL,
    "sha256": H, ...}]}``, or the mapping itself; ``REL`` is relative to ROOT.
    """
    path = root / MANIFEST
    if not path.is_file():
        return {}
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        problems.append(Problem("unparseable_metadata", path, f"cannot read ({e}); expected JSON with sha256 per file"))
        return {}
    files = raw.get("files", raw) if isinstance(raw, dict) else raw
    out: dict[Path, tuple[str, int | None]] = {}
    items = files.items() if isinstance(files, dict) else (
        (f.get("path"), f) for f in files if isinstance(f, dict)) if isinstance(files, list) else ()
    for rel, entry in items:
        if not isinstance(rel, str):
            continue
        if isinstance(entry, str):
            out[root / rel] = (entry.lower(), None)
        elif isinstance(entry, dict) and isinstance(entry.get("sha256"), str):
            size = entry.get("size", entry.get("bytes"))
            out[root / rel] = (entry["sha256"].lower(), int(size) if isinstance(size, int) else None)
    return out


def validate(root: str | Path, *, decode_images: bool = True, workers: int = 2,
             check_hashes: bool = True, progress: bool = True) -> ValidationReport:
    """Check a dataset root and collect every problem without raising.

    Runs the reader's checks (names, annotations, 605 views per scene and target, one
    target per context, boxes inside the image, one image size), then with
    ``decode_images`` force-decodes every image and segmentation in ``workers`` threads
    (OpenCV releases the GIL while decoding), checking each one's size, and checks files
    against the sha256 in ``manifest.json`` where present.
    """
    from tqdm import tqdm

    manifest, problems = scan(root, check=True)
    root = manifest.root
    report = ValidationReport(root=root, manifest=manifest)
    by_scene: dict[str, list] = defaultdict(list)
    for r in manifest.records:
        if r.context is not None:
            by_scene[r.scene].append(r)
    for scene, recs in sorted(by_scene.items()):
        # segmentation is optional (the real release has none), but a scene that has some must
        # have all of it: else `prepare --method ibe_map` refuses what validate passed
        if any(r.seg is not None for r in recs):
            problem = segmentation_problem(manifest, scene, recs)
            if problem:
                problems.append(Problem("incomplete_segmentation", manifest.scene_dirs.get(scene, root), problem))
    hashes = load_file_hashes(root, problems) if check_hashes else {}
    if not decode_images and not hashes:
        report.problems = problems
        return report
    items: list[tuple[Path, bool | None, bool]] = []
    if decode_images:
        items += [(r.image, False, r.image in hashes) for r in manifest.records]
        items += [(r.seg, True, r.seg in hashes) for r in manifest.records if r.seg is not None]
    covered = {p for p, _, _ in items}
    # a missing scene is one problem (from the reader), not one per file it held
    gone = {root / p.path.name for p in problems if p.kind == "missing_scene"}
    items += [(p, None, True) for p in sorted(hashes) if p not in covered and not any(
        g in p.parents for g in gone)]
    # Sizes are judged after decoding: drop the reader's header-based verdict.
    problems = [p for p in problems if p.kind != "mixed_sizes" or not decode_images]
    sizes: dict[tuple[int, int], list[Path]] = defaultdict(list)
    with ThreadPoolExecutor(max(1, int(workers))) as pool:
        results = pool.map(_decode_task, items) if workers > 1 else map(_decode_task, items)
        for (path, kind, _), (_, size, err, digest, nbytes) in tqdm(
            zip(items, results, strict=True), total=len(items), desc="validate", unit="file",
            disable=not progress, leave=False,
        ):
            if err is not None:
                problems.append(Problem("truncated_image" if "truncated" in err else "unreadable_image", path, err))
            elif kind is not None:
                report.decoded += 1
                sizes[size].append(path)
            if path in hashes:
                want, want_size = hashes[path]
                report.hashed += 1
                if digest is not None and digest != want:
                    problems.append(Problem("hash_mismatch", path, f"sha256 {digest[:12]}... differs from "
                                            f"{want[:12]}... in {MANIFEST}; the file changed or is damaged"))
                elif want_size is not None and nbytes != want_size:
                    problems.append(Problem("hash_mismatch", path, f"{nbytes} bytes; {MANIFEST} says {want_size}"))
    if len(sizes) > 1:
        common = max(sizes, key=lambda s: (len(sizes[s]), s))
        for size, paths in sorted(sizes.items()):
            if size != common:
                problems.extend(Problem("mixed_sizes", p, f"image is {size[0]}x{size[1]} (HxW); expected "
                                        f"{common[0]}x{common[1]} like the other {len(sizes[common])} images")
                                for p in paths)
    report.problems = problems
    return report


def add_validate(parser: argparse.ArgumentParser):
    """``uevavd validate ROOT``: check a dataset root, print a report, exit 1 on problems."""
    parser.add_argument("root", type=Path, help="dataset root (UEVAVD layout, real or synthetic)")
    parser.add_argument("--max-per-kind", type=int, default=None, metavar="N",
                        help="list at most N problems of each kind; the report says how many were not "
                             "listed (default: list every problem)")
    parser.add_argument("--verbose", "-v", action="store_true",
                        help="list every problem, even with --max-per-kind (listing all is the default)")
    parser.add_argument("--no-decode", action="store_true", help="skip decoding images (names and annotations only)")
    parser.add_argument("--no-hashes", action="store_true", help="skip the sha256 check against manifest.json")
    parser.add_argument("--workers", type=int, default=2, help="decoding threads (default 2)")
    parser.add_argument("--json", type=Path, default=None, help="also write the summary and problems as JSON here")

    def handler(args) -> int:
        try:
            report = validate(args.root, decode_images=not args.no_decode, workers=args.workers,
                              check_hashes=not args.no_hashes)
        except FileNotFoundError as e:
            print(f"error: {e}")
            return 1
        print(report.format(verbose=args.verbose, per_kind=args.max_per_kind))
        if args.json is not None:
            _write_json(args.json, report)
        return 0 if report.ok else 1

    return handler


def _write_json(path: Path, report: ValidationReport) -> None:
    data = {**report.summary(), "problem_list": [
        {"kind": p.kind, "path": str(p.path), "message": p.message} for p in report.problems]}

    atomic_write_json(path, data)


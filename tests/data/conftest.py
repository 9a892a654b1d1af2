"""Hand-made UEVAVD-layout fixtures: tiny 8x8 images, the full 605 views per scene.

``variant_root`` spells every scene differently (names, separators, targets, image and
annotation formats) and ``broken_root`` has one defect per scene; both are built once per
session. :func:`write_scene` is exposed as the ``write_scene`` fixture for tests that
build their own small datasets.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import cv2
import numpy as np
import pytest

from uevavd.data.grid import N_VIEWS, view_coords
from uevavd.data.layout import view_stem

SIZE = 8


def encoded(ext: str = ".png", size: int = SIZE, seed: int = 0) -> bytes:
    """Bytes of a small RGB image in the format of ``ext``."""
    img = np.random.default_rng(seed).integers(0, 255, (size, size, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def box_for(view: int, size: int = SIZE) -> tuple[int, int, int, int]:
    """A valid box for a view, fully occluded for every ninth view."""
    if view % 9 == 0:
        return (0, 0, 0, 0)
    x1, y1 = view % 3, view % 2
    return (x1, y1, min(size, x1 + 2 + view % 4), min(size, y1 + 3 + view % 3))


def canonical(x, y, z, target, scene):
    return view_stem(x, y, z, target, scene)


def _box_json(view: int, box, label: str) -> object:
    kind = view % 4
    if kind == 0:
        return {"bbox": list(box)}
    if kind == 1:
        return {"box": list(box), "label": label}
    if kind == 2:
        return [list(box)]
    return {"xmin": box[0], "ymin": box[1], "xmax": box[2], "ymax": box[3]}


def _voc(name: str, box, label: str) -> str:
    if box == (0, 0, 0, 0):
        return f"<annotation><filename>{name}</filename></annotation>"
    x1, y1, x2, y2 = box
    return (f"<annotation><filename>{name}</filename><size><width>8</width><height>8</height></size>"
            f"<object><name>{label}</name><bndbox><xmin>{x1}</xmin><ymin>{y1}</ymin>"
            f"<xmax>{x2}</xmax><ymax>{y2}</ymax></bndbox></object></annotation>")


def write_scene(scene_dir: Path, *, target: str, token: str, name=canonical, ext: str = ".png",
                ann: str = "txt", size: int = SIZE, views=None, seed: int | None = None,
                label: str | None = None) -> dict[int, tuple[str, tuple]]:
    """Write one (scene, target) view set; returns view -> (file name, box).

    ``name(x, y, z, target, token)`` gives the stem; ``ann`` is one of "txt",
    "txt_label", "json", "xml", "csv", "csv_noheader", "table_txt", "table_json".
    ``seed`` shuffles the creation order.
    """
    scene_dir.mkdir(parents=True, exist_ok=True)
    data = encoded(ext if ext != ".jpeg" else ".jpg", size)
    views = list(range(N_VIEWS) if views is None else views)
    if seed is not None:
        random.Random(seed).shuffle(views)
    out: dict[int, tuple[str, tuple]] = {}
    rows = []
    for v in views:
        x, y, z = (int(c) for c in view_coords(v))
        stem = name(x, y, z, target, token)
        box = box_for(v, size)
        (scene_dir / (stem + ext)).write_bytes(data)
        out[v] = (stem + ext, box)
        lab = label or target
        if ann == "txt":
            (scene_dir / (stem + ".txt")).write_text(" ".join(map(str, box)) + "\n")
        elif ann == "txt_label":
            (scene_dir / (stem + ".txt")).write_text(f"{lab}," + ",".join(map(str, box)) + "\n")
        elif ann == "json":
            (scene_dir / (stem + ".json")).write_text(json.dumps(_box_json(v, box, lab)))
        elif ann == "xml":
            (scene_dir / (stem + ".xml")).write_text(_voc(stem + ext, box, lab))
        rows.append((stem + ext, box, lab))
    rows.sort()
    if ann == "csv":
        lines = ["image,x1,y1,x2,y2"] + [f"{n},{b[0]},{b[1]},{b[2]},{b[3]}" for n, b, _ in rows]
        (scene_dir / "annotations.csv").write_text("\n".join(lines) + "\n")
    elif ann == "csv_noheader":
        lines = [f"{n},{b[0]},{b[1]},{b[2]},{b[3]},{lab}" for n, b, lab in rows]
        (scene_dir / "boxes.csv").write_text("\n".join(lines) + "\n")
    elif ann == "table_txt":
        (scene_dir / "annotations.txt").write_text("".join(f"{n} {b[0]} {b[1]} {b[2]} {b[3]}\n" for n, b, _ in rows))
    elif ann == "table_json":
        (scene_dir / "annotations.json").write_text(json.dumps({n: {"bbox": list(b)} for n, b, _ in rows}))
    return out


# Each variant: (folder relative to ROOT, target, name function, image ext, annotation format)
VARIANTS = [
    ("urban/001", "sedan", canonical, ".png", "txt"),
    ("urban/2", "sportscar", lambda x, y, z, t, s: f"{x}_{y}_{z}_SportsCar_{s}", ".png", "json"),
    ("scene_003", "sportscar", lambda x, y, z, t, s: f"x{x}-y{y}-z{z}-Sports-Car-{s}", ".jpg", "xml"),
    ("context_4", "sportscar", lambda x, y, z, t, s: f"X{x:+d} Y{y:+d} Z{z:03d} sports car {s}", ".jpeg", "txt_label"),
    ("005", "suv", lambda x, y, z, t, s: f"{x}-{y}-{z}-SUV-{s}", ".png", "csv"),
    ("woods/006", "pickup", lambda x, y, z, t, s: f"x{x:+04d}_y{y:+04d}_z{z:04d}_Pick_up_{s}", ".png", "table_txt"),
    ("007", "hatchback", lambda x, y, z, t, s: f"x{x}_y{y}_z{z}_HatchBack_scene_{s}", ".png", "json"),
    ("8", "hatchback", lambda x, y, z, t, s: f"{x:+03d}_{y:+03d}_{z:03d}_hatchback", ".PNG", "table_json"),
    ("009", "hatchback", lambda x, y, z, t, s: f"{s}_hatch-back_{x}_{y}_{z}", ".png", "csv_noheader"),
]


@pytest.fixture(scope="session")
def write_scene_fn():
    return write_scene


@pytest.fixture(scope="session")
def variant_root(shared) -> tuple[Path, dict]:
    """(root, expected) with expected[(scene, target, view)] = (file name, box)."""
    return shared.once_with("variants", _write_variants)


def _write_variants(root: Path) -> dict:
    expected = {}
    for rel, target, name, ext, ann in VARIANTS:
        scene = Path(rel).name
        token = scene.split("_")[-1]
        got = write_scene(root / rel, target=target, token=token, name=name, ext=ext, ann=ann)
        expected.update({(scene, target, v): fb for v, fb in got.items()})
    for target in ("pickup", "sedan"):
        got = write_scene(root / "00", target=target, token="00")
        expected.update({("00", target, v): fb for v, fb in got.items()})
    got = write_scene(root / "train_605", target="suv", token="train_605")
    expected.update({("train_605", "suv", v): fb for v, fb in got.items()})
    # Segmentation, categories and visible fractions for scene 001.
    seg = np.arange(SIZE * SIZE, dtype=np.uint16).reshape(SIZE, SIZE) % 3
    ok, buf = cv2.imencode(".png", seg)
    seg_dir = root / "urban/001/seg"
    seg_dir.mkdir()
    visible = {}
    for (scene, _, v), (fname, _) in expected.items():
        if scene == "001":
            (seg_dir / fname).write_bytes(buf.tobytes())
            visible[Path(fname).stem] = round(v / N_VIEWS, 4)
    (seg_dir / "categories.json").write_text(json.dumps({"0": "none", "1": "target", "2": "building"}))
    (root / "urban/001/scene.json").write_text(json.dumps({"target": "sedan", "visible": visible}))
    return expected


@pytest.fixture(scope="session")
def broken_root(shared) -> tuple[Path, dict]:
    """(root, defects): scene 001 holds one of most defects (each on its own view), 002 a
    second target, 003 images of another size; defects[kind] = what the message must name."""
    root, defects = shared.once_with("broken", _write_broken)  # paths relative to root
    return root, {k: root / v if isinstance(v, Path) else v for k, v in defects.items()}


def _write_broken(root: Path) -> dict:
    d = root / "001"
    files = write_scene(d, target="sedan", token="001")
    defects: dict[str, Path | str] = {}

    def image(v):
        return d / files[v][0]

    def ann(v):
        return d / (Path(files[v][0]).stem + ".txt")

    # a missing view (image and annotation gone): named by its expected stem
    image(17).unlink()
    ann(17).unlink()
    defects["missing_views"] = Path(files[17][0]).stem
    # a truncated PNG (header intact, so only decoding finds it)
    image(5).write_bytes(image(5).read_bytes()[:40])
    defects["truncated_image"] = image(5)
    # a box outside the 8x8 image; an inverted box
    ann(10).write_text("2 2 9 7\n")
    defects["box_outside"] = image(10)
    ann(11).write_text("5 2 3 6\n")
    defects["box_inverted"] = image(11)
    # an unparseable name and an unknown target
    defects["unparseable_name"] = d / "x-50_y+40_sedan_001.png"
    defects["unknown_target"] = d / "x-50_y+40_z080_truck_001.png"
    for path in (defects["unparseable_name"], defects["unknown_target"]):
        path.write_bytes(encoded())
    # an unparseable annotation and a missing one
    ann(12).write_text("twelve 3 4\n")
    defects["unparseable_annotation"] = ann(12)
    ann(13).unlink()
    defects["missing_annotation"] = image(13)
    # coordinates off the grid
    defects["off_grid"] = d / "x-55_y+40_z080_sedan_001.png"
    defects["off_grid"].write_bytes(encoded())
    (d / "x-55_y+40_z080_sedan_001.txt").write_text("1 1 3 3\n")
    # a duplicate view (the same view again as .jpg)
    defects["duplicate_view"] = image(3).with_suffix(".jpg")
    defects["duplicate_view"].write_bytes(encoded(".jpg"))
    # a second target in a context scene
    write_scene(root / "002", target="sedan", token="002")
    write_scene(root / "002", target="suv", token="002", views=[0])
    defects["two_targets"] = root / "002"
    # images of another size (16x16, boxes still valid)
    write_scene(root / "003", target="sedan", token="003", size=16)
    defects["mixed_sizes"] = root / "003"
    return {k: v.relative_to(root) if isinstance(v, Path) else v for k, v in defects.items()}


@pytest.fixture(name="encoded")
def encoded_fixture():
    """:func:`encoded` for tests (importing ``conftest`` by name is ambiguous: each test
    folder has one)."""
    return encoded

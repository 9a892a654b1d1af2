"""The reader: variant names and annotation formats in, one ordered manifest out;
broken datasets rejected with messages naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from uevavd.data.annotations import (
    AnnotationError,
    parse_box_obj,
    parse_box_text,
    parse_voc_xml,
    read_annotation_table,
)
from uevavd.data.grid import N_VIEWS, coords_to_view
from uevavd.data.naming import NameParseError, normalize_target, parse_scene_dir, parse_view_stem
from uevavd.data.reader import DatasetError, Manifest, ViewRecord, image_size, read_dataset, scan
from uevavd.data.splits import TARGETS

# -- names ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "stem, xyz, target, scene",
    [
        ("x-50_y+40_z080_sedan_001", (-50, 40, 80), "sedan", "1"),
        ("-50_40_80_SportsCar_12", (-50, 40, 80), "sportscar", "12"),
        ("x-50-y40-z80-Sports-Car-12", (-50, 40, 80), "sportscar", "12"),
        ("-50-40-80-SUV-3", (-50, 40, 80), "suv", "3"),
        ("-50--40-80-suv", (-50, -40, 80), "suv", None),
        ("x50 y-40 z100 sports car 7", (50, -40, 100), "sportscar", "7"),
        ("X=-50_Y=40_Z=80_pickup_scene_3", (-50, 40, 80), "pickup", "3"),
        ("y+40_x-50_z080_Pick-up", (-50, 40, 80), "pickup", None),
        ("x-50y+40z080_sedan_00", (-50, 40, 80), "sedan", "0"),
        ("12_Hatch_Back_-50_40_80", (-50, 40, 80), "hatchback", "12"),
        ("x+00_y-00_z060_Sports_Car_train_605", (0, 0, 60), "sportscar", "train_605"),
    ],
)
def test_view_name_variants(stem, xyz, target, scene):
    p = parse_view_stem(stem)
    assert (p.xyz, p.target, p.scene) == (xyz, target, scene)


@pytest.mark.parametrize("stem, says", [
    ("x-50_y+40_z080_truck_001", "unknown target 'truck'"),
    ("1_2_sedan_3", "expected three coordinates"),
    ("x-50_y+40_x-40_sedan_001", "axis letters"),
    ("x-50_y+40_z080_001", "no target"),
    ("x-50_y+40_z080_sedan_001_002", "more than one scene id"),
])
def test_view_name_rejects(stem, says):
    with pytest.raises(NameParseError, match=says):
        parse_view_stem(stem)


@pytest.mark.parametrize("spelling", ["SportsCar", "Sports_Car", "sportscar", "sports car", "Sports-Car", "SPORTS CAR"])
def test_target_spellings(spelling):
    assert normalize_target(spelling) == "sportscar"
    assert normalize_target("SUV") == "suv" and normalize_target("Pick-up truck") == "pickup"


@pytest.mark.parametrize("name, kind, context", [
    ("001", "context", 1), ("1", "context", 1), ("scene_001", "context", 1), ("context_1", "context", 1),
    ("150", "context", 150), ("00", "unoccluded", None), ("train_605", "classifier", None),
])
def test_scene_folder_names(name, kind, context):
    sid = parse_scene_dir(name)
    assert (sid.kind, sid.context) == (kind, context)
    with pytest.raises(NameParseError, match="out of range"):
        parse_scene_dir("151")


# -- annotations -------------------------------------------------------------------------


def test_annotation_formats():
    assert parse_box_text("1 2 5 6").box == (1, 2, 5, 6)
    assert parse_box_text("1,2,5,6\n").box == (1, 2, 5, 6)
    a = parse_box_text("sedan 1.0 2 5 6")
    assert (a.box, a.label) == ((1, 2, 5, 6), "sedan")
    assert parse_box_text("[1, 2, 5, 6]").box == (1, 2, 5, 6)
    assert parse_box_obj({"bbox": [1, 2, 5, 6]}).box == (1, 2, 5, 6)
    assert parse_box_obj({"box": [1, 2, 5, 6], "label": "suv"}).label == "suv"
    assert parse_box_obj([1, 2, 5, 6]).box == (1, 2, 5, 6)
    assert parse_box_obj({"x1": 1, "y1": 2, "x2": 5, "y2": 6}).box == (1, 2, 5, 6)
    voc = "<annotation><object><name>suv</name><bndbox><xmin>1</xmin><ymin>2</ymin><xmax>5</xmax><ymax>6</ymax></bndbox></object></annotation>"
    assert parse_voc_xml(voc).box == (1, 2, 5, 6)
    assert parse_voc_xml("<annotation></annotation>").box == (0, 0, 0, 0)
    for bad in ("", "1 2 3", "a b c d", "1 2 3 4\n5 6 7 8"):
        with pytest.raises(AnnotationError, match="x1 y1 x2 y2|expected one box"):
            parse_box_text(bad, "f.txt")
    with pytest.raises(AnnotationError, match="not well-formed"):
        parse_voc_xml("<annotation><object>", "f.xml")


def test_table_rows_are_reported(tmp_path):
    t = tmp_path / "annotations.csv"
    t.write_text("image,x1,y1,x2,y2\na.png,1,2,3,4\nb.png,1,2,x,4\n")
    boxes, errors = read_annotation_table(t)
    assert boxes == {"a": boxes["a"]} and boxes["a"].box == (1, 2, 3, 4)
    assert len(errors) == 1 and "annotations.csv row 3" in errors[0]


# -- whole datasets ----------------------------------------------------------------------


def test_reads_every_variant(variant_root):
    root, expected = variant_root
    m = read_dataset(root)
    assert isinstance(m, Manifest) and len(m) == len(expected)
    assert m.image_size == (8, 8)
    got = {(r.scene, r.target, r.view): (r.image.name, r.box) for r in m}
    assert got == expected
    assert m.scenes() == ["001", "2", "scene_003", "context_4", "005", "006", "007", "8", "009", "00", "train_605"]
    assert m.contexts() == {1: "sedan", 2: "sportscar", 3: "sportscar", 4: "sportscar", 5: "suv",
                            6: "pickup", 7: "hatchback", 8: "hatchback", 9: "hatchback"}
    for r in m:
        assert isinstance(r, ViewRecord)
        assert coords_to_view(*r.xyz) == r.view and r.target in TARGETS
        assert r.split == ("train" if r.context else None)


def test_order_is_scene_target_view(variant_root):
    m = read_dataset(variant_root[0])
    scene_rank = {s: i for i, s in enumerate(m.scenes())}
    keys = [(scene_rank[r.scene], TARGETS.index(r.target), r.view) for r in m]
    assert keys == sorted(keys) and len(set(keys)) == len(keys)
    assert [r.target for r in m.select(scenes="00")][:: N_VIEWS] == ["pickup", "sedan"]


def test_manifest_arrays_and_select(variant_root):
    m = read_dataset(variant_root[0])
    boxes, views = m.boxes(), m.views()
    assert boxes.shape == (len(m), 4) and boxes.dtype == np.int32
    assert views.dtype == np.int64 and views.max() == N_VIEWS - 1
    assert not boxes.flags.writeable
    assert m.occluded().sum() == sum(1 for r in m if r.box == (0, 0, 0, 0)) > 0
    sub = m.select(targets=["Sports Car"])
    assert {r.target for r in sub} == {"sportscar"} and len(sub) == 3 * N_VIEWS
    assert len(m.select(split="train")) == 9 * N_VIEWS
    assert len(m.select(split="test")) == 0
    assert len(m.select(contexts=[1, 7])) == 2 * N_VIEWS
    i = m.index("001", "sedan", 42)
    assert m[i].view == 42 and m[i].scene == "001"
    with pytest.raises(ValueError, match="unknown scene"):
        m.select(scenes=["077"])


def test_segmentation_categories_and_visible(variant_root):
    m = read_dataset(variant_root[0])
    s1 = m.select(scenes=["001"])
    assert all(r.seg is not None and r.seg.parent.name == "seg" for r in s1)
    assert all(r.seg is None for r in m.select(scenes=["005"]))
    assert m.categories("001") == {0: "none", 1: "target", 2: "building"}
    assert m.categories("005") is None
    vis = s1.visible()
    assert vis.dtype == np.float32 and np.allclose(vis, np.round(s1.views() / N_VIEWS, 4))
    assert np.isnan(m.select(scenes=["005"]).visible()).all()


def test_order_ignores_creation_order(tmp_path, write_scene_fn):
    manifests = []
    for seed in (1, 2):
        root = tmp_path / f"r{seed}"
        order = ["012", "3", "00"] if seed == 1 else ["00", "3", "012"]
        for tok in order:
            targets = ["suv", "pickup"] if tok == "00" else ["suv"]
            for t in (targets if seed == 1 else targets[::-1]):
                write_scene_fn(root / tok, target=t, token=tok, seed=seed, views=range(0, N_VIEWS, 5))
        m = read_dataset(root, check=False)  # a fifth of the views: skip the count check
        assert m.problems == ()
        manifests.append(m)
    a, b = ([(r.scene, r.target, r.view, r.image.name, r.box) for r in m] for m in manifests)
    assert a == b
    assert [s for s in manifests[0].scenes()] == ["3", "012", "00"]


def test_broken_dataset_names_every_file(broken_root):
    root, defects = broken_root
    with pytest.raises(DatasetError) as info:
        read_dataset(root)
    err = info.value
    by_kind = {}
    for p in err.problems:
        by_kind.setdefault(p.kind, []).append(p)
    for kind, where in defects.items():
        if kind == "truncated_image":
            continue  # the header is intact: only decoding (validate) finds it
        assert kind in by_kind, f"{kind} not reported; got {sorted(by_kind)}"
        text = " | ".join(str(p) for p in by_kind[kind])
        assert str(where) in text, f"{kind}: {where} not named in {text}"
        assert str(where) in str(err)
    missing = by_kind["missing_views"][0]
    assert missing.path == root / "001" and "604 of 605" in missing.message
    assert "leaves the 8x8 image" in str(by_kind["box_outside"][0])
    assert "x2 > x1" in str(by_kind["box_inverted"][0])
    assert "expected exactly one target" in str(by_kind["two_targets"][0])
    # Without checks the reader returns what parsed and keeps the problems.
    m = read_dataset(root, check=False)
    assert len(m) > 2 * N_VIEWS and m.problems


def test_missing_and_damaged_pieces(tmp_path, write_scene_fn):
    files = write_scene_fn(tmp_path / "001", target="sedan", token="001")
    read_dataset(tmp_path)  # clean
    name = files[300][0]
    ann = tmp_path / "001" / (Path(name).stem + ".txt")
    ann.write_text("3 3 3 5\n")
    with pytest.raises(DatasetError, match=str(tmp_path / "001" / name).replace("+", r"\+")):
        read_dataset(tmp_path)
    ann.unlink()
    with pytest.raises(DatasetError, match="no box annotation"):
        read_dataset(tmp_path)
    (tmp_path / "001" / "annotations.json").write_text(json.dumps({name: [1, 1, 4, 4]}))
    assert read_dataset(tmp_path).select(scenes="001")[300].box == (1, 1, 4, 4)


def test_scene_mismatch_and_unknown_folder(tmp_path, write_scene_fn):
    write_scene_fn(tmp_path / "001", target="sedan", token="002")
    write_scene_fn(tmp_path / "misc", target="sedan", token="003", views=[0])
    problems = scan(tmp_path)[1]
    kinds = {p.kind for p in problems}
    assert {"scene_mismatch", "unknown_scene"} <= kinds
    assert any(p.path == tmp_path / "misc" for p in problems)
    with pytest.raises(FileNotFoundError, match="not a folder"):
        read_dataset(tmp_path / "nowhere")


def test_a_root_whose_scene_named_folders_hold_no_views_says_no_scenes(tmp_path):
    """A folder that is not a dataset but holds a folder named like a scene (``/etc`` has
    ``postgresql/15``): the report says no scene holds a view, naming the folder it took for
    one, not just that a subfolder was not read."""
    (tmp_path / "postgresql" / "15" / "main").mkdir(parents=True)
    (tmp_path / "hosts").write_text("127.0.0.1 localhost\n")
    manifest, problems = scan(tmp_path)
    assert len(manifest.records) == 0
    no_scenes = [p for p in problems if p.kind == "no_scenes"]
    assert len(no_scenes) == 1 and no_scenes[0].path == tmp_path
    assert str(tmp_path / "postgresql" / "15") in no_scenes[0].message


def test_files_the_reader_cannot_use_are_named(tmp_path, write_scene_fn, encoded, caplog):
    files = write_scene_fn(tmp_path / "001", target="sedan", token="001")
    d = tmp_path / "001"
    # obvious non-data files: never reported
    for name in ("README.md", "readme.txt", "LICENSE", "scene.json", ".DS_Store", ".hidden.txt", "Thumbs.db"):
        (d / name).write_text("{}")
    (d / "seg").mkdir()
    (d / "seg" / "notes.bin").write_text("x")
    (tmp_path / "manifest.json").write_text("{}")
    (tmp_path / "uevavd.json").write_text("{}")
    manifest, problems = scan(tmp_path)
    assert problems == [] and len(manifest) == N_VIEWS
    # an annotation whose image is gone; an annotation whose name does not parse; unknown types
    stem = Path(files[7][0]).stem
    (d / files[7][0]).rename(d / (stem + ".bmp"))
    (d / "x-50_y+40_sedan_001.json").write_text("[1, 1, 3, 3]")
    (d / "notes.docx").write_bytes(b"PK")
    (d / "boxes_v2.csv").write_text("image,x1,y1,x2,y2\n")
    (d / "labels").mkdir()
    (d / "labels" / "annotations.csv").write_text("image,x1,y1,x2,y2\n")
    (d / "labels" / "x-15_y+10_z070_sedan_001.xml").write_text("<annotation/>")
    (d / "extra").mkdir()
    kept = next(fb for fb in files.values() if fb[0] == "x+50_y+50_z100_sedan_001.png")
    (d / "annotations.csv").write_text("image,x1,y1,x2,y2\nx+50_y+50_z100_sedan_001.png," + ",".join(map(str, kept[1]))
                                      + "\ngarbage.png,1,1,3,3\n")
    problems = scan(tmp_path)[1]
    got = {(p.kind, p.path) for p in problems}
    expected = {
        ("orphan_annotation", d / (stem + ".txt")),
        ("unknown_file", d / (stem + ".bmp")),
        ("unparseable_annotation_name", d / "x-50_y+40_sedan_001.json"),
        ("unknown_file", d / "notes.docx"),
        ("unknown_file", d / "boxes_v2.csv"),
        ("unknown_file", d / "labels" / "annotations.csv"),
        ("orphan_annotation", d / "labels" / "x-15_y+10_z070_sedan_001.xml"),
        ("unknown_file", d / "extra"),
        ("unparseable_annotation_name", d / "annotations.csv"),  # row 'garbage'
        ("missing_views", d),  # the view whose image became a .bmp
    }
    assert got == expected, sorted(got ^ expected)
    msgs = {p.kind: p.message for p in problems}
    assert "without its image" in msgs["orphan_annotation"] and ".png" in msgs["unknown_file"] + str(problems)
    rows = [p for p in problems if p.path == d / "annotations.csv"]
    assert "garbage" in rows[0].message
    # the row for an existing image agrees with its .txt: no orphan and no conflict is reported for it
    assert not any("x+50_y+50_z100" in p.message for p in problems)
    # read_dataset raises for the missing view, and lists the unused files with it
    with pytest.raises(DatasetError, match="notes.docx"):
        read_dataset(tmp_path)
    # unused files alone are logged, not raised: the views read are complete
    (d / (stem + ".bmp")).rename(d / files[7][0])
    with caplog.at_level("WARNING", logger="uevavd.data.reader"):
        m = read_dataset(tmp_path)
    assert len(m) == N_VIEWS and "not used" in caplog.text and "uevavd validate" in caplog.text
    assert {p.kind for p in m.problems} == {"unknown_file", "unparseable_annotation_name", "orphan_annotation"}


def test_image_size_from_header(tmp_path, encoded):
    for ext in (".png", ".jpg"):
        f = tmp_path / f"a{ext}"
        f.write_bytes(encoded(ext, 16))
        assert image_size(f) == (16, 16)
    bad = tmp_path / "b.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="b.png"):
        image_size(bad)


def test_copy_reads_the_same(variant_root, tmp_path):
    """Moving a dataset keeps its manifest (paths are relative to the root)."""
    src, _ = variant_root
    dst = tmp_path / "copy"
    shutil.copytree(src / "urban", dst / "urban")
    a = read_dataset(src).select(scenes=["001", "2"])
    b = read_dataset(dst)
    assert [(r.scene, r.view, r.image.relative_to(src), r.box) for r in a] == [
        (r.scene, r.view, r.image.relative_to(dst), r.box) for r in b]


# -- round trip with the synthetic writer --------------------------------------------------


def _check_round_trip(root: Path, m: Manifest) -> None:
    for scene in m.scenes():
        folder = m.scene_dirs[scene]
        meta = json.loads((folder / "scene.json").read_text())
        cats = json.loads((folder / "seg" / "categories.json").read_text())
        assert m.categories(scene) == {int(k): v for k, v in cats.items()}
        sub = m.select(scenes=[scene])
        assert len(sub) == N_VIEWS * len(meta["targets"])
        for r in sub:
            assert r.image.parent == folder and r.image.exists() and r.seg.exists()
            assert r.box == tuple(map(int, r.image.with_suffix(".txt").read_text().split()))
            assert r.visible == pytest.approx(meta["visible"][r.image.stem], abs=1e-6)
            assert r.context == meta["context"]
            assert r.split == (meta["split"] if r.context is not None else None)
            assert r.target in meta["targets"]


def test_synthetic_round_trip(synthetic_root):
    m = read_dataset(synthetic_root)
    meta = json.loads((synthetic_root / "026" / "scene.json").read_text())
    assert m.scenes() == ["026"] and m.contexts() == {26: meta["target"]}
    assert m.image_size == (16, 16) and meta["split"] == "hard" == m[0].split
    assert np.array_equal(m.views(), np.arange(N_VIEWS))
    _check_round_trip(synthetic_root, m)
    # Boxes of visible targets are real boxes, occluded views are exactly the invisible ones.
    assert np.array_equal(m.occluded(), m.visible() == 0)


@pytest.mark.slow
def test_synthetic_round_trip_with_unoccluded_scenes(tmp_path):
    from uevavd.data.synthetic import write_world

    write_world(tmp_path, contexts=[1, 150], size=16, seed=2, progress=False)
    m = read_dataset(tmp_path)
    assert m.scenes() == ["001", "150", "00", "train_605"]
    assert len(m) == 2 * N_VIEWS + 2 * len(TARGETS) * N_VIEWS
    assert [r.target for r in m.select(scenes="train_605")][::N_VIEWS] == list(TARGETS)
    _check_round_trip(tmp_path, m)


def test_an_unchecked_read_of_a_clean_checked_root_is_served_from_memory(tmp_path, write_scene_fn, monkeypatch):
    from uevavd.data import reader

    write_scene_fn(tmp_path / "001", target="sedan", token="001")
    checked = read_dataset(tmp_path)
    monkeypatch.setattr(reader, "scan", lambda *a, **k: pytest.fail("scanned again"))
    assert read_dataset(tmp_path, check=False) is checked


def test_a_second_read_sees_every_change(tmp_path, write_scene_fn):
    """read_dataset serves an unchanged root from memory; any change under it is read."""
    files = write_scene_fn(tmp_path / "001", target="sedan", token="001")
    first = read_dataset(tmp_path)
    assert read_dataset(tmp_path) is first  # unchanged: the same (immutable) manifest
    stem = Path(files[300][0]).stem
    ann = tmp_path / "001" / (stem + ".txt")
    old = ann.read_text()
    new = "1 1 4 4\n"
    ann.write_text(new)  # edited in place
    assert read_dataset(tmp_path).select(scenes="001")[300].box == (1, 1, 4, 4)
    ann.unlink()
    with pytest.raises(DatasetError, match="no box annotation"):
        read_dataset(tmp_path)
    ann.write_text(old)
    assert read_dataset(tmp_path).select(scenes="001")[300].box == first.select(scenes="001")[300].box
    relative = read_dataset(tmp_path)
    assert read_dataset(tmp_path, check=False).records == relative.records


def test_second_annotations_must_agree(tmp_path, write_scene_fn):
    files = write_scene_fn(tmp_path / "001", target="sedan", token="001")  # .txt beside every image
    d = tmp_path / "001"
    (a_name, a_box), (b_name, b_box), (c_name, c_box) = files[10], files[20], files[30]
    a, b, c = (Path(n).stem for n in (a_name, b_name, c_name))
    # agreeing duplicates are fine: a .json and a table row giving the .txt's box
    (d / (a + ".json")).write_text(json.dumps(list(a_box)))
    (d / "annotations.csv").write_text(f"image,x1,y1,x2,y2\n{a_name}," + ",".join(map(str, a_box)) + "\n")
    assert scan(tmp_path)[1] == []
    # a VOC file in labels/ that moves the box, a table row that does, a .json that does not parse
    moved = (b_box[0] + 1, *b_box[1:])
    (d / "labels").mkdir()
    (d / "labels" / (b + ".xml")).write_text(
        "<annotation><object><name>sedan</name><bndbox><xmin>{}</xmin><ymin>{}</ymin><xmax>{}</xmax>"
        "<ymax>{}</ymax></bndbox></object></annotation>".format(*moved))
    (d / "annotations.csv").write_text(f"image,x1,y1,x2,y2\n{a_name},0,0,0,0\n")
    (d / (c + ".json")).write_text("{not json")
    problems = scan(tmp_path)[1]
    conflicts = {p.path: p.message for p in problems if p.kind == "conflicting_annotation"}
    assert set(conflicts) == {d / "labels" / (b + ".xml"), d / "annotations.csv", d / (c + ".json")}
    assert str(moved) in conflicts[d / "labels" / (b + ".xml")] and str(b_box) in conflicts[d / "labels" / (b + ".xml")]
    assert b + ".txt" in conflicts[d / "labels" / (b + ".xml")]
    assert repr(a_name) in conflicts[d / "annotations.csv"] and "(0, 0, 0, 0)" in conflicts[d / "annotations.csv"]
    assert "cannot be parsed" in conflicts[d / (c + ".json")]
    with pytest.raises(DatasetError, match="conflicting_annotation|disagree|prefers"):
        read_dataset(tmp_path)
    # without checks the preferred .txt is used and the others are not read
    m = read_dataset(tmp_path, check=False)
    boxes = {r.image.name: r.box for r in m}
    assert boxes[a_name] == a_box and boxes[b_name] == b_box and boxes[c_name] == c_box


def test_an_odd_sized_first_image_is_named_not_the_healthy_ones(tmp_path):
    """The reader read the size from a scene's first image only: a wrong-sized first image
    made every healthy file's box look outside the image (375 false box_outside), and the
    odd file was never named."""
    import cv2

    from uevavd.data.reader import scan
    from uevavd.testing.worlds import write_tiny_world

    root = write_tiny_world(tmp_path / "w", contexts=(1,), train605=False)
    first = sorted(p for p in (root / "001").iterdir() if p.suffix == ".png")[0]
    cv2.imwrite(str(first), np.zeros((20, 20, 3), np.uint8))
    _, problems = scan(root)
    kinds = [p.kind for p in problems]
    assert "box_outside" not in kinds
    assert [p.path for p in problems if p.kind == "mixed_sizes"] == [first]


def test_self_links_in_a_dataset_root_are_walked_once(tmp_path, monkeypatch):
    """`ln -s . D/a; ln -s a D/027` made the tree signature walk D/a/a/a/... to the longest
    path the OS takes (minutes in `prepare`); each folder is walked once now."""
    import os

    from uevavd.data import reader
    from uevavd.testing.worlds import write_tiny_world

    root = write_tiny_world(tmp_path / "w", contexts=(1,), train605=False)
    (root / "a").symlink_to(".")
    (root / "027").symlink_to("a")
    real_dirs = sum(1 for _, dirs, _ in os.walk(root) for _ in dirs) + 1
    calls = []
    scandir = os.scandir

    def counting(path):
        calls.append(path)
        assert len(calls) <= real_dirs + 2, f"walked {len(calls)} folders, e.g. {calls[-1]}"
        return scandir(path)

    monkeypatch.setattr(reader.os, "scandir", counting)
    reader._tree_signature(root)
    assert len(calls) <= real_dirs

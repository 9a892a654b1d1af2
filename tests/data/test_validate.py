"""`validate` and `uevavd validate`: decode every image, report every problem by file."""

from __future__ import annotations

import hashlib
import json

import pytest

from uevavd.cli import main
from uevavd.data.grid import N_VIEWS
from uevavd.data.validate import check_image_bytes, validate


def test_clean_variants_validate(variant_root):
    root, expected = variant_root
    report = validate(root, progress=False)
    assert report.ok, report.format()
    assert report.decoded == len(expected) + N_VIEWS  # images + scene 001's segmentations
    s = report.summary()
    assert s["splits"]["train"] == {"contexts": 9, "views": 9 * N_VIEWS}
    assert s["targets"]["sportscar"] == [2, 3, 4]
    occluded = sum(1 for _, box in expected.values() if box == (0, 0, 0, 0)) / len(expected)
    assert s["occluded"]["all"] == pytest.approx(occluded)
    assert set(s["occluded"]) == {"all", "train", "00", "train_605"}


def test_truncated_png_named(broken_root):
    root, defects = broken_root
    report = validate(root, progress=False)
    assert not report.ok
    truncated = [p for p in report.problems if p.kind == "truncated_image"]
    assert [p.path for p in truncated] == [defects["truncated_image"]]
    assert "truncated PNG" in truncated[0].message
    # Every reader defect is still reported, each naming its file.
    text = "\n".join(str(p) for p in report.problems)
    for kind, where in defects.items():
        assert str(where) in text, kind
    # Size is judged per decoded file: each 16x16 image of scene 003 is named.
    mixed = [p for p in report.problems if p.kind == "mixed_sizes"]
    assert len(mixed) == N_VIEWS and all(p.path.parent == root / "003" for p in mixed)


def test_check_image_bytes(encoded):
    png, jpg = encoded(".png"), encoded(".jpg")
    assert check_image_bytes(png, None) == ((8, 8), None)
    assert check_image_bytes(jpg, None) == ((8, 8), None)
    assert "truncated PNG" in check_image_bytes(png[:-20], None)[1]
    assert "truncated JPEG" in check_image_bytes(jpg[: len(jpg) // 2], None)[1]
    assert "empty" in check_image_bytes(b"", None)[1]
    assert "signature" in check_image_bytes(b"GIF89a....", None)[1]
    # A PNG whose end survived but whose middle is garbage does not decode.
    damaged = png[:40] + bytes(len(png) - 52) + png[-12:]
    assert "cannot be decoded" in check_image_bytes(damaged, None)[1]
    assert "single-channel" in check_image_bytes(png, None, seg=True)[1]


def test_hashes_from_manifest_json(tmp_path, write_scene_fn):
    files = write_scene_fn(tmp_path / "001", target="suv", token="001")
    entries = {}
    for name, _ in files.values():
        rel = f"001/{name}"
        entries[rel] = {"sha256": hashlib.sha256((tmp_path / rel).read_bytes()).hexdigest(),
                        "size": (tmp_path / rel).stat().st_size}
    txt = "001/" + files[0][0].replace(".png", ".txt")
    entries[txt] = {"sha256": "0" * 64, "size": 8}  # annotation recorded with a wrong hash
    (tmp_path / "manifest.json").write_text(json.dumps({"files": entries}))
    report = validate(tmp_path, progress=False)
    assert report.hashed == N_VIEWS + 1
    assert [(p.kind, p.path) for p in report.problems] == [("hash_mismatch", tmp_path / txt)]
    assert validate(tmp_path, check_hashes=False, progress=False).ok


def test_cli_clean_and_broken(variant_root, broken_root, capsys, tmp_path):
    assert main(["validate", str(variant_root[0]), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    for line in ("image size  8 x 8", "sportscar", "train", "occluded", "no problems", "partial release"):
        assert line in out
    code = main(["validate", str(broken_root[0]), "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert code == 1
    assert "PROBLEMS" in out and "truncated_image (1)" in out and "two_targets (1)" in out
    assert str(broken_root[1]["box_outside"]) in out
    # every problem is listed by default: all 605 mixed-size files
    assert "not listed" not in out and out.count("\n    ") == len(broken_root_problems(tmp_path / "r.json"))
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["problems"]["mixed_sizes"] == N_VIEWS and len(data["problem_list"]) == sum(data["problems"].values())
    assert all(p["path"] in out for p in data["problem_list"])
    # a cap says how many it left out and how to see them
    assert main(["validate", str(broken_root[0]), "--max-per-kind", "20"]) == 1
    out = capsys.readouterr().out
    hidden = N_VIEWS - 20
    assert f"({hidden} not listed: at most 20 per kind; omit --max-per-kind to list all)" in out
    assert f"... {hidden} more mixed_sizes not listed" in out
    assert main(["validate", str(broken_root[0]), "--no-decode", "--max-per-kind", "20", "--verbose"]) == 1
    out = capsys.readouterr().out
    assert "not listed" not in out and "truncated_image" not in out
    assert main(["validate", str(tmp_path / "absent")]) == 1


def broken_root_problems(report_json):
    return json.loads(report_json.read_text())["problem_list"]


def test_synthetic_world_validates_and_hashes(synthetic_root, tmp_path):
    import shutil

    report = validate(synthetic_root, progress=False)
    assert report.ok, report.format()
    listed = json.loads((synthetic_root / "manifest.json").read_text())["files"]
    assert report.hashed == len(listed) and report.decoded == 2 * N_VIEWS
    assert report.summary()["splits"]["hard"] == {"contexts": 1, "views": N_VIEWS}
    # A changed byte inside one PNG's pixel data: caught by the hash, named by path.
    root = tmp_path / "copy"
    shutil.copytree(synthetic_root, root)
    victim = sorted((root / "026").glob("*.png"))[7]
    data = bytearray(victim.read_bytes())
    data[60] ^= 0xFF
    victim.write_bytes(bytes(data))
    problems = validate(root, progress=False).problems
    assert victim in {p.path for p in problems if p.kind == "hash_mismatch"}
    assert all(p.path == victim for p in problems)


def test_a_listed_scene_folder_that_is_missing_is_named_once(synthetic_root, tmp_path, capsys):
    """The dataset card and manifest.json list scene 026: without its folder, read_dataset
    (and so prepare and ablate --data) refuses the root naming the scene, and validate says
    so once instead of a line per missing file (it used to drop the scene silently)."""
    import shutil

    from uevavd.data.reader import DatasetError, read_dataset

    root = tmp_path / "copy"
    shutil.copytree(synthetic_root, root)
    (root / "027").mkdir()  # an empty second scene keeps the root a dataset
    shutil.rmtree(root / "026")
    with pytest.raises(DatasetError, match="scene 026 is listed in uevavd.json but its folder is missing"):
        read_dataset(root)
    problems = validate(root, progress=False).problems
    assert [p.kind for p in problems].count("missing_scene") == 1
    assert not [p for p in problems if "026" in str(p.path) and p.kind != "missing_scene"]


def test_validate_and_prepare_agree_on_incomplete_segmentation(synthetic_root, tmp_path):
    """A scene whose seg/categories.json is missing (or some of whose seg PNGs are): validate
    used to pass it while `prepare --method ibe_map` refused it; both now name the file."""
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(synthetic_root, root)
    (root / "026" / "seg" / "categories.json").unlink()
    manifest_path = root / "manifest.json"
    listed = json.loads(manifest_path.read_text())
    listed["files"].pop("026/seg/categories.json")  # keep the hash check out of it
    manifest_path.write_text(json.dumps(listed))
    problems = validate(root, progress=False).problems
    seg = [p for p in problems if p.kind == "incomplete_segmentation"]
    assert len(seg) == 1 and "categories.json is missing" in seg[0].message

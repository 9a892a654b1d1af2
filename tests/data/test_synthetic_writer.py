"""The synthetic world's writer: layout, determinism, resume, manifest, CLI."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from uevavd.cli import main
from uevavd.data import layout
from uevavd.data.grid import N_VIEWS, view_coords
from uevavd.data.synthetic import render_context, write_world
from uevavd.data.synthetic.cli import parse_contexts
from uevavd.data.synthetic.writer import scene_complete, write_scene

SIZE = 16  # the smallest crop: the writer's behaviour does not depend on the size


def _tree_bytes(root: Path) -> dict[str, bytes]:
    """The dataset's files (a scene's hidden check stamp holds file times, not data)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.startswith(".")}


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("world")
    rc = main(["synth", "--out", str(out), "--contexts", "5", "--size", str(SIZE), "--seed", "3",
               "--no-unoccluded", "--quiet"])
    assert rc == 0
    return out


def test_layout_and_annotations(world):
    folder = world / "005"
    meta = json.loads((folder / layout.SCENE_META).read_text())
    assert (meta["scene"], meta["context"], meta["split"], meta["target"], meta["terrain"]) == (
        "005", 5, "train", "hatchback", "urban")
    assert meta["placement"] == "training" and meta["draw"] == 0 and "visible >= 0.9" in meta["validity"]
    assert (meta["size"], meta["seed"]) == (SIZE, 3)
    assert len(meta["visible"]) == N_VIEWS
    stem = layout.view_stem(-50, 40, 80, "hatchback", "005")
    rgb = cv2.imread(str(folder / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
    assert rgb.shape == (SIZE, SIZE, 3) and rgb.dtype == np.uint8
    seg = cv2.imread(str(folder / layout.SEG_DIR / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
    assert seg.shape == (SIZE, SIZE) and seg.dtype == np.uint16
    cats = json.loads((folder / layout.SEG_DIR / layout.CATEGORIES).read_text())
    target_ids = [int(k) for k, v in cats.items() if v == "target"]
    assert target_ids == [1]
    x1, y1, x2, y2 = map(int, (folder / f"{stem}.txt").read_text().split())
    mask = seg == 1
    if mask.any():
        ys, xs = np.nonzero(mask)
        assert [x1, y1, x2, y2] == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
        assert meta["visible"][stem] > 0
    else:
        assert [x1, y1, x2, y2] == [0, 0, 0, 0] and meta["visible"][stem] == 0
    assert set(np.unique(seg).tolist()) <= {int(k) for k in cats}


def test_manifest_covers_every_file(world):
    manifest = json.loads((world / layout.MANIFEST).read_text())["files"]
    on_disk = {k for k in _tree_bytes(world) if k != layout.MANIFEST}
    assert set(manifest) == on_disk
    for rel in list(manifest)[:50] + [layout.DATASET_CARD, f"005/{layout.SCENE_META}"]:
        data = (world / rel).read_bytes()
        assert manifest[rel] == {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}
    card = json.loads((world / layout.DATASET_CARD).read_text())
    assert card["contexts"] == [5] and card["size"] == SIZE


def test_same_seed_and_context_give_identical_files(world, tmp_path):
    again = write_world(tmp_path / "again", contexts=[5], size=SIZE, seed=3, include_unoccluded=False,
                        progress=False)
    assert _tree_bytes(again) == _tree_bytes(world)


def test_render_context_matches_the_written_files(world):
    views = render_context(5, size=SIZE, seed=3)
    assert views.rgb.shape == (N_VIEWS, SIZE, SIZE, 3) and views.boxes.dtype == np.int32
    meta = json.loads((world / "005" / layout.SCENE_META).read_text())
    assert np.allclose(views.visible, list(meta["visible"].values()), atol=1e-6)
    assert (views.boxes[views.visible == 0] == 0).all()


def test_resume_redoes_only_broken_scenes(world, tmp_path):
    out = tmp_path / "w"
    shutil.copytree(world, out)
    (out / "006").mkdir()
    shutil.copytree(world / "005", out / "006", dirs_exist_ok=True)  # a scene 006 from another context
    folder = out / "005"
    a_file = sorted(folder.glob("*.png"))[0]
    stamp = a_file.stat().st_mtime_ns
    victim = sorted(folder.glob("*.png"))[5]
    original = victim.read_bytes()
    victim.write_bytes(original[:-7])  # a truncated file, as an interrupted run would leave
    box_file = sorted(folder.glob("*.txt"))[3]
    box_file.unlink()
    assert not scene_complete(folder, size=SIZE, seed=3)
    assert scene_complete(out / "006", size=SIZE, seed=3)
    assert not scene_complete(out / "006", size=SIZE + 1, seed=3)
    assert not scene_complete(out / "006", size=SIZE, seed=4)
    write_world(out, contexts=[5], size=SIZE, seed=3, include_unoccluded=False, progress=False)
    assert victim.read_bytes() == original and box_file.is_file()
    assert scene_complete(folder, size=SIZE, seed=3)
    assert _tree_bytes(out / "005") == _tree_bytes(world / "005")
    # a complete scene is skipped, not rewritten
    stamp = a_file.stat().st_mtime_ns
    write_world(out, contexts=[5], size=SIZE, seed=3, include_unoccluded=False, progress=False)
    assert a_file.stat().st_mtime_ns == stamp


def test_a_world_with_other_settings_is_refused(world, tmp_path):
    out = tmp_path / "w"
    out.mkdir()
    shutil.copy(world / layout.DATASET_CARD, out / layout.DATASET_CARD)
    with pytest.raises(ValueError, match="size=16, seed=3"):
        write_world(out, contexts=[5], size=SIZE, seed=1, include_unoccluded=False, progress=False)


def test_parse_contexts():
    assert parse_contexts("1-4,21,26") == [1, 2, 3, 4, 21, 26]
    assert parse_contexts(" 7 , 7,8-8") == [7, 8]
    for bad in ("0", "151", "4-1", "a", ","):
        with pytest.raises(ValueError):
            parse_contexts(bad)


def test_cli_reports_bad_input(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path / "w"), "--contexts", "0-3", "--quiet"]) == 2
    assert "context id 0 is out of range" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("args, needle", [
    (["--contexts", ""], "names no context"),  # used to render the preset's 30
    (["--contexts", "1", "--seed", "-1"], "--seed -1: expected a world seed >= 0"),  # said so after making the folder
    (["--contexts", "1", "--workers", "0"], "--workers 0: expected at least 1"),
])
def test_cli_refuses_empty_contexts_negative_seeds_and_no_workers_before_writing(tmp_path, capsys, args, needle):
    assert main(["synth", "--out", str(tmp_path / "w"), "--quiet", *args]) == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


SYNTH_HOLDER = """
import sys, time
from pathlib import Path
from filelock import FileLock
from uevavd.data.synthetic.writer import _write_world
out = Path(sys.argv[1])
with FileLock(str(out.parent / f".{out.name}.lock")):  # a synth of seed 0, holding the folder
    Path(sys.argv[2]).touch()
    time.sleep(1.0)
    _write_world(out, [1], 16, 0, False, 1, False)
"""


def test_a_second_synth_into_the_same_folder_waits_then_checks_the_seed(tmp_path, capsys, monkeypatch):
    """Two `uevavd synth` into one folder (seeds 0 and 1) both exited 0, the seed-1 one
    printing "wrote ... (seed 1)" over a folder holding seed 0. The second now waits for the
    first (two ablations sharing a cache verify one world), then its card check refuses the
    other seed."""
    import subprocess
    import sys
    import time

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    out, ready = tmp_path / "w", tmp_path / "holding"
    holder = subprocess.Popen([sys.executable, "-c", SYNTH_HOLDER, str(out), str(ready)])
    try:
        end = time.monotonic() + 60
        while not ready.exists():
            assert time.monotonic() < end and holder.poll() is None
            time.sleep(0.01)
        assert main(["synth", "--out", str(out), "--contexts", "1", "--size", "16", "--no-unoccluded",
                     "--quiet", "--seed", "1"]) == 2
    finally:
        holder.wait(timeout=120)
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "holds a synthetic world with size=16, seed=0, not size=16, seed=1" in err, err
    assert main(["synth", "--out", str(out), "--contexts", "1", "--size", "16", "--no-unoccluded", "--quiet",
                 "--seed", "0"]) == 0  # the same world again: verified, kept


def test_cli_starts_no_more_processes_than_scenes(tmp_path, monkeypatch):
    """--workers 1000 for one scene used to fork 1000 processes."""
    import uevavd.data.synthetic.writer as writer

    seen = {}

    def fake_write_world(out, **kwargs):
        seen.update(kwargs)
        raise ValueError("stop here")

    monkeypatch.setattr(writer, "write_world", fake_write_world)
    assert main(["synth", "--out", str(tmp_path / "w"), "--quiet", "--contexts", "1", "--no-unoccluded",
                 "--workers", "1000"]) == 2
    assert seen["workers"] == 1


@pytest.mark.parametrize("command", [["synth", "--contexts", "1", "--size", "16", "--quiet"], ["demo"]])
def test_an_output_folder_that_is_a_file_is_one_line_saying_what_to_do(tmp_path, capsys, monkeypatch, command):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert main([command[0], "--out", str(afile), *command[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(afile) in err
    assert "; a file stands where a folder is expected: choose another path, or move the file (" in err, err
    assert afile.read_text() == "keep me"


def _written_train_605(folder: Path):
    meta = json.loads((folder / layout.SCENE_META).read_text())
    cats = {int(k): v for k, v in json.loads((folder / layout.SEG_DIR / layout.CATEGORIES).read_text()).items()}
    segs = {stem: cv2.imread(str(folder / layout.SEG_DIR / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
            for stem in meta["visible"]}
    return meta, cats, segs


def test_train_605_stages_are_written_in_one_id_space(tmp_path, monkeypatch):
    from uevavd.data.synthetic import writer

    jobs = writer._jobs_of

    def two_stages(name, seed):  # the first two stages, hatchback and sedan, three views each
        for stage, scene, views, render in jobs(name, seed):
            if stage == 2:
                return
            if scene.target in ("hatchback", "sedan"):
                yield stage, scene, views[:3], render

    monkeypatch.setattr(writer, "_jobs_of", two_stages)
    meta = writer.write_scene(tmp_path, "train_605", size=SIZE, seed=0)
    assert meta["split"] == "train_605" and meta["target"] is None and len(meta["stages"]) == 2
    assert len(meta["stage_of_view"]) == N_VIEWS
    meta, cats, segs = _written_train_605(tmp_path / "train_605")
    assert len(segs) == 12 and set(meta["visible"].values()) == {1.0}
    assert [k for k, v in cats.items() if v == "target"] == [1]
    ids = {stem: set(np.unique(s).tolist()) - {0, 1} for stem, s in segs.items()}
    assert all(i <= set(cats) for i in ids.values())
    stages = np.asarray(meta["stage_of_view"])

    def objects(stage, target):
        return set().union(*(ids[layout.view_stem(*view_coords(int(v)), target, "train_605")]
                             for v in np.flatnonzero(stages == stage)[:3]))

    # one stage is one background for every target; the two stages' objects never share an id
    assert objects(0, "hatchback") & objects(0, "sedan")
    assert objects(0, "hatchback") and objects(1, "hatchback")
    assert not (objects(0, "hatchback") | objects(0, "sedan")) & (objects(1, "hatchback") | objects(1, "sedan"))


@pytest.mark.slow
def test_train_605_is_unoccluded_and_consistent(tmp_path):
    from uevavd.data.synthetic.writer import write_scene

    write_scene(tmp_path, "train_605", size=SIZE, seed=0)
    meta, cats, segs = _written_train_605(tmp_path / "train_605")
    assert len(segs) == 5 * N_VIEWS and set(meta["visible"].values()) == {1.0}
    assert {v["terrain"] for v in meta["stages"]} == {"urban", "woodland"}
    assert set().union(*(np.unique(s).tolist() for s in segs.values())) <= set(cats)


def test_a_checked_scene_is_not_hashed_again_until_a_file_changes(world, tmp_path, monkeypatch):
    """A cached world is checked in a stat per file, not a read and a hash (59 s for paper64's
    96,800 views); a file rewritten in place, even at its size and with its mtime restored, is
    still caught (its ctime moved) and the scene redone."""
    import os
    import time

    from uevavd.data.synthetic import writer

    out = tmp_path / "w"
    shutil.copytree(world, out)  # new ctimes: the copy is hashed once, then stamped
    folder = out / "005"
    assert scene_complete(folder, size=SIZE, seed=3)
    hashed = []
    real = writer.sha256_hex
    monkeypatch.setattr(writer, "sha256_hex", lambda data: hashed.append(len(data)) or real(data))
    assert scene_complete(folder, size=SIZE, seed=3)
    assert len(hashed) == 1  # scene.json's own digest, against the stamp's; no view file
    victim = sorted(folder.glob("*.png"))[2]
    st = victim.stat()
    data = bytearray(victim.read_bytes())
    data[-20] ^= 0xFF
    time.sleep(0.05)  # past the file system's time granularity
    victim.write_bytes(bytes(data))
    os.utime(victim, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert victim.stat().st_size == st.st_size and victim.stat().st_mtime_ns == st.st_mtime_ns
    assert not scene_complete(folder, size=SIZE, seed=3)
    monkeypatch.setattr(writer, "sha256_hex", real)
    write_world(out, contexts=[5], size=SIZE, seed=3, include_unoccluded=False, progress=False)
    assert _tree_bytes(out / "005") == _tree_bytes(world / "005")


def test_a_scene_killed_while_being_rewritten_is_not_complete(world, tmp_path, monkeypatch):
    """View files are written in place; scene.json is the commit record, so a rewrite that
    dies half-way leaves the scene incomplete (redone on resume), never a stale record that
    vouches for files of two runs."""
    from uevavd.data.synthetic import writer

    out = tmp_path / "w"
    shutil.copytree(world, out)
    calls = {"n": 0}
    real_png = writer._png

    def dying_png(image, path):
        calls["n"] += 1
        if calls["n"] == 40:
            raise KeyboardInterrupt
        return real_png(image, path)

    monkeypatch.setattr(writer, "_png", dying_png)
    with pytest.raises(KeyboardInterrupt):
        writer.write_scene(out, "005", size=SIZE, seed=3)
    assert not scene_complete(out / "005", size=SIZE, seed=3)
    monkeypatch.setattr(writer, "_png", real_png)
    write_world(out, contexts=[5], size=SIZE, seed=3, include_unoccluded=False, progress=False)
    assert _tree_bytes(out / "005") == _tree_bytes(world / "005")


def test_a_resumed_world_s_progress_rate_counts_only_the_views_it_renders(world, tmp_path, capsys):
    """Views already on disk start the bar; they are not views rendered in no time (a rerun of
    a finished world printed hundreds of millions of views/s)."""
    out = tmp_path / "w"
    shutil.copytree(world, out)
    write_world(out, contexts=[5], size=SIZE, seed=3, include_unoccluded=False, progress=True)
    err = capsys.readouterr().err
    assert f"{N_VIEWS}/{N_VIEWS}" in err
    rates = [float(r) for r in re.findall(r"([0-9.]+)view/s", err)]
    assert all(r == 0 for r in rates), err  # nothing rendered: no rate, or 0


def test_a_folder_that_is_not_a_world_is_refused_and_left_as_it_was(tmp_path, capsys, monkeypatch):
    """synth --out a folder holding something else (a model zoo's copy: its own manifest.json)
    overwrote that manifest; it is refused before anything is written, while a world a killed
    call left unfinished (scene folders, no card yet) still resumes."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    other = tmp_path / "zoo-copy"
    (other / "quick").mkdir(parents=True)
    (other / layout.MANIFEST).write_text('{"mine": true}\n')
    argv = ["--contexts", "5", "--size", str(SIZE), "--seed", "3", "--no-unoccluded", "--quiet"]
    assert main(["synth", "--out", str(other), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{other} is not a synthetic world (it holds 'quick')" in err
    assert (other / layout.MANIFEST).read_text() == '{"mine": true}\n' and sorted(p.name for p in other.iterdir()) == [
        "manifest.json", "quick"]
    partial = tmp_path / "partial"
    assert main(["synth", "--out", str(partial), *argv]) == 0
    (partial / layout.DATASET_CARD).unlink()
    (partial / layout.MANIFEST).unlink()
    (partial / f".{layout.MANIFEST}.abc123.tmp").write_text("killed mid-write")
    assert main(["synth", "--out", str(partial), *argv]) == 0
    assert (partial / layout.DATASET_CARD).is_file()


def test_a_scene_reports_each_view_as_it_is_written(world, tmp_path):
    """The world's bar moves view by view, not a scene (605 or 3,025 views) at a time."""
    ticks = []
    meta = write_scene(tmp_path, "005", size=SIZE, seed=3,
                              on_view=lambda: ticks.append(len(list((tmp_path / "005").glob("*.png")))))
    assert len(ticks) == N_VIEWS and ticks == list(range(1, N_VIEWS + 1))  # each after its image is on disk
    assert _tree_bytes(tmp_path / "005") == _tree_bytes(world / "005") and meta["scene"] == "005"

"""`uevavd prepare`: table contents, keys, resume after interruption, refusals."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import uevavd.perception.prepare as prep
from uevavd.data.grid import N_VIEWS
from uevavd.table import ObservationTable, TableError


@pytest.fixture(scope="module")
def built(tiny_world, tiny_classifier, tmp_path_factory, method_toml):
    d = tmp_path_factory.mktemp("tables")
    method = d / "tiny.toml"
    method.write_text(method_toml.format(decompose="true"))
    path = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=d / "out",
                              progress=False)
    return method, path


def test_table_contents(built, tiny_world):
    method, path = built
    t = ObservationTable.load(path, expect_key=path.name)
    assert t.scenes == ("001", "031") and t.splits == ("train", "train")
    assert t.targets.tolist() == [0, 1] and t.contexts.tolist() == [1, 31]
    assert t.features.shape == (2, N_VIEWS, 512) and t.features.dtype == np.float16
    assert isinstance(t.features, np.memmap)
    assert t.probs.dtype == np.float32 and np.allclose(t.probs.sum(-1), 1, atol=1e-3)
    # boxes normalised by the 16 px crop; fully occluded views all zero; visibility from scene.json
    vis = json.loads((tiny_world / "001" / "scene.json").read_text())["visible"]
    assert np.isclose(t.visible[0, 0], vis["x-50_y-50_z060_hatchback_001"])
    assert (t.boxes[t.visible == 0] == 0).all() and t.boxes.max() <= 1
    assert t.meta["config"]["key_parts"]["encoder"].startswith("encoder:resnet18:random")
    assert not (path.parent / f"{path.name}.partial").exists()
    # the classifier recognises the fully visible views and fails the hidden ones
    assert t.argmax_correct()[t.visible > 0.9].mean() > 0.9


def test_rerun_reuses_the_table(built, tiny_world, tiny_classifier, monkeypatch):
    import uevavd.perception.nets as nets

    method, path = built
    monkeypatch.setattr(prep, "_compute_scene", lambda *a, **k: pytest.fail("recomputed a finished table"))
    # the encoder and recognizer are built for their identities only: no network is made ready to run
    monkeypatch.setattr(nets, "fold_batchnorm", lambda *a, **k: pytest.fail("folded a network it never runs"))
    again = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=path.parent,
                               progress=False)
    assert again == path


def test_key_changes_with_every_input(built, own_tiny_world, tiny_classifier, tmp_path, monkeypatch):
    method, path = built
    tiny_world = own_tiny_world  # scene 031 is edited below
    import functools

    import uevavd.data.reader as reader

    # the manifest itself is the same for every variant; the fingerprint still stats every file
    monkeypatch.setattr(reader, "read_dataset", functools.lru_cache(reader.read_dataset))

    def key(**over):
        return prep.plan_table(tiny_world, method, classifier_path=tiny_classifier, overrides=over or None).key

    base = key()
    assert base == path.name
    import torch

    from uevavd.perception.segmenters import GroundTruthSegmenter
    from uevavd.perception.weights import make_resnet

    same_weights = tmp_path / "r18-seed0.pt"  # the very weights of weights="random", seed 0, as a file
    torch.save(make_resnet("resnet18", seed=0).state_dict(), same_weights)
    variants = [
        key(**{"perception.gray_seed": 1}),
        key(**{"perception.decompose": False}),
        key(**{"perception.encoder.seed": 1}),
        key(**{"perception.encoder.name": "resnet50", "perception.encoder.weights": "random"}),  # architecture
        key(**{"perception.encoder.weights": f"file:{same_weights}"}),  # the weights spec, same tensors
        key(**{"perception.encoder.weights": "classifier"}),
    ]
    with monkeypatch.context() as m:  # another segmenter (version)
        m.setattr(GroundTruthSegmenter, "identity", lambda self: "segmenter:gt:v999")
        variants.append(key())
    other_clf = tmp_path / "other.safetensors"
    from uevavd.perception.classifier import read_classifier_file, write_classifier_file
    from uevavd.perception.weights import state_dict_hash

    sd, meta = read_classifier_file(tiny_classifier)
    sd["fc.bias"] = sd["fc.bias"] + 0.1  # other weights, written as a classifier file is (with their hash)
    meta["train"]["weights_hash"] = state_dict_hash(sd)
    write_classifier_file(other_clf, sd, meta)
    variants.append(prep.plan_table(tiny_world, method, classifier_path=other_clf).key)
    assert len({base, *variants}) == len(variants) + 1
    # the dataset: one image rewritten (same bytes, new mtime) changes the key
    img = next((tiny_world / "031").glob("*.png"))
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        assert key() != base
    finally:
        os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert key() == base
    # one box annotation changed (the image untouched) changes the key
    box = img.with_suffix(".txt")
    text = box.read_text()
    x1, y1, x2, y2 = map(int, text.split())
    box.write_text("1 1 3 3\n" if x2 == 0 else f"{x1} {y1} {x2} {y2 - 1}\n" if y2 - 1 > y1 else "0 0 0 0\n")
    try:
        reader.read_dataset.cache_clear()
        assert key() != base
    finally:
        box.write_text(text)
        reader.read_dataset.cache_clear()
    assert key() == base


def test_resume_after_interruption(built, tiny_world, tiny_classifier, tmp_path, monkeypatch):
    method, path = built
    out = tmp_path / "out"
    real = prep._compute_scene
    calls = []

    def dies_on_second(scene, *a, **k):
        calls.append(scene)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(scene, *a, **k)

    monkeypatch.setattr(prep, "_compute_scene", dies_on_second)
    with pytest.raises(KeyboardInterrupt):
        prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    partial = out / f"{path.name}.partial"
    assert (partial / "001.npz").is_file() and not (out / path.name).exists()
    assert not list(partial.glob(".*tmp"))  # no half-written shard left behind
    with pytest.raises(TableError):
        ObservationTable.load(partial)
    calls.clear()
    monkeypatch.setattr(prep, "_compute_scene", lambda scene, *a, **k: calls.append(scene) or real(scene, *a, **k))
    done = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert calls == ["031"]
    a, b = ObservationTable.load(done), ObservationTable.load(path)
    for name in ("features", "probs", "boxes"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


class _Killed(BaseException):
    """Stands for the process dying: nothing after it runs in the 'killed' frame."""


def test_killed_while_writing_a_shard(built, tiny_world, tiny_classifier, tmp_path, monkeypatch):
    """A crash in the middle of writing scene 031's shard, as a kill would leave it: half a file
    under the shard's own name (what a non-atomic writer leaves) and a half temp file. The rerun
    recomputes 031, never serves the half file, and gives the table of an uninterrupted build."""
    import io

    method, path = built
    out = tmp_path / "out"
    partial = out / f"{path.name}.partial"
    real_write = prep.write_shard

    def dies_mid_write(target, arrays):
        if target.stem != "031":
            return real_write(target, arrays)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        data = buf.getvalue()
        target.write_bytes(data[: len(data) // 2])
        (target.parent / f".{target.name}.k1ll3d.tmp").write_bytes(data[: len(data) // 3])
        raise _Killed

    monkeypatch.setattr(prep, "write_shard", dies_mid_write)
    with pytest.raises(_Killed):
        prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert not (out / path.name).exists()
    assert (partial / "031.npz").stat().st_size > 0  # the half file is there, under the shard's name
    assert prep.read_shard(partial / "031.npz", 512, 5) is None  # and is not taken for a finished shard
    assert prep.read_shard(partial / "001.npz", 512, 5) is not None
    with pytest.raises(TableError):
        ObservationTable.load(partial)
    monkeypatch.setattr(prep, "write_shard", real_write)
    calls = []
    real_compute = prep._compute_scene
    monkeypatch.setattr(prep, "_compute_scene", lambda scene, *a, **k: calls.append(scene) or real_compute(scene, *a, **k))
    done = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert calls == ["031"] and done == out / path.name and not partial.exists()
    a, b = ObservationTable.load(done), ObservationTable.load(path)
    for name in ("features", "probs", "boxes", "visible"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_killed_inside_the_real_shard_writer_leaves_no_shard(built, tiny_world, tiny_classifier, tmp_path,
                                                              monkeypatch):
    """The real writer goes through a temp file and a rename: a crash while np.savez is half
    way leaves nothing under the shard's name; the same for a crash while the table is saved."""
    method, path = built
    out = tmp_path / "out"
    partial = out / f"{path.name}.partial"
    real_savez = np.savez
    written = []

    def savez_dies_on_second(fh, **arrays):  # the second scene's shard (caches are .npz files too)
        if "boxes" in arrays:
            written.append(fh)
        if len(written) == 2:
            fh.write(b"PK\x03\x04 half a zip")
            raise _Killed
        return real_savez(fh, **arrays)

    monkeypatch.setattr(np, "savez", savez_dies_on_second)
    with pytest.raises(_Killed):
        prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    monkeypatch.setattr(np, "savez", real_savez)
    assert sorted(p.name for p in partial.glob("*.npz")) == ["001.npz"]
    # now die while the finished table is written: no table appears, the shards stay
    real_save = np.save
    monkeypatch.setattr(np, "save", lambda fh, arr, *a, **k: (fh.write(b"\x93NUMPY half"), _raise(_Killed)))
    with pytest.raises(_Killed):
        prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    monkeypatch.setattr(np, "save", real_save)
    assert not (out / path.name).exists() and sorted(p.name for p in partial.glob("*.npz")) == ["001.npz", "031.npz"]
    monkeypatch.setattr(prep, "_compute_scene", lambda *a, **k: pytest.fail("a finished shard was recomputed"))
    done = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    np.testing.assert_array_equal(ObservationTable.load(done).features, ObservationTable.load(path).features)


def _raise(exc):
    raise exc


def test_corrupt_shard_is_recomputed(built, tiny_world, tiny_classifier, tmp_path, monkeypatch):
    method, path = built
    out = tmp_path / "out"
    partial = out / f"{path.name}.partial"
    partial.mkdir(parents=True)
    shutil.copy(path / "meta.json", partial / "001.npz")  # garbage where a shard should be
    done = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    np.testing.assert_array_equal(ObservationTable.load(done).features, ObservationTable.load(path).features)


def test_table_refusals(built, tmp_path):
    method, path = built
    with pytest.raises(TableError, match="key"):
        ObservationTable.load(path, expect_key="0" * 20)
    copy = tmp_path / "old"
    shutil.copytree(path, copy)
    meta = json.loads((copy / "meta.json").read_text())
    meta["schema_version"] = 0
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(TableError, match="schema version"):
        ObservationTable.load(copy)
    t = ObservationTable.load(path, mmap=False)
    f = np.array(t.features)
    f[1, 3, 0] = np.inf
    with pytest.raises(TableError, match="NaN or inf"):
        ObservationTable.from_arrays(f, t.probs, t.boxes, scenes=t.scenes, targets=t.targets, splits=t.splits)


def test_decompose_without_segmenter_is_refused(tiny_world, tiny_classifier, tmp_path, method_toml):
    m = tmp_path / "m.toml"
    m.write_text(method_toml.format(decompose="true").replace('segmenter = { name = "gt" }\n', ""))
    with pytest.raises(ValueError, match="needs a perception.segmenter"):
        prep.plan_table(tiny_world, m, classifier_path=tiny_classifier)
    with pytest.raises(ValueError, match="decompose = true with segmenter 'none'"):
        prep.plan_table(tiny_world, "ibe_map", classifier_path=tiny_classifier,
                        overrides={"perception.segmenter.name": "none", "perception.encoder.name": "resnet18",
                                   "perception.encoder.weights": "random"})
    # without decomposition the segmenter does not matter (and is not built)
    assert prep.plan_table(tiny_world, "ibe_map", classifier_path=tiny_classifier, overrides={
        "perception.segmenter.name": "none", "perception.decompose": False, "perception.encoder.name": "resnet18",
        "perception.encoder.weights": "random"}).segmenter is None


def test_gt_segmenter_without_categories_is_refused(tiny_classifier, tmp_path, method_toml):
    from uevavd.testing.worlds import write_tiny_world

    world = write_tiny_world(tmp_path / "w", contexts=(1,), train605=False)
    m = tmp_path / "m.toml"
    m.write_text(method_toml.format(decompose="true"))
    cats = world / "001" / "seg" / "categories.json"
    cats.write_text('{"0": "none", "2": "building", "3": "ground"}')  # no target
    with pytest.raises(ValueError, match=r"categories\.json: no instance has category 'target'"):
        prep.plan_table(world, m, classifier_path=tiny_classifier)
    cats.unlink()
    with pytest.raises(ValueError, match=r"001/seg/categories\.json is missing"):
        prep.plan_table(world, m, classifier_path=tiny_classifier)
    with pytest.raises(ValueError, match=r"categories\.json is missing"):
        prep.prepare_table(world, m, classifier_path=tiny_classifier, out_dir=tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_ray_backend_builds_the_same_table(tiny_world, tiny_classifier, tmp_path, local_ray):
    """Scenes sharded over Ray tasks (a local 1-CPU instance, one task process, a scene a
    shard) give the local build's table."""
    from uevavd.perception.prepare import prepare_table
    from uevavd.perception.prepare_ray import prepare_table_ray
    from uevavd.table import ObservationTable

    world = tiny_world
    method = dict(classifier_path=tiny_classifier,
                  overrides={"perception.encoder.name": "resnet18", "perception.encoder.weights": "random"})
    local = prepare_table(world, "ibe_map", out_dir=tmp_path / "local", workers=1, progress=False, **method)
    remote = prepare_table_ray(world, "ibe_map", out_dir=tmp_path / "ray", shards=2, progress=False, **method)
    assert local_ray.is_initialized()  # the build used the running instance and left it running
    assert remote.name == local.name  # the same key
    a, b = ObservationTable.load(local), ObservationTable.load(remote)
    assert list(a.scenes) == list(b.scenes) == ["001", "031"]
    for name in ("features", "probs", "boxes"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not (tmp_path / "ray" / f"{remote.name}.partial").exists()


def test_cli_bad_input_is_one_line_and_exit_2(tiny_world, tiny_classifier, tmp_path, capsys, monkeypatch):
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # no ImageNet files there
    (tmp_path / "empty").mkdir()
    truncated = tmp_path / "cut.safetensors"
    truncated.write_bytes(tiny_classifier.read_bytes()[:1000])
    world = str(tiny_world)
    cases = [
        (["prepare", world, "--method", "ibe_map", "--set", "nokey"], "ConfigError", "KEY=VALUE"),
        (["prepare", world, "--method", "no_such_method"], "ConfigError", "no_such_method"),
        (["prepare", world, "--method", "ibe_map", "--set", "perception.encoder.name=nope"], "", "nope"),
        (["prepare", world, "--method", "map", "--set", "perception.encoder.weights=random", "--classifier",
          str(truncated)], "WeightsError", "cut.safetensors"),
        # the named classifier is checked before the encoder loads (its ImageNet weights are
        # absent here, which once hid the bad file behind a "weights not found")
        (["prepare", world, "--method", "map", "--classifier", str(truncated)], "WeightsError", "cut.safetensors"),
        (["prepare", world, "--method", "map"], "WeightsError", "not found"),
        (["prepare", str(tmp_path / "empty"), "--method", "map"], "DatasetError", "no scene folders"),
        (["train-classifier", str(tmp_path / "empty"), "--out", str(tmp_path / "c.safetensors")],
         "DatasetError", "no scene folders"),
    ]
    for argv, kind, needle in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"uevavd {argv[0]}: error: ") and needle in err and kind in err, err
        assert "Traceback" not in err
    monkeypatch.setenv("UEVAVD_DEBUG", "1")
    from uevavd.config import ConfigError

    with pytest.raises(ConfigError):
        main(["prepare", world, "--method", "ibe_map", "--set", "nokey"])


def _small_table(n: int = 2, dim: int = 8) -> ObservationTable:
    rng = np.random.default_rng(0)
    probs = rng.random((n, N_VIEWS, 5)).astype(np.float32)
    return ObservationTable.from_arrays(
        rng.standard_normal((n, N_VIEWS, dim)), probs / probs.sum(-1, keepdims=True),
        np.tile(np.array([0.25, 0.25, 0.75, 0.75], np.float32), (n, N_VIEWS, 1)),
        scenes=[f"{i + 1:03d}" for i in range(n)], targets=list(range(n)), splits=["train"] * n)


def _poke(f, value: float, index: int = 3) -> None:
    """Overwrite one float16 of an .npy file in place (size unchanged), as a hand edit would."""
    offset = np.load(f, mmap_mode="r").offset
    with open(f, "r+b") as fh:
        fh.seek(offset + 2 * index)
        fh.write(np.float16(value).tobytes())


def test_table_load_does_not_scan_the_features(tmp_path, monkeypatch):
    path = _small_table().save(tmp_path / "t")
    meta = json.loads((path / "meta.json").read_text())
    rec = meta["integrity"]["files"]["features.npy"]
    assert rec["bytes"] == (path / "features.npy").stat().st_size and len(rec["sha256"]) == 64
    scanned = []
    real = np.isfinite
    monkeypatch.setattr(np, "isfinite", lambda a, *k, **kw: scanned.append(np.shape(a)) or real(a, *k, **kw))
    t = ObservationTable.load(path)
    assert isinstance(t.features, np.memmap)
    assert scanned and t.features.shape not in scanned  # probs and boxes are checked, features are not
    monkeypatch.setattr(np, "isfinite", real)
    assert t.verify() is t


def test_table_written_by_hand_is_refused(tmp_path):
    path = _small_table().save(tmp_path / "t")
    feats = path / "features.npy"
    # NaN written into the feature file in place (same size), right after save
    _poke(feats, np.nan)
    with pytest.raises(TableError, match="features contain NaN or inf"):
        ObservationTable.load(path)
    # a finite change is refused too: the file no longer is the one that was checked
    _poke(feats, 7.0)
    with pytest.raises(TableError, match="changed since the table was written"):
        ObservationTable.load(path)
    # ... also when the editor restores the timestamp (the file's ctime, which no one can set
    # back, moved: it used to be served, only verify() saw it)
    rec = json.loads((path / "meta.json").read_text())["integrity"]["files"]["features.npy"]
    os.utime(feats, ns=(rec["mtime_ns"], rec["mtime_ns"]))
    with pytest.raises(TableError, match="sha256 differs"):
        ObservationTable.load(path)
    # a truncated file
    feats.write_bytes(feats.read_bytes()[:-10])
    with pytest.raises(TableError):
        ObservationTable.load(path)
    # a copy that did not keep the times is hashed, found intact and served
    good = _small_table().save(tmp_path / "good")
    copy = tmp_path / "copy"
    shutil.copytree(good, copy, copy_function=shutil.copyfile)
    assert ObservationTable.load(copy).verify().key == ObservationTable.load(good).key
    # a meta.json edited after its checksum was removed was served: a table is written with one
    meta = json.loads((copy / "meta.json").read_text())
    del meta["meta_sha256"]
    meta["splits"][0] = "hard"
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(TableError, match="the checksum was removed"):
        ObservationTable.load(copy)


@pytest.mark.parametrize("damage", ["visible", "probs", "utf8", "no_scenes"])
def test_a_damaged_small_array_or_meta_json_is_refused_naming_the_file(tmp_path, damage):
    """visible.npy values of 7.0 (the visibility oracle moved 0.25 -> 0.21), permuted probs
    rows, invalid UTF-8 in meta.json (a UnicodeDecodeError), a meta.json without its scenes
    (a KeyError): each was served or a traceback naming no file."""
    path = _small_table().save(tmp_path / "t")
    if damage == "visible":
        v = np.load(path / "visible.npy")
        v[0, :3] = [0.9, 0.1, 0.5] if v[0, 0] != 0.9 else [0.1, 0.9, 0.5]
        np.save(path / "visible.npy", v)
    elif damage == "probs":
        p = np.load(path / "probs.npy")
        np.save(path / "probs.npy", p[::-1].copy())
    elif damage == "utf8":
        raw = (path / "meta.json").read_bytes()
        (path / "meta.json").write_bytes(raw[:40] + b"\xff\xfe" + raw[42:])
    else:
        meta = json.loads((path / "meta.json").read_text())
        del meta["scenes"]
        from uevavd.table import _meta_digest

        meta.pop("meta_sha256")
        meta["meta_sha256"] = _meta_digest(meta)
        (path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(TableError) as err:
        ObservationTable.load(path)
    assert str(path) in str(err.value) and "rebuild" in str(err.value)


def test_classifier_backbone_encoder_shares_one_forward(tiny_world, tiny_classifier, tmp_path, monkeypatch):
    """weights='classifier' on raw views: features and probabilities from one forward pass,
    equal to what the encoder and the classifier give separately."""
    from uevavd.data.reader import read_dataset
    from uevavd.perception.classifier import load_classifier
    from uevavd.perception.encoders import build_resnet18

    method = tmp_path / "own.toml"
    method.write_text(METHOD_OWN)
    clf = load_classifier(tiny_classifier, device="cpu")
    enc = build_resnet18(weights="classifier", classifier=str(tiny_classifier), device="cpu")
    assert clf.shares_backbone(enc)
    assert not clf.shares_backbone(build_resnet18(weights="random", device="cpu"))
    monkeypatch.setattr(type(clf), "predict_proba",
                        lambda self, images: pytest.fail("second forward"))
    path = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=tmp_path / "out",
                              progress=False)
    monkeypatch.undo()
    t = ObservationTable.load(path)
    recs = sorted((r for r in read_dataset(tiny_world).records if r.scene == "001"), key=lambda r: r.view)
    import cv2

    images = np.stack([cv2.cvtColor(cv2.imread(str(r.image)), cv2.COLOR_BGR2RGB) for r in recs[:50]])
    np.testing.assert_allclose(t.probs[0, :50], clf.predict_proba(images), atol=1e-5)
    np.testing.assert_allclose(t.features[0, :50].astype(np.float32), enc.encode(images), rtol=1e-2, atol=1e-2)


def test_decomposed_table_reuses_the_raw_views_probabilities(built, tiny_world, tiny_classifier, tmp_path,
                                                             monkeypatch):
    """The probabilities on raw views are cached by (classifier, scene files): a second table
    of the same data and classifier (another segmenter or encoder) classifies nothing again."""
    method, path = built
    probs_dirs = list((path.parent / "probs").iterdir())
    assert len(probs_dirs) == 1 and len(list(probs_dirs[0].glob("*.npz"))) == 2
    other = tmp_path / "other.toml"
    other.write_text(method.read_text().replace("gray_seed = 0", "gray_seed = 1"))
    out = tmp_path / "out"
    shutil.copytree(path.parent / "probs", out / "probs")
    from uevavd.perception.classifier import ResNetClassifier

    monkeypatch.setattr(ResNetClassifier, "predict_proba", lambda self, images: pytest.fail("reclassified"))
    second = prep.prepare_table(tiny_world, other, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert second.name != path.name
    np.testing.assert_array_equal(ObservationTable.load(second).probs, ObservationTable.load(path).probs)


def test_each_scene_is_keyed_by_its_own_files(built, own_tiny_world, tiny_classifier):
    """The raw views' probabilities are cached per scene under that scene's own fingerprint,
    so rewriting one image invalidates its scene's cache entry and no other."""
    method, path = built
    tiny_world = own_tiny_world  # scene 031 is edited below
    p = prep.plan_table(tiny_world, method, classifier_path=tiny_classifier)
    assert p.scene_fingerprints == {s: prep.dataset_fingerprint(p.manifest, [(s, r)]) for s, r in p.scenes}
    cached = {f.name for f in (path.parent / "probs").glob("*/*.npz")}
    assert cached == {f"{s}-{fp}.npz" for s, fp in p.scene_fingerprints.items()}
    img = next((tiny_world / "031").glob("*.png"))
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        changed = prep.plan_table(tiny_world, method, classifier_path=tiny_classifier).scene_fingerprints
    finally:
        os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert [s for s in changed if changed[s] != p.scene_fingerprints[s]] == ["031"]


def test_prepare_with_a_preset(built, tiny_world, tiny_classifier, tmp_path, capsys):
    """``prepare --preset`` builds the table of the method loaded with the preset's [overrides]
    by the precedence rule: a key the method file sets itself keeps the file's value, and
    ``--set`` wins over both."""
    from uevavd.cli import main

    method, path = built  # its file sets perception.gray_seed = 0
    preset = tmp_path / "mine.toml"
    preset.write_text('name = "mine"\n[overrides]\n"perception.gray_seed" = 7\n"perception.encoder.seed" = 3\n')
    capsys.readouterr()
    args = ["prepare", str(tiny_world), "--method", str(method), "--preset", str(preset), "--classifier",
            str(tiny_classifier), "--out", str(path.parent)]
    assert main(args) == 0
    printed = Path(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed == path  # the file's gray_seed and encoder seed, not the preset's
    assert main([*args, "--set", "perception.gray_seed=7"]) == 0
    printed = Path(capsys.readouterr().out.strip().splitlines()[-1])
    want = prep.plan_table(tiny_world, method, classifier_path=tiny_classifier,
                           overrides={"perception.gray_seed": 7}).key
    assert printed.name == want != path.name
    assert ObservationTable.load(printed).meta["config"]["key_parts"]["gray_seed"] == 7


METHOD_OWN = """
name = "own"
[perception]
segmenter = { name = "none" }
encoder = { name = "resnet18", weights = "classifier" }
classifier = { name = "resnet18" }
decompose = false
"""


def test_an_edited_meta_json_is_refused(tmp_path):
    """meta.json is under the integrity check: swapped targets or splits are refused by
    load() (they would change every reward), naming the file."""
    path = _small_table().save(tmp_path / "t")
    good = ObservationTable.load(path)
    for key, change in (("targets", lambda m: [(t + 1) % 5 for t in m["targets"]]),
                        ("splits", lambda m: ["hard"] * len(m["splits"]))):
        copy = tmp_path / key
        shutil.copytree(path, copy)
        meta = json.loads((copy / "meta.json").read_text())
        meta[key] = change(meta)
        assert meta[key] != json.loads((path / "meta.json").read_text())[key]
        (copy / "meta.json").write_text(json.dumps(meta))
        with pytest.raises(TableError, match="meta.json was changed after the table was written"):
            ObservationTable.load(copy)
    assert ObservationTable.load(path).key == good.key


def test_an_empty_array_file_is_a_table_error_and_prepare_rebuilds(built, tiny_world, tiny_classifier, tmp_path):
    """A zero-byte features.npy (a killed copy, a full disk): one TableError naming the
    file, not an EOFError traceback; prepare rebuilds the table."""
    method, path = built
    copy_root = tmp_path / "tables"
    shutil.copytree(path.parent, copy_root)
    broken = copy_root / path.name
    (broken / "features.npy").write_bytes(b"")
    with pytest.raises(TableError, match="features.npy: unreadable array.*rebuild"):
        ObservationTable.load(broken)
    rebuilt = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=copy_root,
                                 progress=False)
    assert rebuilt == broken and ObservationTable.load(rebuilt).verify().key == ObservationTable.load(path).key


def test_two_prepares_of_one_key_at_once_both_get_the_table(tiny_world, tiny_classifier, method_toml, tmp_path):
    """Two ablations sharing UEVAVD_CACHE build the same table at the same moment (two
    processes: another and this one, started together once the other has imported uevavd):
    the second waits on the key's file lock and finds the first's table (it used to fail on
    the first's vanished .partial folder)."""
    import subprocess
    import sys

    method = tmp_path / "tiny.toml"
    method.write_text(method_toml.format(decompose="false"))
    code = ("import sys, torch; torch.set_num_threads(1); from uevavd.perception.prepare import prepare_table; "
            "print('ready', flush=True); sys.stdin.readline(); "
            "print(prepare_table(sys.argv[1], sys.argv[2], classifier_path=sys.argv[3], out_dir=sys.argv[4], "
            "workers=1, progress=False))")
    args = [str(tiny_world), str(method), str(tiny_classifier), str(tmp_path / "shared")]
    other = subprocess.Popen([sys.executable, "-c", code, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline() == "ready\n", other.stderr.read()[-2000:]
        other.stdin.write("go\n")
        other.stdin.flush()
        here = prep.prepare_table(*args[:2], classifier_path=args[2], out_dir=args[3], workers=1, progress=False)
        out, err = other.communicate(timeout=300)
    finally:
        other.kill()
    assert other.returncode == 0, err[-2000:]
    assert Path(out.strip().splitlines()[-1]) == here
    assert ObservationTable.load(here).verify().key == here.name


def test_what_a_killed_build_leaves_is_removed_by_the_next(built, tiny_world, tiny_classifier, tmp_path,
                                                         monkeypatch):
    """A build killed inside the table's atomic folder write leaves ``.KEY.*.tmp`` (full table
    size), one killed between its renames ``.KEY.old-PID``, one killed after the save
    ``KEY.partial``: none was ever removed. The next prepare of the key, holding its lock, does."""
    method, path = built
    out = tmp_path / "out"
    shutil.copytree(path, out / path.name)
    key = path.name
    litter = [out / f".{key}.k3j2.tmp", out / f".{key}.old-99999", out / f"{key}.partial"]
    for d in litter:
        d.mkdir()
        (d / "features.npy").write_bytes(b"x" * 1000)
    other = out / ".otherkey.abcd.tmp"  # another table's: not this build's to remove
    other.mkdir()
    monkeypatch.setattr(prep, "_compute_scene", lambda *a, **k: pytest.fail("recomputed a finished table"))
    assert prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False) \
        == out / key
    assert not any(d.exists() for d in litter) and other.is_dir()


def test_a_killed_policy_save_leaves_no_temporary_after_the_resume(tmp_path):
    """``.policy.safetensors.*.tmp.safetensors`` (a policy save killed mid-write) was never
    removed: the trainer's sweep matched ``.*.tmp`` only."""
    from uevavd.atomic import remove_temporaries

    run = tmp_path / "run"
    run.mkdir()
    for name in (".policy.safetensors.ab12.tmp.safetensors", ".checkpoint.pt.cd34.tmp", "checkpoint.pt"):
        (run / name).write_bytes(b"x")
    remove_temporaries(run)
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt"]


def test_a_read_only_cache_serves_a_table_it_holds(built, tiny_world, tiny_classifier, monkeypatch):
    """A read-only UEVAVD_CACHE that already held the table failed on the lock file; a built
    table is served without the lock now. (The tests run as root, whom permissions do not stop:
    the lock file's creation fails as it does on a read-only file system.)"""
    method, path = built

    import filelock

    def read_only(self, *a, **k):
        raise OSError(30, "Read-only file system", self.lock_file)

    monkeypatch.setattr(filelock.FileLock, "acquire", read_only)
    monkeypatch.setattr(prep, "_compute_scene", lambda *a, **k: pytest.fail("recomputed a finished table"))
    assert prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=path.parent,
                              progress=False) == path


def test_a_table_with_the_recognizer_in_the_state(built, tiny_world, tiny_classifier, tmp_path):
    """perception.recognizer_in_state: the features end with the recognizer's class
    probabilities of the raw view; another key, so a policy of one never reads the other's; the
    encoder's cached features are shared; the keys of tables without it do not move."""
    method, path = built
    reco = tmp_path / "reco.toml"
    reco.write_text(method.read_text().replace("gray_seed = 0", "gray_seed = 0\nrecognizer_in_state = true"))
    out = tmp_path / "out"
    shutil.copytree(path.parent / "features", out / "features")  # the encoder's work, reused
    second = prep.prepare_table(tiny_world, reco, classifier_path=tiny_classifier, out_dir=out, progress=False)
    a, b = ObservationTable.load(path), ObservationTable.load(second)
    assert second.name != path.name and b.perception_identity != a.perception_identity
    assert b.features.shape == (2, N_VIEWS, 512 + 5)
    np.testing.assert_array_equal(b.features[..., :512], a.features)
    np.testing.assert_array_equal(b.features[..., 512:], a.probs.astype(np.float16))
    assert prep.plan_table(tiny_world, method, classifier_path=tiny_classifier).key == path.name


def test_a_damaged_feature_or_probability_cache_is_computed_again_not_baked_into_a_table(
        built, tiny_world, tiny_classifier, tmp_path, caplog):
    """The per-scene caches a rebuild reuses had no digest: a flipped bit there went into a
    rebuilt table under the same key with a fresh digest (or, in a high bit of a probability,
    failed with "probabilities do not sum to 1" naming no file)."""
    import logging

    method, path = built
    out = tmp_path / "out"
    for name in ("features", "probs"):
        shutil.copytree(path.parent / name, out / name)
    damaged = [f for name in ("features", "probs") for f in sorted((out / name).glob("*/*.npz"))]  # other tests' too
    for f in damaged:
        data = bytearray(f.read_bytes())
        data[len(data) // 2] ^= 0x40
        f.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="uevavd.perception.prepare"):
        rebuilt = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert rebuilt.name == path.name
    a, b = ObservationTable.load(path), ObservationTable.load(rebuilt)
    for name in ("features", "probs", "boxes", "visible"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    named = {f.parent.parent.name for f in damaged if str(f) in " ".join(r.getMessage() for r in caplog.records)}
    assert named == {"features", "probs"}  # the caches this build reads, each named
    # computed again and cached again: a second rebuild reads the caches without a warning
    caplog.clear()
    shutil.rmtree(rebuilt)
    with caplog.at_level(logging.WARNING, logger="uevavd.perception.prepare"):
        prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    assert not [r for r in caplog.records if "damaged" in r.getMessage() or "unreadable" in r.getMessage()]


def test_another_scenes_cache_copied_in_is_computed_again_not_baked_into_a_table(
        built, tiny_world, tiny_classifier, tmp_path, caplog):
    """A scene's sealed cache replaced by another scene's went into the table, exit 0 (MAP's train
    return 0.4566 -> 0.2574): the seal proved the bytes, not whose they were."""
    import logging

    method, path = built
    out = tmp_path / "out"
    for name in ("features", "probs"):
        shutil.copytree(path.parent / name, out / name)
    swapped = []
    for name in ("features", "probs"):
        for folder in sorted((out / name).iterdir()):
            scenes = sorted(folder.glob("*.npz"))
            if len(scenes) >= 2:
                shutil.copy(scenes[1], scenes[0])  # the second scene's arrays under the first's name
                swapped.append(scenes[0])
    assert swapped
    with caplog.at_level(logging.WARNING, logger="uevavd.perception.prepare"):
        rebuilt = prep.prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=out, progress=False)
    a, b = ObservationTable.load(path), ObservationTable.load(rebuilt)
    for name in ("features", "probs", "boxes", "visible"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert any("copied from another scene" in r.getMessage() for r in caplog.records)

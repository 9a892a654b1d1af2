"""Fine-tuning and small-SAM training on the tiny drawn world (tiny models, CPU, seconds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.perception.sam import build_sam_segmenter, load_sam
from uevavd.perception.sam.model import SmallConfig, build_model, save_full
from uevavd.perception.training.sam.data import selection_keys, split_heldout
from uevavd.perception.training.sam.evaluate import evaluate
from uevavd.perception.training.sam.finetune import finetune_model
from uevavd.perception.training.sam.loop import TrainArgs, train_loop

TINY = SmallConfig(img_size=32, patch_size=8, embed_dim=32, depth=1, num_heads=2, prompt_dim=32,
                   decoder_depth=1, decoder_heads=2, decoder_mlp=64)


@pytest.fixture(scope="module")
def views(tiny_world):
    return split_heldout(tiny_world, per_context=24, heldout_per_context=12, seed=0)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("sam_base") / "tiny.safetensors"
    save_full(path, build_model("small", TINY), "small", TINY)
    return path


def test_views_hold_out_a_context(views):
    train, held = views
    assert len(train) == 24 and len(held) == 12
    assert not np.array_equal(train.images[:12], held.images)
    assert all(train.target_mask(i).any() or not train.boxes[i].any() for i in range(len(train)))


def assert_same_views(a, b) -> None:
    """Two lists of SamView are exactly equal: target, segments, ring points, raw masks."""
    assert len(a) == len(b)
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
        assert np.array_equal(x.target, y.target), f"view {i}: target masks differ"
        assert len(x.segments) == len(y.segments), f"view {i}: {len(x.segments)} vs {len(y.segments)} segments"
        assert all(np.array_equal(s, t) for s, t in zip(x.segments, y.segments, strict=True)), f"view {i}: segments"
        assert np.array_equal(x.points, y.points) and len(x.raw) == len(y.raw)
        assert all(np.array_equal(s, t) for s, t in zip(x.raw, y.raw, strict=True)), f"view {i}: raw ring masks"


def test_finetune_lowers_loss_and_the_saved_model_gives_the_same_masks(views, base, tmp_path):
    train, held = views
    out = tmp_path / "ft.safetensors"
    # lr 1e-2: enough for the tiny decoder to give non-empty target masks to compare.
    args = TrainArgs(steps=30, batch_size=4, lr=1e-2, warmup=1, points_per_view=1, save_every=10)
    rep, in_memory = finetune_model(base, train, held, out=out, args=args, device="cpu",
                                    embedding_cache=tmp_path / "emb.pt")
    assert rep["loss_last"] < rep["loss_first"]
    assert (tmp_path / "emb.pt").is_file() and not (tmp_path / "ft.safetensors.resume").exists()
    assert {"heldout_before", "heldout_after"} <= set(rep)
    tuned = build_sam_segmenter(checkpoint=str(out), device="cpu")
    assert tuned.loaded.model_type == "small"
    assert tuned.identity() == in_memory.identity()
    # The reloaded model (base file + saved decoder) gives exactly the in-memory model's
    # target masks, surrounding segments, ring points and raw ring masks.
    idx = np.array([0, 3, 5, 8, 11])
    assert held.boxes[idx].any(1).sum() >= 3  # mostly views with a visible target
    got = tuned.segment_detailed(held.images[idx], held.boxes[idx])
    assert_same_views(got, in_memory.segment_detailed(held.images[idx], held.boxes[idx]))
    assert sum(len(v.segments) for v in got) > 0 and sum(v.target.any() for v in got) >= 3
    # ... and not the base model's: fine-tuning changed masks, so the check above can fail.
    before = build_sam_segmenter(checkpoint=str(base), device="cpu").segment_detailed(held.images[idx],
                                                                                       held.boxes[idx])
    with pytest.raises(AssertionError):
        assert_same_views(got, before)
    assert evaluate(tuned, held) == rep["heldout_after"]
    base_dec = load_sam(base).model.mask_decoder.state_dict()
    assert any(not torch.equal(v, base_dec[k]) for k, v in tuned.model.mask_decoder.state_dict().items())
    assert tuned.identity() != build_sam_segmenter(checkpoint=str(base)).identity()
    # The decoder file names the views it was trained on (for the mask-quality report).
    assert selection_keys(tuned.loaded.meta["train_views"]) == set(train.keys)


def test_training_resumes_from_its_snapshot(views, tmp_path):
    train, _ = views
    torch.manual_seed(0)
    model = build_model("small", TINY)
    args = TrainArgs(steps=6, batch_size=2, lr=1e-3, warmup=1, save_every=2)
    calls = []

    def features(idx, fail_at=None):
        calls.append(len(calls))
        if fail_at is not None and len(calls) > fail_at:
            raise KeyboardInterrupt
        x = torch.as_tensor(train.images[idx]).permute(0, 3, 1, 2).float()
        x = torch.nn.functional.interpolate(x, (32, 32), mode="bilinear")
        return model.image_encoder(model.preprocess(x))

    snap = tmp_path / "run.resume"
    with pytest.raises(KeyboardInterrupt):
        train_loop(model, model, lambda i: features(i, fail_at=5), train, args, resume_path=snap,
                   settings={"t": 1}, desc="t")
    assert snap.is_file()
    calls.clear()
    losses = train_loop(model, model, features, train, args, resume_path=snap, settings={"t": 1}, desc="t")
    assert len(calls) == 2 and len(losses) == 6  # resumed at step 4 of 6
    with pytest.raises(ValueError, match="other settings"):
        train_loop(model, model, features, train, args, resume_path=snap, settings={"t": 2}, desc="t")


def test_train_sam_small_command(tiny_world, tmp_path, capsys):
    from uevavd.cli import main

    out = tmp_path / "small.safetensors"
    rc = main(["train-sam-small", str(tiny_world), "--out", str(out), "--steps", "3", "--batch-size", "2",
               "--per-context", "8", "--heldout-per-context", "4", "--img-size", "32", "--embed-dim", "32",
               "--depth", "1", "--heads", "2"])
    assert rc == 0 and out.is_file() and (tmp_path / "small.safetensors.report.json").is_file()
    assert "target_miou" in capsys.readouterr().out
    seg = build_sam_segmenter(checkpoint=str(out))
    loaded = seg.loaded
    assert loaded.model_type == "small" and loaded.meta["config"]["img_size"] == 32
    assert loaded.meta["data_hash"] and loaded.meta["train"]["steps"] == 3
    # The checkpoint names the views it was trained on: the same 8 that split_heldout draws.
    train, _ = split_heldout(tiny_world, per_context=8, heldout_per_context=4, seed=0)
    sel = loaded.meta["train_views"]
    assert selection_keys(sel) == set(train.keys) and len(train.keys) == sel["n"] == 8
    assert sel["per_context"] == 8 and sel["seed"] == 0 and sel["contexts"] == [1]


def test_report_leaves_out_the_training_views(tiny_world, views, base, tmp_path):
    """The mask-quality report's train row is measured on views the model was not trained
    on: the checkpoint's metadata names them (or, for files written before it did, they are
    redrawn from the seed and checked against the data hash)."""
    from uevavd.perception.sam.model import save_decoder
    from uevavd.perception.training.sam.data import load_views, read_manifest, view_selection
    from uevavd.perception.training.sam.report import miou_per_split, training_views

    train, _ = views  # 24 views of context 1, seed 0
    m = read_manifest(tiny_world)
    torch.manual_seed(0)
    model = build_model("small", TINY)
    recorded = tmp_path / "recorded.safetensors"
    save_full(recorded, model, "small", TINY, train_views=view_selection(train))
    keys, how = training_views(load_sam(recorded), m)
    assert keys == set(train.keys) and len(keys) == 24 and how == "recorded"
    left = load_views(m, contexts=[1], per_context=605, seed=123, exclude=keys)
    assert len(left) == 605 - 24 and not set(left.keys) & keys
    seg = build_sam_segmenter(checkpoint=str(recorded), ring_points=2)
    rows = miou_per_split(seg, tiny_world, per_context=2, exclude=keys)
    assert rows["train"]["training_views_left_out"] == 24 and rows["train"]["contexts"] == [1, 31]
    # An older file of ours (no train_views): redrawn from seed and count, verified by hash.
    old = tmp_path / "old.safetensors"
    save_full(old, model, "small", TINY, data_hash=train.digest(), n_train_views=24, train={"seed": 0})
    keys_old, how_old = training_views(load_sam(old), m)
    assert keys_old == keys and "data hash verified" in how_old
    save_full(old, model, "small", TINY, data_hash="0" * 64, n_train_views=24, train={"seed": 0})
    assert training_views(load_sam(old), m)[0] is None
    # A fine-tuned decoder: its own training views and its base's.
    other = train.subset(np.arange(5))
    other.keys = ["031/" + k.split("/", 1)[1] for k in other.keys]
    dec = tmp_path / "dec.safetensors"
    save_decoder(dec, model, load_sam(recorded), train_views=view_selection(other))
    assert training_views(load_sam(dec), m)[0] == keys | set(other.keys)
    # A file that records no training here (an official checkpoint) leaves nothing out.
    torch.save(model.state_dict(), tmp_path / "official.pth")
    assert training_views(load_sam(tmp_path / "official.pth"), m)[0] == set()


@pytest.fixture(scope="module")
def one_context_world(tmp_path_factory):
    """The tiny world with one context scene (605 views of 16 px: a table needs all 605)."""
    from uevavd.testing.worlds import write_tiny_world

    return write_tiny_world(tmp_path_factory.mktemp("one-context"), contexts=(1,), train605=False)


@pytest.fixture(scope="module")
def random_classifier(tmp_path_factory):
    """An untrained resnet18 classifier file (a table needs one; its quality does not matter here)."""
    from uevavd.data.splits import TARGETS
    from uevavd.perception.classifier import write_classifier_file
    from uevavd.perception.weights import make_resnet

    path = tmp_path_factory.mktemp("clf") / "random.safetensors"
    meta = {"arch": "resnet18", "classes": list(TARGETS), "mean": [0.5] * 3, "std": [0.25] * 3}
    return write_classifier_file(path, make_resnet("resnet18", num_classes=len(TARGETS)).state_dict(), meta)


def test_prepare_builds_a_decomposed_table_with_sam(one_context_world, random_classifier, base, tmp_path,
                                                     method_toml):
    """`sam` plugs into `prepare` like any segmenter: the table's features are those of the
    views pre-decomposed with the sam segmenter's masks (fast: tiny SAM, 2 ring points)."""
    from uevavd.data.grid import N_VIEWS
    from uevavd.perception.decompose import decompose, view_seed
    from uevavd.perception.images import read_rgb
    from uevavd.perception.prepare import plan_table, prepare_table
    from uevavd.perception.sam import SamSegmenter
    from uevavd.table import ObservationTable
    from uevavd.testing import check_segmenter

    method = tmp_path / "tiny_sam.toml"
    method.write_text(method_toml.format(decompose="true").replace(
        '{ name = "gt" }', f'{{ name = "sam", checkpoint = "{base}", ring_points = 2, batch_size = 64 }}'))
    path = prepare_table(one_context_world, method, classifier_path=random_classifier, out_dir=tmp_path / "t",
                         workers=1, progress=False)
    t = ObservationTable.load(path, expect_key=path.name)
    assert t.features.shape == (1, N_VIEWS, 512)
    parts = t.meta["config"]["key_parts"]
    assert parts["decompose"] is True and parts["segmenter"].startswith("sam:small:") and ":n2:" in parts["segmenter"]
    # The same components as prepare built them: contract checks, and the features of a few
    # views recomputed from sam's masks (the first image-encoder batch, as in prepare).
    plan = plan_table(one_context_world, method, classifier_path=random_classifier)
    assert plan.key == path.name and isinstance(plan.segmenter, SamSegmenter)
    check_segmenter(plan.segmenter)
    scene, recs = plan.scenes[0]
    images = np.stack([read_rgb(r.image) for r in recs[:64]])
    segs = plan.segmenter.segment(images, np.array([r.box for r in recs[:64]], np.int64))
    idx = [0, 5, 20, 41, 63]
    assert any(segs[i].target.any() for i in idx) and all(segs[i].segments for i in idx)
    decomposed = np.stack([decompose(images[i], segs[i].target, segs[i].segments,
                                     seed=view_seed(plan.gray_seed, scene, recs[i].view, recs[i].target))
                           for i in idx])
    assert not np.array_equal(decomposed, images[idx])
    want = plan.encoder.encode(decomposed)
    got = t.features[0, idx].astype(np.float32)
    scale = float(np.abs(want).max())
    assert np.allclose(got, want, rtol=1e-2, atol=1e-2 * scale)
    raw = plan.encoder.encode(images[idx])
    assert not np.allclose(got, raw, rtol=1e-2, atol=1e-2 * scale)  # the encoder saw decomposed views


@pytest.mark.slow
def test_ibe_map_table_with_the_sam_segmenter(tiny_world, tiny_classifier, base, tmp_path, method_toml):
    """`prepare` builds a pre-decomposed observation table with `sam` like any segmenter."""
    from uevavd.data.grid import N_VIEWS
    from uevavd.perception.prepare import prepare_table
    from uevavd.table import ObservationTable

    method = tmp_path / "tiny_sam.toml"
    method.write_text(method_toml.format(decompose="true").replace(
        '{ name = "gt" }', f'{{ name = "sam", checkpoint = "{base}", ring_points = 4, batch_size = 64 }}'))
    path = prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=tmp_path / "t",
                         progress=False)
    t = ObservationTable.load(path, expect_key=path.name)
    assert t.features.shape == (2, N_VIEWS, 512)
    assert t.meta["config"]["key_parts"]["segmenter"].startswith("sam:small:")

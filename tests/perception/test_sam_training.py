"""Fine-tuning and small-SAM training on the tiny drawn world (tiny models, CPU, seconds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.perception.sam import build_sam_segmenter, load_sam
from uevavd.perception.sam.data import split_heldout
from uevavd.perception.sam.evaluate import evaluate
from uevavd.perception.sam.finetune import finetune
from uevavd.perception.sam.model import SmallConfig, build_model, save_full
from uevavd.perception.sam.training import TrainArgs, train_loop

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


def test_finetune_lowers_loss_and_the_saved_model_gives_the_same_masks(views, base, tmp_path):
    train, held = views
    out = tmp_path / "ft.safetensors"
    args = TrainArgs(steps=30, batch_size=4, lr=3e-3, warmup=1, points_per_view=1, save_every=10)
    rep = finetune(base, train, held, out=out, args=args, device="cpu", embedding_cache=tmp_path / "emb.pt")
    assert rep["loss_last"] < rep["loss_first"]
    assert (tmp_path / "emb.pt").is_file() and not (tmp_path / "ft.safetensors.resume").exists()
    assert {"heldout_before", "heldout_after"} <= set(rep)
    tuned = build_sam_segmenter(checkpoint=str(out), device="cpu")
    assert tuned.loaded.model_type == "small"
    # Same numbers as the in-memory model measured right after training.
    assert evaluate(tuned, held) == rep["heldout_after"]
    base_dec = load_sam(base).model.mask_decoder.state_dict()
    assert any(not torch.equal(v, base_dec[k]) for k, v in tuned.model.mask_decoder.state_dict().items())
    assert tuned.identity() != build_sam_segmenter(checkpoint=str(base)).identity()


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


@pytest.mark.slow
def test_ibe_map_table_with_the_sam_segmenter(tiny_world, tiny_classifier, base, tmp_path, method_toml):
    """`prepare` builds a pre-decomposed observation table with `sam` like any segmenter."""
    from uevavd.data.grid import N_VIEWS
    from uevavd.perception.prepare import prepare_table
    from uevavd.perception.table import ObservationTable

    method = tmp_path / "tiny_sam.toml"
    method.write_text(method_toml.format(decompose="true").replace(
        '{ name = "gt" }', f'{{ name = "sam", checkpoint = "{base}", ring_points = 4, batch_size = 64 }}'))
    path = prepare_table(tiny_world, method, classifier_path=tiny_classifier, out_dir=tmp_path / "t",
                         progress=False)
    t = ObservationTable.load(path, expect_key=path.name)
    assert t.features.shape == (2, N_VIEWS, 512)
    assert t.meta["config"]["key_parts"]["segmenter"].startswith("sam:small:")

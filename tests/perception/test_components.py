"""Contract checks over every registered built-in encoder, classifier and segmenter."""

from __future__ import annotations

import numpy as np
import pytest

from uevavd.perception.segmenters import build_gt
from uevavd.plugins.manager import manager
from uevavd.testing import check_classifier, check_encoder, check_segmenter
from uevavd.testing.perception import sample_ground_truth, sample_images

OTHER_OWNERS = {"sam"}  # tested with its own weights in tests/perception/test_sam*.py


@pytest.mark.parametrize("name", [n for n in manager.registry.names("encoder")])
def test_encoder_contract(name):
    # Lite0's ImageNet weights ship with its package: the contract is checked on the real
    # thing (its random initialisation maps every small image to nearly the same features)
    weights = "imagenet" if name == "efficientnet_lite0" else "random"
    enc = manager.registry.build("encoder", name, weights=weights, seed=0, device="cpu")
    check_encoder(enc)
    assert enc.feature_dim == {"resnet18": 512, "resnet50": 2048}.get(name, enc.feature_dim)


@pytest.mark.parametrize("name", [n for n in manager.registry.names("segmenter") if n not in OTHER_OWNERS])
def test_segmenter_contract(name):
    check_segmenter(manager.registry.build("segmenter", name))


def test_classifier_contract(tiny_classifier, tmp_path):
    from uevavd.data.splits import TARGETS
    from uevavd.perception.classifier import write_classifier_file
    from uevavd.perception.efficientnet import imagenet_backbone
    from uevavd.perception.training.classifier import input_norm

    mean, std = input_norm("efficientnet_lite0")  # an untrained 5-way head on the ImageNet backbone
    lite = write_classifier_file(tmp_path / "lite.safetensors", imagenet_backbone(num_classes=5).state_dict(),
                                 {"arch": "efficientnet_lite0", "classes": list(TARGETS), "mean": list(mean),
                                  "std": list(std)})
    files = {"efficientnet_lite0": lite}
    for name in manager.registry.names("classifier"):
        path = files.get(name, tiny_classifier)
        check_classifier(manager.registry.build("classifier", name, path=str(path), device="cpu"))


def test_gt_segmenter_reads_instances():
    boxes, maps, cats = sample_ground_truth(2, 32)
    out = build_gt().segment(sample_images(2, 32), boxes, instance_maps=maps, categories=cats)
    np.testing.assert_array_equal(out[0].target, maps[0] == 1)
    assert len(out[0].segments) == 2  # building and tree; id 0 ("none") is left uncovered
    with pytest.raises(ValueError, match="ground-truth"):
        build_gt().segment(sample_images(2, 32), boxes)

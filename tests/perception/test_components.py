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
    enc = manager.registry.build("encoder", name, weights="random", seed=0, device="cpu")
    check_encoder(enc)
    assert enc.feature_dim == {"resnet18": 512, "resnet50": 2048}.get(name, enc.feature_dim)


@pytest.mark.parametrize("name", [n for n in manager.registry.names("segmenter") if n not in OTHER_OWNERS])
def test_segmenter_contract(name):
    check_segmenter(manager.registry.build("segmenter", name))


def test_classifier_contract(tiny_classifier):
    for name in manager.registry.names("classifier"):
        check_classifier(manager.registry.build("classifier", name, path=str(tiny_classifier), device="cpu"))


def test_gt_segmenter_reads_instances():
    boxes, maps, cats = sample_ground_truth(2, 32)
    out = build_gt().segment(sample_images(2, 32), boxes, instance_maps=maps, categories=cats)
    np.testing.assert_array_equal(out[0].target, maps[0] == 1)
    assert len(out[0].segments) == 2  # building and tree; id 0 ("none") is left uncovered
    with pytest.raises(ValueError, match="ground-truth"):
        build_gt().segment(sample_images(2, 32), boxes)

"""Frozen torchvision ResNet encoders: images -> global-pooled features (512 / 2048).

Weights (``weights=``): ``"imagenet"`` (torch's cache directory), ``"file:PATH"``,
``"random"`` (seeded by ``seed``, with a logged warning) or ``"classifier"`` (the backbone
of a trained recognizer: ``classifier=PATH``, else the default location for ``data``).
See :mod:`uevavd.perception.weights`.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from .classifier import default_classifier_path, file_weights_hash, read_classifier_file
from .nets import BatchRunner, check_images
from .weights import (
    WeightsError,
    imagenet_path,
    load_state_dict_file,
    load_strict,
    make_resnet,
    parse_spec,
    random_weights_hash,
    state_dict_hash,
)

log = logging.getLogger(__name__)

FEATURE_DIMS = {"resnet18": 512, "resnet34": 512, "resnet50": 2048}


class ResNetEncoder:
    """(N, H, W, 3) uint8 RGB -> (N, feature_dim) float32 pooled ResNet features."""

    def __init__(self, arch: str, model: torch.nn.Module, *, weights_desc: str, weights_hash: str,
                 device: str = "auto", batch_size: int | None = None):
        self.arch = arch
        self.feature_dim = FEATURE_DIMS[arch]
        model.fc = torch.nn.Identity()
        self.runner = BatchRunner(model, device=device, batch_size=batch_size)
        self.weights_desc = weights_desc
        self.weights_hash = weights_hash

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = check_images(images, f"{self.arch} encoder")
        if len(images) == 0:
            return np.zeros((0, self.feature_dim), np.float32)
        return self.runner(images)

    def identity(self) -> str:
        return f"encoder:{self.arch}:{self.weights_desc}:{self.weights_hash}:{self.runner.describe()}"

    def __repr__(self) -> str:
        return f"ResNetEncoder({self.arch}, weights={self.weights_desc}, device={self.runner.device})"


def load_backbone(arch: str, weights: str, *, seed: int = 0, classifier: str | None = None,
                  data: str | None = None) -> tuple[torch.nn.Module, str, str]:
    """``(model with its fc, weights description, weights hash)`` for a weights spec."""
    kind, arg = parse_spec(weights)
    if kind == "random":
        log.warning("%s encoder: random weights (seed %d), not pretrained", arch, seed)
        return make_resnet(arch, seed=seed), f"random:{seed}", random_weights_hash(arch, seed=seed)
    if kind == "classifier":
        path = classifier or (default_classifier_path(data) if data else None)
        if path is None:
            raise WeightsError(
                f"{arch} encoder with weights='classifier' needs classifier=PATH (a file written by "
                "`uevavd train-classifier`) or the dataset (data=ROOT) whose default classifier to use"
            )
        sd, meta = read_classifier_file(path)
        if meta.get("arch") != arch:
            raise WeightsError(f"{path}: a {meta.get('arch')} classifier cannot give a {arch} backbone")
        model = make_resnet(arch, num_classes=len(meta["classes"]), empty=True)
        load_strict(model, sd, arch=arch, source=str(path))
        return model, "classifier", file_weights_hash(sd, meta)
    path = imagenet_path(arch) if kind == "imagenet" else arg
    sd = load_state_dict_file(path)
    num_classes = sd["fc.weight"].shape[0] if "fc.weight" in sd else 1000
    model = make_resnet(arch, num_classes=num_classes, empty=True)
    if "fc.weight" not in sd:  # a bare backbone: a placeholder for the (discarded) fc
        fc = {k: torch.zeros(v.shape) for k, v in model.state_dict().items() if k.startswith("fc.")}
        sd = {**fc, **sd}
    load_strict(model, sd, arch=arch, source=str(path))
    return model, kind, state_dict_hash({k: v for k, v in sd.items() if not k.startswith("fc.")})


def _build(arch: str, weights: str, seed: int, device: str, batch_size: int, classifier: str | None,
           data: str | None) -> ResNetEncoder:
    model, desc, digest = load_backbone(arch, weights, seed=seed, classifier=classifier, data=data)
    return ResNetEncoder(arch, model, weights_desc=desc, weights_hash=digest, device=device,
                         batch_size=batch_size)


def build_resnet18(*, weights: str = "imagenet", seed: int = 0, device: str = "auto", batch_size: int | None = None,
                   classifier: str | None = None, data: str | None = None) -> ResNetEncoder:
    """ResNet18 encoder, 512-d features. ``data`` (dataset root) locates the default
    classifier for ``weights="classifier"``; ``uevavd prepare`` passes it."""
    return _build("resnet18", weights, seed, device, batch_size, classifier, data)


def build_resnet50(*, weights: str = "imagenet", seed: int = 0, device: str = "auto", batch_size: int | None = None,
                   classifier: str | None = None, data: str | None = None) -> ResNetEncoder:
    """ResNet50 encoder, 2048-d features (the paper's encoder)."""
    return _build("resnet50", weights, seed, device, batch_size, classifier, data)

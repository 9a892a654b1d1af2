"""The recognition classifier: a ResNet18 over the five targets, frozen after training.

File format: a ``.safetensors`` state dict of a torchvision ResNet18 with a 5-way ``fc``,
and JSON metadata in the safetensors header under ``"uevavd"``: ``arch``, ``classes``,
``input_size`` (H, W), ``mean``/``std``, ``data_hash`` (the ``train_605`` crops it was
trained on), ``train`` (settings and results). Written by ``uevavd train-classifier``
(:mod:`uevavd.perception.training.classifier`); the pipeline's default location is
``<cache>/classifiers/<data_hash>.safetensors`` (:func:`default_classifier_path`).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_save
from ..data.reader import read_dataset
from ..data.splits import CLASSIFIER_SCENE
from ..hashing import json_digest
from ..paths import cache_dir
from .efficientnet import check_size, fold_lite0, make_lite0
from .nets import BatchRunner, check_images
from .weights import WeightsError, load_state_dict_file, load_strict, make_resnet, state_dict_hash

META_KEY = "uevavd"
FORMAT = "uevavd-classifier/1"


def classifiers_dir() -> Path:
    return cache_dir() / "classifiers"


def train_records(manifest) -> list:
    """The unoccluded ``train_605`` records the classifier trains on (in manifest order)."""
    recs = [r for r in manifest.records if r.scene == CLASSIFIER_SCENE]
    if not recs:
        raise ValueError(
            f"{manifest.root}: no {CLASSIFIER_SCENE!r} scene; the classifier trains on its unoccluded crops"
        )
    return recs


def data_hash(records) -> str:
    """16-hex sha256 over the names, targets, views and bytes of the training images."""
    h = hashlib.sha256()
    for r in sorted(records, key=lambda r: (r.target, r.view, r.image.name)):
        h.update(f"{r.target}:{r.view}:{r.image.name}:".encode())
        h.update(hashlib.sha256(Path(r.image).read_bytes()).digest())
    return h.hexdigest()[:16]


def classifier_cache_path(data_digest: str, recipe: Any = None) -> Path:
    """The one naming rule of recognizer files in the cache, for the ``train_605`` crops of
    digest ``data_digest``: with ``recipe`` (a ClassifierRecipe), where a recognizer of that
    recipe is cached, ``<cache>/classifiers/<data>-<recipe>.safetensors`` (what ``uevavd
    ablate`` and :func:`uevavd.api.train_classifier` reuse, so a regenerated world or another
    recipe never reuses an old recognizer); without, the dataset's default recognizer,
    ``<cache>/classifiers/<data>.safetensors`` (what ``uevavd train-classifier`` writes when
    given no ``--out``, and ``uevavd prepare`` reads when given no ``--classifier``)."""
    if recipe is None:
        return classifiers_dir() / f"{data_digest}.safetensors"
    return classifiers_dir() / f"{data_digest}-{json_digest(recipe.__dict__, 12)}.safetensors"


def default_classifier_path(data: str | os.PathLike[str]) -> Path:
    """Where ``uevavd train-classifier`` puts, and the pipeline looks for, the classifier of
    dataset ``data`` (a root folder): ``<cache>/classifiers/<data_hash>.safetensors``."""
    return classifier_cache_path(data_hash(train_records(read_dataset(data))))


def write_classifier_file(path: str | os.PathLike[str], state_dict: Mapping[str, torch.Tensor],
                          meta: Mapping[str, Any]) -> Path:
    """Save state dict + metadata as safetensors, atomically."""
    from safetensors.torch import save_file

    meta = {"format": FORMAT, **meta}
    tensors = {k: v.detach().cpu().contiguous() for k, v in state_dict.items()}
    return atomic_save(path, lambda tmp: save_file(tensors, tmp, metadata={META_KEY: json.dumps(meta, sort_keys=True)}))


def read_classifier_file(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``(state dict, metadata)`` of a classifier file; a clear error when it is not one."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise WeightsError(
            f"classifier file {path} does not exist; train one with `uevavd train-classifier DATA --out {path}`"
        )
    sd = load_state_dict_file(path) if path.suffix == ".safetensors" else None
    if sd is None:
        raise WeightsError(f"{path}: a classifier file must be .safetensors (written by `uevavd train-classifier`)")
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as fh:
        raw = (fh.metadata() or {}).get(META_KEY)
    try:
        meta = json.loads(raw) if raw else None
    except json.JSONDecodeError:
        meta = None
    if not isinstance(meta, dict) or not {"arch", "classes", "mean", "std"} <= set(meta):
        raise WeightsError(
            f"{path}: no uevavd classifier metadata (arch, classes, mean, std) in its header; "
            "it was not written by `uevavd train-classifier`"
        )
    # the weights against the hash written with them: a cached recognizer with one flipped
    # exponent bit was reused (train accuracy 0.78 -> 0.92)
    written = _written_hash(meta)
    if written is not None and state_dict_hash(sd) != written:
        raise WeightsError(f"{path}: damaged (its weights no longer match the weights_hash written with them); "
                           "delete it: the pipeline trains it again (or `uevavd zoo check` restores the zoo's)")
    return sd, meta


def _written_hash(meta: dict[str, Any]) -> str | None:
    return (meta.get("train") or {}).get("weights_hash") if isinstance(meta.get("train"), dict) else None


def file_weights_hash(sd: dict[str, torch.Tensor], meta: dict[str, Any]) -> str:
    """The weights hash of a classifier file read by :func:`read_classifier_file`: the one
    written with it (which that read checked against the weights), or computed for a file
    written without one."""
    return _written_hash(meta) or state_dict_hash(sd)


class ResNetClassifier:
    """(N, H, W, 3) uint8 RGB -> (N, len(classes)) float32 softmax probabilities."""

    def __init__(self, model: torch.nn.Module, *, arch: str, classes: tuple[str, ...], mean, std,
                 weights_hash: str, device: str = "auto", batch_size: int | None = None, meta=None):
        self.arch = arch
        self.classes = tuple(classes)
        self.weights_hash = weights_hash
        self.meta = dict(meta or {})
        lite = arch == "efficientnet_lite0"
        if lite:  # torch.fx cannot fold its batch norms: fold them here
            model = fold_lite0(model)
        self.runner = BatchRunner(model, device=device, batch_size=batch_size, mean=tuple(mean), std=tuple(std),
                                  post=lambda y: torch.softmax(y, dim=1), fold=not lite)

    def predict_proba(self, images: np.ndarray) -> np.ndarray:
        images = check_images(images, f"{self.arch} classifier")
        if self.arch == "efficientnet_lite0":
            check_size(images, f"{self.arch} classifier")
        if len(images) == 0:
            return np.zeros((0, len(self.classes)), np.float32)
        p = self.runner(images)
        return p / p.sum(axis=1, keepdims=True)

    def identity(self) -> str:
        return f"classifier:{self.arch}:{','.join(self.classes)}:{self.weights_hash}:{self.runner.describe()}"

    def shares_backbone(self, encoder: Any) -> bool:
        """True when ``encoder`` is this recognizer's own backbone (``weights="classifier"``
        from the same file) run with the same preprocessing on the same device: then one
        forward pass gives both the features and, through :meth:`proba_from_features`, the
        probabilities."""
        runner = getattr(encoder, "runner", None)
        return (getattr(encoder, "arch", None) == self.arch
                and getattr(encoder, "weights_desc", None) == "classifier"
                and getattr(encoder, "weights_hash", None) == self.weights_hash
                and runner is not None and runner.mean == self.runner.mean and runner.std == self.runner.std
                and runner.device == self.runner.device)

    def proba_from_features(self, features: np.ndarray) -> np.ndarray:
        """(N, D) float pooled backbone features -> (N, K) float32 probabilities through
        this classifier's ``fc`` (what :meth:`predict_proba` computes after the backbone)."""
        fc = self.runner.model.fc if hasattr(self.runner.model, "fc") else self.runner.model._fc
        with torch.inference_mode():
            x = torch.as_tensor(np.asarray(features, np.float32), device=fc.weight.device)
            p = torch.softmax(fc(x), dim=1).cpu().numpy().astype(np.float32, copy=False)
        return p / p.sum(axis=1, keepdims=True)

    def __repr__(self) -> str:
        return f"ResNetClassifier({self.arch}, classes={self.classes}, device={self.runner.device})"


def make_recognizer(arch: str, *, num_classes: int, seed: int = 0, empty: bool = False) -> torch.nn.Module:
    """An untrained recognizer network of a supported architecture (a torchvision ResNet or
    EfficientNet-Lite0), ``num_classes`` outputs."""
    if arch == "efficientnet_lite0":
        return make_lite0(num_classes=num_classes, seed=seed)
    return make_resnet(arch, num_classes=num_classes, seed=seed, empty=empty)


def load_classifier(path: str | os.PathLike[str], *, device: str = "auto", batch_size: int | None = None) -> ResNetClassifier:
    sd, meta = read_classifier_file(path)
    arch = meta["arch"]
    model = make_recognizer(arch, num_classes=len(meta["classes"]), empty=True)
    if arch == "efficientnet_lite0":
        try:
            model.load_state_dict(sd, strict=True)
        except RuntimeError as exc:
            raise WeightsError(f"{path}: cannot load into {arch} ({str(exc).splitlines()[0]})") from None
        model.eval()
    else:
        load_strict(model, sd, arch=arch, source=str(path))
    return ResNetClassifier(model, arch=arch, classes=tuple(meta["classes"]), mean=meta["mean"], std=meta["std"],
                            weights_hash=file_weights_hash(sd, meta), device=device, batch_size=batch_size, meta=meta)


def build_resnet18_classifier(*, path: str | None = None, device: str = "auto", batch_size: int | None = None,
                              data: str | None = None) -> ResNetClassifier:
    """The trained ResNet18 recognizer from ``path``; ``path=None`` means the default
    location for dataset ``data`` (``uevavd prepare`` passes it)."""
    return _build_classifier("resnet18", path, device, batch_size, data)


def build_efficientnet_lite0_classifier(*, path: str | None = None, device: str = "auto", batch_size: int | None = None,
                                        data: str | None = None) -> ResNetClassifier:
    """The trained EfficientNet-Lite0 recognizer from ``path`` (as :func:`build_resnet18_classifier`)."""
    return _build_classifier("efficientnet_lite0", path, device, batch_size, data)


def _build_classifier(arch: str, path: str | None, device: str, batch_size: int, data: str | None):
    if path is None:
        if data is None:
            raise WeightsError(
                f"classifier {arch}: no path given and no dataset to find the default one; pass "
                "path=FILE (from `uevavd train-classifier DATA --out FILE`)"
            )
        default = default_classifier_path(data)
        if not default.is_file():
            raise WeightsError(
                f"no trained classifier for dataset {data}: expected {default}. Run "
                f"`uevavd train-classifier {data} --out {default}` first (or pass --classifier FILE)"
            )
        path = str(default)
    clf = load_classifier(path, device=device, batch_size=batch_size)
    if clf.arch != arch:
        raise WeightsError(f"{path}: a {clf.arch} classifier, but the {arch!r} classifier was asked for; set "
                           f"[perception.classifier] name = {clf.arch!r} (--set perception.classifier.name={clf.arch})")
    return clf

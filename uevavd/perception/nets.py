"""Batched inference shared by the encoders and the classifier.

Images are fed at their own size (the crops are 64-256 px; no resize), normalised with
the ImageNet mean/std the torchvision weights use, channels-last, under
``torch.inference_mode``; on a GPU with bf16 autocast. Batch norms are folded into the
convolutions before them (``torch.fx.experimental.optimization.fuse``; the same function
up to float rounding; the ResNet18 forward at 64 px was 13-24 % faster on the development
CPU). ``torch.set_num_threads`` is left to the caller.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from ..runtime import resolve_device

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def check_images(images: np.ndarray, where: str) -> np.ndarray:
    """Validate (N, H, W, 3) uint8 RGB."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"{where}: expected (N, H, W, 3) uint8 RGB images, got {images.shape} {images.dtype}")
    return images


def fold_batchnorm(model: torch.nn.Module) -> torch.nn.Module:
    """An inference copy of ``model`` (in eval mode) with every conv -> batch-norm pair folded
    into one conv, via torch.fx; ``model`` itself is left as it is. A model torch.fx cannot
    trace (a plugin's, say) is returned unchanged, with a debug message."""
    from torch.fx.experimental.optimization import fuse

    try:
        fused = fuse(model)
    except Exception as err:  # noqa: BLE001 - any tracing failure: run the model as given
        log.debug("batch norms not folded (%s: %s); running %s as given", type(err).__name__, err,
                  type(model).__name__)
        return model
    return fused.eval()


class BatchRunner:
    """Runs ``model`` over uint8 image batches; returns float32 numpy outputs.

    ``post`` maps the model's float output tensor (N, C) to what the caller wants
    (e.g. a softmax), applied in float32.
    """

    def __init__(self, model: torch.nn.Module, *, device: str = "auto", batch_size: int = 256,
                 mean: tuple[float, ...] = IMAGENET_MEAN, std: tuple[float, ...] = IMAGENET_STD,
                 post=None, fold: bool = True):
        if int(batch_size) < 1:
            raise ValueError(f"batch_size={batch_size}: expected a positive integer")
        self.device = resolve_device(device)
        self.batch_size = int(batch_size)
        self._given, self._fold, self._model = model.eval(), fold, None
        shape = (1, 3, 1, 1)
        self._scale = (1.0 / (255.0 * torch.tensor(std))).view(shape).to(self.device)
        self._shift = (-torch.tensor(mean) / torch.tensor(std)).view(shape).to(self.device)
        self.post = post
        self.mean, self.std = tuple(mean), tuple(std)

    @property
    def model(self) -> torch.nn.Module:
        """The network run, made ready at first use (batch norms folded, on the device, no
        gradients): a component built only for its identity, as for a table found in the
        cache, never pays for the folding."""
        if self._model is None:
            model = fold_batchnorm(self._given) if self._fold else self._given
            model = model.to(self.device, memory_format=torch.channels_last)
            for p in model.parameters():
                p.requires_grad_(False)
            self._model, self._given = model, None
        return self._model

    def to_input(self, batch: np.ndarray) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> normalised (N, 3, H, W) float32, channels-last, on device."""
        x = torch.from_numpy(np.ascontiguousarray(batch)).to(self.device, non_blocking=True)
        x = x.permute(0, 3, 1, 2).float()
        x = x * self._scale + self._shift
        return x.contiguous(memory_format=torch.channels_last)

    def __call__(self, images: np.ndarray) -> np.ndarray:
        outs = []
        with torch.inference_mode():
            for i in range(0, len(images), self.batch_size):
                x = self.to_input(images[i : i + self.batch_size])
                if self.device.type == "cuda":
                    with torch.autocast("cuda", dtype=torch.bfloat16):
                        y = self.model(x)
                else:
                    y = self.model(x)
                y = y.float()
                if self.post is not None:
                    y = self.post(y)
                outs.append(y.cpu().numpy())
        if not outs:
            return np.zeros((0, 0), np.float32)
        return np.concatenate(outs).astype(np.float32, copy=False)

    def describe(self) -> str:
        precision = "bf16" if self.device.type == "cuda" else "fp32"
        return f"mean={list(self.mean)},std={list(self.std)},no-resize,{precision}"

"""Batched inference shared by the encoders and the classifier.

Images are fed at their own size (the crops are 64-256 px; no resize), normalised with
the ImageNet mean/std the torchvision weights use, channels-last, under
``torch.inference_mode``; on a GPU with bf16 autocast. On a CPU a batch holds
:data:`CPU_BATCH_PIXELS` pixels by default (64 views of 64 px, 4 of 256 px): its activations
then stay in the cache, and the forward ran 1.2-2.2x faster than in batches of 256
(``benchmarks/bench_batch.py``); a view's output does not depend on its batch. Batch norms
are folded into the convolutions before them (``torch.fx.experimental.optimization.fuse``; the same function
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
#: Pixels per batch on a CPU when the caller names no batch size (see the module's docstring).
CPU_BATCH_PIXELS = 64 * 64 * 64
#: Images per batch on a GPU when the caller names no batch size.
GPU_BATCH = 256


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

    def __init__(self, model: torch.nn.Module, *, device: str = "auto", batch_size: int | None = None,
                 mean: tuple[float, ...] = IMAGENET_MEAN, std: tuple[float, ...] = IMAGENET_STD,
                 post=None, fold: bool = True):
        if batch_size is not None and (isinstance(batch_size, bool) or int(batch_size) < 1):
            raise ValueError(f"batch_size={batch_size}: expected a positive integer (or none: chosen by the "
                             "images' size)")
        self.device = resolve_device(device)
        self.batch_size = None if batch_size is None else int(batch_size)
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

    def batch_of(self, images: np.ndarray) -> int:
        """Images per batch for ``images`` (N, H, W, 3): the batch size given, else
        :data:`GPU_BATCH` on a GPU and :data:`CPU_BATCH_PIXELS` pixels' worth on a CPU."""
        if self.batch_size is not None:
            return self.batch_size
        if self.device.type != "cpu":
            return GPU_BATCH
        return max(1, CPU_BATCH_PIXELS // max(1, int(images.shape[1]) * int(images.shape[2])))

    def __call__(self, images: np.ndarray) -> np.ndarray:
        outs = []
        step = self.batch_of(images)
        with torch.inference_mode():
            for i in range(0, len(images), step):
                x = self.to_input(images[i : i + step])
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

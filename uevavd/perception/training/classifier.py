"""Training the recognition classifier (``uevavd train-classifier``).

A torchvision ResNet18 (the paper's recognizer) or an EfficientNet-Lite0 on the unoccluded
``train_605`` crops of the five targets (``ClassifierRecipe.arch``). A share
of the *viewpoints* (the same views for every target) is held out for validation.
Augmentation keeps the task honest: photometric jitter (brightness, contrast,
saturation), small shifts and scale; no flips or rotations (orientation is fixed by the
camera model). Initial weights (``ClassifierRecipe.init``): ImageNet (ResNet18: when the user
names a file or torch's cache has it, else random with a logged warning; Lite0: from its
installed package), or random.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ...atomic import atomic_save, check_writable
from ...data.reader import read_dataset
from ...data.splits import TARGETS
from ...hashing import sha256_hex
from ...runtime import resolve_device, torch_threads
from ..classifier import classifier_cache_path, data_hash, train_records, write_classifier_file
from ..efficientnet import LITE0_FILE, LITE_MEAN, LITE_STD, check_size, imagenet_backbone, make_lite0
from ..images import Decoder
from ..nets import IMAGENET_MEAN, IMAGENET_STD
from ..weights import (
    WeightsError,
    imagenet_path,
    load_state_dict_file,
    load_strict,
    make_resnet,
    state_dict_hash,
)
from .recipe import ARCHS as ARCHS
from .recipe import THREADS as THREADS
from .recipe import ClassifierRecipe as ClassifierRecipe
from .report import visibility_report

log = logging.getLogger(__name__)


def split_views(n_views: int, val_fraction: float, seed: int) -> np.ndarray:
    """Sorted int64 view indices held out for validation (seeded; the same for every target)."""
    k = max(1, round(val_fraction * n_views))
    return np.sort(np.random.default_rng(seed).choice(n_views, size=k, replace=False)).astype(np.int64)


def sample_views(views: np.ndarray, settings: ClassifierRecipe) -> np.ndarray:
    """The viewpoints used for training + validation: all, or a seeded ``max_views`` sample."""
    if settings.max_views is None or settings.max_views >= len(views):
        return views
    rng = np.random.default_rng(settings.seed + 1)
    return np.sort(rng.choice(views, settings.max_views, replace=False))


def input_norm(arch: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The (mean, std) an architecture's ImageNet weights expect, on [0, 1] RGB."""
    if arch == "efficientnet_lite0":
        return LITE_MEAN, LITE_STD
    return IMAGENET_MEAN, IMAGENET_STD


def initial_model(imagenet: str | None, n_classes: int, seed: int, *, arch: str = "resnet18",
                  init: str = "imagenet") -> tuple[torch.nn.Module, str]:
    """A recognizer with a fresh ``n_classes`` head; backbone from ImageNet when asked and
    available (ResNet18: ``imagenet`` file or torch's cache; Lite0: its package)."""
    if arch == "efficientnet_lite0":
        if init == "random":
            return make_lite0(num_classes=n_classes, seed=seed), f"random:{seed}"
        return imagenet_backbone(num_classes=n_classes, seed=seed), f"imagenet:{LITE0_FILE}"
    model = make_resnet("resnet18", num_classes=n_classes, seed=seed)
    if init == "random":
        return model, f"random:{seed}"
    path: Path | None = Path(imagenet) if imagenet else None
    if path is None:
        try:
            path = imagenet_path("resnet18")
        except WeightsError:
            log.warning("train-classifier: no ImageNet ResNet18 file in torch's cache; starting from random "
                        "weights (seed %d). Pass --imagenet FILE to start from ImageNet.", seed)
            return model, f"random:{seed}"
    sd = load_state_dict_file(path)
    head = {k: v for k, v in model.state_dict().items() if k.startswith("fc.")}
    backbone = {k: v for k, v in sd.items() if not k.startswith("fc.")}
    load_strict(model, {**backbone, **head}, arch="resnet18", source=str(path))
    return model, f"imagenet:{path.name}"


def augment(x: torch.Tensor, s: ClassifierRecipe, gen: torch.Generator) -> torch.Tensor:
    """(N, 3, H, W) float in [0, 1] -> jittered, shifted and scaled copy (no flips/rotations)."""
    n = x.shape[0]

    def u(lo, hi):
        return lo + (hi - lo) * torch.rand(n, 1, 1, 1, generator=gen)

    j = s.jitter
    gray = x.mean(dim=1, keepdim=True)
    x = gray + (x - gray) * u(1 - j, 1 + j)  # saturation
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = mean + (x - mean) * u(1 - j, 1 + j)  # contrast
    x = (x * u(*s.brightness)).clamp(0, 1)  # brightness
    zoom = u(1 - s.scale, 1 + s.scale).view(n)
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0 / zoom
    theta[:, :, 2] = (torch.rand(n, 2, generator=gen) * 2 - 1) * 2 * s.shift
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)


def _normalise(x: torch.Tensor, norm=(IMAGENET_MEAN, IMAGENET_STD)) -> torch.Tensor:
    mean = torch.tensor(norm[0]).view(1, 3, 1, 1)
    std = torch.tensor(norm[1]).view(1, 3, 1, 1)
    return ((x - mean) / std).contiguous(memory_format=torch.channels_last)


def _to_float(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)


@torch.inference_mode()
def predict(model: torch.nn.Module, images: np.ndarray, batch_size: int = 256, *,
            norm=(IMAGENET_MEAN, IMAGENET_STD)) -> np.ndarray:
    """(N, H, W, 3) uint8 -> (N, K) float32 probabilities (eval mode, on the model's device,
    returned on the CPU); ``norm``: the (mean, std) of :func:`input_norm`."""
    model.eval()
    dev = next(model.parameters()).device
    out = [torch.softmax(model(_normalise(_to_float(images[i : i + batch_size]), norm).to(dev)), 1).cpu()
           for i in range(0, len(images), batch_size)]
    return torch.cat(out).numpy() if out else np.zeros((0, 0), np.float32)


def fit(images: np.ndarray, labels: np.ndarray, views: np.ndarray, settings: ClassifierRecipe, *,
        imagenet: str | None = None, n_classes: int = len(TARGETS), progress: bool = True,
        device: str = "auto", threads: int | None = THREADS, checkpoint: Path | None = None):
    """Train on (N, H, W, 3) uint8 crops with (N,) int class labels and (N,) view indices.

    Returns ``(model, info)``; ``info`` holds the held-out views, clean validation accuracy,
    per-epoch history and the initial weights used. Reproducible: torch's global generator
    (which layers such as dropout and Lite0's drop-connect draw from, and which torch seeds
    at random in every process) is seeded from ``settings.seed`` for the call and restored
    after it. ``device`` ("cpu", "cuda", "auto") runs the forward and backward passes there;
    batches and their augmentation are drawn on the CPU either way, so both devices see the
    same images, and the model comes back on the CPU. On the CPU it trains on ``threads``
    torch threads (default :data:`THREADS`; ``None``: torch's current setting), restored
    after; ``info["threads"]`` records the count (``None`` on a GPU) and ``info["kernels"]`` torch's
    CPU kernel set (``AVX512``, ``AVX2``, ...) or the GPU's name. ``checkpoint``: a file
    the training state is saved to after each epoch and resumed from (when it holds a training
    of the same data and recipe), to the weights of an uninterrupted training.
    """
    dev = resolve_device(device)
    cpu_threads = threads if dev.type == "cpu" else None
    with torch.random.fork_rng(devices=[]), torch_threads(cpu_threads):
        torch.manual_seed(int(settings.seed) + 12345)
        model, info = _fit(images, labels, views, settings, imagenet=imagenet, n_classes=n_classes,
                           progress=progress, device=dev, checkpoint=checkpoint)
        info["threads"] = torch.get_num_threads() if dev.type == "cpu" else None
        # the kernels it trained with: the same recipe on another CPU family or GPU may train other weights
        info["kernels"] = torch.backends.cpu.get_cpu_capability() if dev.type == "cpu" else torch.cuda.get_device_name(dev)
    return model, info


def _fit(images: np.ndarray, labels: np.ndarray, views: np.ndarray, settings: ClassifierRecipe, *,
         imagenet: str | None, n_classes: int, progress: bool, device: torch.device, checkpoint: Path | None):
    from tqdm.auto import tqdm

    settings.check()
    images, labels, views = np.asarray(images), np.asarray(labels, np.int64), np.asarray(views, np.int64)
    if settings.arch == "efficientnet_lite0":
        check_size(images, "training the efficientnet_lite0 recognizer")
    all_views = sample_views(np.unique(views), settings)
    val_views = all_views[split_views(len(all_views), settings.val_fraction, settings.seed)]
    is_val = np.isin(views, val_views)
    used = np.isin(views, all_views)
    tr, va = np.flatnonzero(used & ~is_val), np.flatnonzero(is_val)
    if len(tr) == 0 or len(va) == 0:
        raise ValueError(f"{len(images)} crops leave {len(tr)} for training and {len(va)} for validation")
    model, init = initial_model(imagenet, n_classes, settings.seed, arch=settings.arch, init=settings.init)
    norm = input_norm(settings.arch)
    model = model.to(device=device, memory_format=torch.channels_last)
    gen = torch.Generator().manual_seed(settings.seed)
    steps_per_epoch = math.ceil(len(tr) / settings.batch_size)
    total = settings.epochs * steps_per_epoch
    opt = torch.optim.AdamW(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=settings.lr, total_steps=total, pct_start=0.2)
    history: list[dict] = []
    key = sha256_hex(b"".join([repr((asdict(settings), imagenet, n_classes, init, str(device))).encode(),
                               images.tobytes(), labels.tobytes(), views.tobytes()]))
    start = _resume(checkpoint, key, model, opt, sched, gen, history)
    bar = tqdm(total=total, initial=start * steps_per_epoch, desc="train-classifier", unit="batch",
               disable=not progress)
    t0 = time.perf_counter()
    for epoch in range(start, settings.epochs):
        model.train()
        order = tr[torch.randperm(len(tr), generator=gen).numpy()]
        losses = []
        for i in range(0, len(order), settings.batch_size):
            idx = order[i : i + settings.batch_size]
            x = _normalise(augment(_to_float(images[idx]), settings, gen), norm).to(device, non_blocking=True)
            loss = F.cross_entropy(model(x), torch.from_numpy(labels[idx]).to(device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.3f}")
        acc = float((predict(model, images[va], norm=norm).argmax(1) == labels[va]).mean())
        history.append({"epoch": epoch + 1, "loss": float(np.mean(losses)), "val_accuracy": acc})
        bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses):.3f}", val_acc=f"{acc:.3f}")
        if checkpoint is not None and epoch + 1 < settings.epochs:
            state = {"key": key, "epoch": epoch + 1, "history": history, "model": model.state_dict(),
                     "opt": opt.state_dict(), "sched": sched.state_dict(), "gen": gen.get_state(),
                     "rng": torch.random.get_rng_state()}
            atomic_save(checkpoint, lambda tmp, state=state: torch.save(state, tmp))
    bar.close()
    model = model.cpu().eval()
    info = {
        "init": init,
        "val_views": val_views.tolist(),
        "n_train": len(tr),
        "n_val": len(va),
        "val_accuracy": history[-1]["val_accuracy"],
        "history": history,
        "seconds": round(time.perf_counter() - t0, 1),
        "settings": asdict(settings),
        "weights_hash": state_dict_hash(model.state_dict()),
    }
    return model, info


def _resume(checkpoint: Path | None, key: str, model, opt, sched, gen: torch.Generator, history: list) -> int:
    """The epochs done by the training ``checkpoint`` holds, its state loaded into ``model``,
    ``opt``, ``sched``, ``gen``, torch's global generator and ``history``; 0 when it holds
    none of this data and recipe (or cannot be read: the training starts over)."""
    if checkpoint is None or not Path(checkpoint).is_file():
        return 0
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a damaged checkpoint costs its epochs, nothing else
        log.warning("%s: unreadable (%s); training the recognizer from its start", checkpoint, exc)
        return 0
    if not isinstance(state, dict) or state.get("key") != key:
        return 0
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    sched.load_state_dict(state["sched"])
    gen.set_state(state["gen"])
    torch.random.set_rng_state(state["rng"])
    history += state["history"]
    return int(state["epoch"])


def train_classifier(data: str | Path, out: str | Path | None = None, *, settings: ClassifierRecipe | None = None,
                     imagenet: str | None = None, workers: int = 2, report_views: int = 3000,
                     progress: bool = True, device: str = "auto", threads: int | None = THREADS) -> Path:
    """Train on ``data``'s ``train_605`` crops, write the classifier file (safetensors) and
    its report (``<out>.md`` and ``<out>.png``) beside it. ``out=None`` writes to the
    default location the pipeline reads (:func:`default_classifier_path`). Returns ``out``.
    ``device``: where the network trains ("auto": CUDA when present); ``threads``: torch CPU
    threads on the CPU; see :func:`fit`."""
    settings = settings or ClassifierRecipe()
    manifest = read_dataset(data)
    recs = train_records(manifest)
    digest = data_hash(recs)
    out = Path(out) if out is not None else classifier_cache_path(digest)
    if out.suffix != ".safetensors":
        raise ValueError(f"--out {out}: the classifier is written as safetensors; name it *.safetensors")
    check_writable(out)  # before the minutes of training, not after
    used = set(sample_views(np.unique([r.view for r in recs]), settings).tolist())
    recs = [r for r in recs if r.view in used]
    with Decoder(workers) as dec:
        images = dec.images([r.image for r in recs])
        labels = np.array([TARGETS.index(r.target) for r in recs], np.int64)
        views = np.array([r.view for r in recs], np.int64)
        partial = out.parent / f".{out.name}.partial.pt"  # the epochs a killed training had done
        model, info = fit(images, labels, views, settings, imagenet=imagenet, progress=progress, device=device,
                          threads=threads, checkpoint=partial)
        meta = {
            "arch": settings.arch,
            "classes": list(TARGETS),
            "input_size": list(images.shape[1:3]),
            "mean": list(input_norm(settings.arch)[0]),
            "std": list(input_norm(settings.arch)[1]),
            "data_hash": digest,
            "data_root": str(Path(data).resolve()),
            "train": {k: v for k, v in info.items() if k != "val_views"},
            "val_views": info["val_views"],
        }
        path = write_classifier_file(out, model.state_dict(), meta)
        partial.unlink(missing_ok=True)
        visibility_report(model, manifest, path, info, decoder=dec, max_views=report_views, seed=settings.seed)
    return path

"""Weights resolution for the perception networks, in one place. Nothing here downloads.

Order of precedence (as timm resolves pretrained weights): an explicit state dict, then a
local file, then torch's cache directory (:func:`uevavd.paths.torch_hub_dir`, with the
file names torchvision's weights enums give, e.g. ``resnet18-f37072fd.pth``).

Weights specs (strings a method TOML may set):

* ``"imagenet"``: the torchvision ImageNet file from torch's cache directory;
* ``"file:PATH"``: a state dict file (``.pth`` / ``.pt`` via ``torch.load(weights_only=True)``,
  or ``.safetensors``);
* ``"random"``: seeded random initialisation (a logged warning says so);
* ``"classifier"``: the backbone of a classifier trained by ``uevavd train-classifier``.

Every file is loaded with ``map_location="cpu"`` and ``weights_only=True`` (a pickle that
would run code is refused, never executed), checked against the sha256 prefix embedded
in torchvision file names, and loaded strictly: a file for another architecture is an
error naming both.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import re
from collections.abc import Mapping
from pathlib import Path

import torch

from ..hashing import file_sha256
from ..paths import torch_hub_dir

log = logging.getLogger(__name__)

#: torchvision's ImageNet file names per architecture (first = preferred when several exist).
IMAGENET_FILES: dict[str, tuple[str, ...]] = {
    "resnet18": ("resnet18-f37072fd.pth",),
    "resnet34": ("resnet34-b627a593.pth",),
    "resnet50": ("resnet50-0676ba61.pth", "resnet50-11ad3fa6.pth"),
}
IMAGENET_URLS = "https://download.pytorch.org/models/"
_HASH_IN_NAME = re.compile(r"-([0-9a-f]{8,64})\.[A-Za-z]+$")


class WeightsError(ValueError):
    """A weights file is missing, unreadable, unsafe, or for another architecture."""


def parse_spec(spec: str) -> tuple[str, str | None]:
    """``"file:PATH"`` -> ``("file", "PATH")``; ``"imagenet"`` -> ``("imagenet", None)``."""
    kind, sep, arg = str(spec).partition(":")
    kind = kind.strip().lower()
    if kind not in ("imagenet", "random", "file", "classifier"):
        raise WeightsError(
            f"weights {spec!r}: expected 'imagenet', 'random', 'file:PATH' or 'classifier'"
        )
    if kind == "file" and not arg:
        raise WeightsError(f"weights {spec!r}: 'file:' needs a path, e.g. file:/models/resnet50.pth")
    return kind, (arg or None)


def imagenet_path(arch: str) -> Path:
    """The torch-cache file of an architecture's ImageNet weights; an error naming the
    expected path and how to get it when absent."""
    names = IMAGENET_FILES.get(arch)
    if not names:
        raise WeightsError(f"no ImageNet weights known for architecture {arch!r}; use weights='file:PATH'")
    hub = torch_hub_dir()
    for name in names:
        if (hub / name).is_file():
            return hub / name
    raise WeightsError(
        f"ImageNet weights for {arch} not found: expected {hub / names[0]}. uevavd never downloads; "
        f"fetch {IMAGENET_URLS}{names[0]} on a machine with internet and copy it there "
        f"(or set TORCH_HOME), or pass weights='file:PATH', or weights='random'"
    )


def check_name_hash(path: Path) -> None:
    """torchvision file names embed a sha256 prefix (``resnet18-f37072fd.pth``); check it."""
    m = _HASH_IN_NAME.search(path.name)
    if not m or not path.name.startswith(tuple(IMAGENET_FILES)):
        return
    digest = file_sha256(path)
    if not digest.startswith(m.group(1)):
        raise WeightsError(
            f"{path}: sha256 {digest[:12]}... does not match the prefix {m.group(1)} in its name; "
            "the file is corrupt or truncated: fetch it again"
        )


def load_state_dict_file(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a state dict safely (tensors only; never runs pickled code)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise WeightsError(f"weights file {path} does not exist; pass an existing .pth/.safetensors file")
    if path.suffix == ".safetensors":
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            sd = load_file(str(path), device="cpu")
        except (SafetensorError, OSError, ValueError) as exc:
            raise WeightsError(f"{path}: not a readable safetensors file ({exc}); it may be truncated") from None
    else:
        check_name_hash(path)
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any failure: the file is unusable
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if "weights_only" in str(exc) or "Unsupported" in str(exc) or "pickle" in str(exc).lower():
                raise WeightsError(
                    f"{path}: refused: the file holds pickled objects other than tensors (it could run "
                    f"code when loaded), so it was not executed ({text}). Save a plain state dict "
                    "(torch.save(model.state_dict(), f)) or a .safetensors file"
                ) from None
            raise WeightsError(f"{path}: cannot read weights ({text}); the file may be truncated") from None
    if isinstance(sd, Mapping) and "state_dict" in sd and isinstance(sd["state_dict"], Mapping):
        sd = sd["state_dict"]
    if not isinstance(sd, Mapping) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise WeightsError(f"{path}: expected a state dict (name -> tensor), got {type(sd).__name__}")
    return {str(k).removeprefix("module."): v for k, v in sd.items()}


def detect_arch(sd: Mapping[str, torch.Tensor]) -> str:
    """Best guess of the ResNet architecture a state dict belongs to."""
    if "layer3.0.conv1.weight" not in sd:
        return "an unknown (non-ResNet) architecture"
    blocks = len({k.split(".")[1] for k in sd if k.startswith("layer3.")})
    bottleneck = "layer1.0.conv3.weight" in sd
    names = {(False, 2): "resnet18", (False, 6): "resnet34", (True, 6): "resnet50",
             (True, 23): "resnet101", (True, 36): "resnet152"}
    return names.get((bottleneck, blocks), f"a ResNet with {blocks} layer3 blocks")


def load_strict(model: torch.nn.Module, sd: Mapping[str, torch.Tensor], *, arch: str, source: str) -> None:
    """``model.load_state_dict(sd, strict=True)`` with an error that names both architectures.
    A model built on the meta device (``make_resnet(..., empty=True)``) takes the tensors as
    they are (no initialisation wasted)."""
    assign = any(p.is_meta for p in model.parameters())
    try:
        model.load_state_dict(sd, strict=True, assign=assign)
    except RuntimeError as exc:
        found = detect_arch(sd)
        first = str(exc).splitlines()[1:3]
        raise WeightsError(
            f"{source}: weights for {found} cannot load into {arch} (strict): {' '.join(s.strip() for s in first)}"
        ) from None


def state_dict_hash(sd: Mapping[str, torch.Tensor]) -> str:
    """16-hex sha256 over names, shapes, dtypes and values (order-independent)."""
    h = hashlib.sha256()
    for k in sorted(sd):
        t = sd[k].detach().to("cpu").contiguous()
        h.update(f"{k}:{tuple(t.shape)}:{t.dtype}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()[:16]


def make_resnet(arch: str, *, num_classes: int = 1000, seed: int = 0, empty: bool = False) -> torch.nn.Module:
    """A torchvision ResNet with torchvision's own initialisation drawn from ``seed``
    (the global RNG state is left untouched); ``empty=True`` builds it on the meta device,
    to be filled by :func:`load_strict`."""
    import torchvision.models as tvm

    if arch not in IMAGENET_FILES:
        raise WeightsError(f"unknown architecture {arch!r}: expected one of {sorted(IMAGENET_FILES)}")
    with torch.device("meta"):
        model = getattr(tvm, arch)(weights=None, num_classes=num_classes)
    if not empty:  # a copy of the seed's tensors: the caller may train them in place
        model.load_state_dict({k: v.clone() for k, v in _seeded_init(arch, num_classes, seed)[0].items()},
                              assign=True)
    return model


def random_weights_hash(arch: str, *, num_classes: int = 1000, seed: int = 0) -> str:
    """:func:`state_dict_hash` of ``make_resnet(arch, num_classes=num_classes, seed=seed)``."""
    return _seeded_init(arch, num_classes, seed)[1]


@functools.lru_cache(maxsize=2)
def _seeded_init(arch: str, num_classes: int, seed: int) -> tuple[dict[str, torch.Tensor], str]:
    """torchvision's initialisation of ``arch`` from ``seed`` and its hash, drawn once per
    process (0.1 s and 0.04 s for a ResNet18): a table build asks for the encoder's random
    weights for its key, an ablation for every method's table."""
    import torchvision.models as tvm

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        sd = getattr(tvm, arch)(weights=None, num_classes=int(num_classes)).state_dict()
    return sd, state_dict_hash(sd)

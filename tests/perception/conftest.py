"""Fixtures for perception tests on the tiny world of :mod:`uevavd.testing.worlds`
(16 px rectangles of five shapes, occluded by a band that grows with the view index)."""

from __future__ import annotations

from pathlib import Path

import pytest

from uevavd.testing.worlds import SHAPES, SIZE, draw_view, write_tiny_world  # noqa: F401  (re-exported to tests)


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread: on a shared, loaded 2-core machine two threads spin against each other."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_world(shared) -> Path:
    """Two context scenes (1: hatchback, 31: pickup), 605 views each, with segmentation."""
    return shared.tiny_world((1, 31), train605=False)


@pytest.fixture
def own_tiny_world(tiny_world, tmp_path) -> Path:
    """``tiny_world`` for a test that edits scene 031's files: a copy of that scene (file
    times kept, so the world's tables keep their keys) beside links to the rest. The shared
    world is read by the other xdist worker meanwhile, so it is never edited in place."""
    import shutil

    root = tmp_path / "own-tiny-world"
    root.mkdir()
    for entry in tiny_world.iterdir():
        if entry.name == "031":
            shutil.copytree(entry, root / entry.name)
        else:
            (root / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    return root


@pytest.fixture(scope="session")
def world_605(shared) -> Path:
    """One context scene plus ``train_605`` (the five classes, unoccluded)."""
    return shared.tiny_world((1,), train605=True)


@pytest.fixture(scope="session")
def tiny_classifier(world_605, shared) -> Path:
    """A classifier trained by the CLI on 40 viewpoints of ``world_605`` (a few seconds)."""
    from uevavd.cli import main

    def build(folder: Path) -> None:
        folder.mkdir()
        rc = main(["train-classifier", str(world_605), "--out", str(folder / "tiny.safetensors"), "--epochs", "3",
                   "--max-views", "40", "--batch-size", "32", "--lr", "3e-3", "--threads", "1"])
        assert rc == 0

    return shared.once("tiny-classifier", build) / "tiny.safetensors"


METHOD_TOML = """
name = "tiny"
[perception]
segmenter = {{ name = "gt" }}
encoder = {{ name = "resnet18", weights = "random", seed = 0 }}
classifier = {{ name = "resnet18" }}
decompose = {decompose}
gray_seed = 0
"""


@pytest.fixture(scope="session")
def method_toml() -> str:
    """A method TOML template with a ``{decompose}`` field."""
    return METHOD_TOML

"""AODEnv(render_mode="rgb_array"): the current view from the dataset beside the path map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uevavd.data.grid import N_VIEWS
from uevavd.env import AODEnv
from uevavd.env.render import PANEL
from uevavd.perception.images import read_rgb
from uevavd.table import ObservationTable


def test_frames_show_the_dataset_view_and_the_path(synthetic_root):
    from uevavd.data.reader import read_dataset

    root = synthetic_root  # context 26 of the synthetic world at 16 px, as written
    manifest = read_dataset(root)
    rec = next(r for r in manifest.records if r.context == 26)
    rng = np.random.default_rng(0)
    probs = np.full((1, N_VIEWS, 5), 0.2)
    table = ObservationTable.from_arrays(
        rng.normal(size=(1, N_VIEWS, 4)), probs, np.tile([0.2, 0.2, 0.6, 0.6], (1, N_VIEWS, 1)),
        scenes=[rec.scene], contexts=[26], targets=[rec.target_index], splits=["train"],
        config={"data_root": str(root)})
    env = AODEnv(table, "train", render_mode="rgb_array")
    env.reset(options={"view": 302})
    frame = env.render()
    assert frame.shape == (PANEL, 2 * PANEL, 3) and frame.dtype == np.uint8
    image = read_rgb(manifest.records[manifest.index(rec.scene, rec.target, 302)].image)
    np.testing.assert_array_equal(frame[:, :PANEL], cv2.resize(image, (PANEL, PANEL), interpolation=cv2.INTER_NEAREST))
    before = frame[:, PANEL:].copy()
    env.step([3, 1])  # right, 2 steps: another image, and the path map gains a segment
    after = env.render()
    image2 = read_rgb(manifest.records[manifest.index(rec.scene, rec.target, env._view)].image)
    np.testing.assert_array_equal(after[:, :PANEL], cv2.resize(image2, (PANEL, PANEL), interpolation=cv2.INTER_NEAREST))
    assert (after[:, PANEL:] != before).any()


def test_without_a_dataset_folder_the_view_panel_says_so(table):
    env = AODEnv(table, "train", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (PANEL, 2 * PANEL, 3)
    assert (frame[0, :PANEL] == 128).all()  # the gray "no image" panel
    assert AODEnv(table, "train").render() is None  # no render_mode: nothing drawn
    with pytest.raises(ValueError, match="render_mode='human'"):
        AODEnv(table, "train", render_mode="human")

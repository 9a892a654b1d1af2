"""Pre-decomposition invariants (docs/perception.md, "Segmenters and pre-decomposition")."""

from __future__ import annotations

import numpy as np
import pytest

from uevavd.perception.decompose import decompose, view_seed


@pytest.fixture()
def scene():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (12, 10, 3), dtype=np.uint8)
    target = np.zeros((12, 10), bool)
    target[4:8, 3:7] = True
    a = np.zeros((12, 10), bool)
    a[:3] = True
    b = np.zeros((12, 10), bool)
    b[2:5, :] = True  # overlaps a (b wins) and the target (target wins)
    return image, target, [a, b]


def test_invariants(scene):
    image, target, (a, b) = scene
    out = decompose(image, target, [a, b], seed=7)
    assert out.shape == image.shape and out.dtype == np.uint8
    np.testing.assert_array_equal(out[target], image[target])
    gray = out[..., 0]
    assert (out[~target] == gray[~target][:, None]).all(), "non-target pixels must be gray (R = G = B)"
    regions = {"a": a & ~b & ~target, "b": b & ~target, "uncovered": ~(a | b | target)}
    values = {}
    for name, mask in regions.items():
        assert mask.any()
        vals = np.unique(gray[mask])
        assert len(vals) == 1, f"segment {name} is not one flat gray"
        values[name] = int(vals[0])
    g = np.random.default_rng(7).random(3)  # one draw per segment, then the uncovered one
    assert values == {"a": round(255 * g[0]), "b": round(255 * g[1]), "uncovered": round(255 * g[2])}


def test_deterministic_per_seed(scene):
    image, target, segs = scene
    np.testing.assert_array_equal(decompose(image, target, segs, seed=3), decompose(image, target, segs, seed=3))
    assert not np.array_equal(decompose(image, target, segs, seed=3), decompose(image, target, segs, seed=4))


def test_no_segments_and_no_target(scene):
    image, target, _ = scene
    out = decompose(image, np.zeros_like(target), [], seed=1)
    assert len(np.unique(out)) == 1  # the whole view is the one uncovered segment
    np.testing.assert_array_equal(decompose(image, np.ones_like(target), [], seed=1), image)


def test_view_seed_is_stable_and_distinct():
    assert view_seed(0, "001", 5) == view_seed(0, "001", 5)
    assert len({view_seed(0, "001", 5), view_seed(1, "001", 5), view_seed(0, "002", 5), view_seed(0, "001", 6)}) == 4


def test_bad_shapes_are_named(scene):
    image, target, segs = scene
    with pytest.raises(ValueError, match="segment 1"):
        decompose(image, target, [segs[0], segs[1][:5]], seed=0)
    with pytest.raises(ValueError, match="uint8"):
        decompose(image.astype(np.float32), target, segs, seed=0)


def test_ground_truth_fast_path_matches_the_definition():
    from uevavd.perception.segmenters import build_gt

    rng = np.random.default_rng(0)
    gt = build_gt()
    for trial in range(12):
        maps = rng.integers(0, 8, (2, 20, 24)).astype(np.uint16)
        if trial % 3 == 0:
            maps[maps == 0] = 5  # nothing uncovered
        if trial % 4 == 0:
            maps[maps == 1] = 2  # target fully hidden
        images = rng.integers(0, 256, (2, 20, 24, 3), dtype=np.uint8)
        cats = [{0: "none", 1: "target", 2: "building", 3: "tree", 4: "road", 5: "ground", 6: "vehicle",
                 7: "tree"}] * 2
        segs = gt.segment(images, np.zeros((2, 4), np.int64), instance_maps=maps, categories=cats)
        fast = gt.decompose_views(images, maps, cats, [trial, trial + 100])
        for i, s in enumerate(segs):
            np.testing.assert_array_equal(fast[i], decompose(images[i], s.target, s.segments, seed=trial + 100 * i))


def test_scene_decomposed_in_slices_equals_one_pass(tmp_path):
    """prepare decomposes a scene's views in one slice per decoding thread: same views,
    same order, same pixels as one call over the scene."""
    from uevavd.perception.images import Decoder
    from uevavd.perception.segmenters import build_gt

    rng = np.random.default_rng(1)
    n = 37
    maps = rng.integers(0, 9, (n, 16, 12)).astype(np.uint16)
    images = rng.integers(0, 256, (n, 16, 12, 3), dtype=np.uint8)
    cats = [{0: "none", 1: "target", **{k: "building" for k in range(2, 9)}}] * n
    seeds = list(range(100, 100 + n))
    gt = build_gt()
    whole = gt.decompose_views(images, maps, cats, seeds)
    with Decoder(4) as dec:
        seen = []
        out = np.zeros_like(images)

        def part(s):
            seen.append(s)
            out[s] = gt.decompose_views(images[s], maps[s], cats[s], seeds[s])

        dec.map_slices(part, n)
    assert sorted((s.start, s.stop) for s in seen) == [(0, 10), (10, 20), (20, 30), (30, 37)]
    np.testing.assert_array_equal(out, whole)

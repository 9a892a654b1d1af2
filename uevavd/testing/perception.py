"""Contract checks for perception components (segmenters, encoders, classifiers).

    from uevavd.testing import check_encoder
    check_encoder(build_resnet18(weights="random"))

Each check runs the component on small random images and raises ``AssertionError``
saying what is wrong: shapes, dtypes, finiteness, determinism, batch independence.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..perception.base import Classifier, Encoder, Segmentation, Segmenter


def sample_images(n: int = 3, size: int = 32, seed: int = 0) -> np.ndarray:
    """(n, size, size, 3) uint8 RGB test images: random noise with a bright centre blob."""
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)
    c = size // 2
    images[:, c - size // 8 : c + size // 8, c - size // 6 : c + size // 6] = 230
    return images


def sample_ground_truth(n: int = 3, size: int = 32) -> tuple[np.ndarray, np.ndarray, list[Mapping[int, str]]]:
    """``(boxes (n, 4) int64 XYXY, instance maps (n, H, W) uint16, categories)`` matching
    :func:`sample_images`: instance 1 = target at the centre, 2 = a building band, 3 = a
    tree, 0 = uncovered."""
    c = size // 2
    maps = np.zeros((n, size, size), np.uint16)
    maps[:, : size // 4] = 2
    maps[:, size - size // 4 :, : size // 2] = 3
    maps[:, c - size // 8 : c + size // 8, c - size // 6 : c + size // 6] = 1
    box = [c - size // 6, c - size // 8, c + size // 6, c + size // 8]
    boxes = np.array([box] * n, np.int64)
    cats = [{0: "none", 1: "target", 2: "building", 3: "tree"}] * n
    return boxes, maps, cats


def _check_identity(obj, what: str) -> None:
    ident = obj.identity()
    assert isinstance(ident, str) and ident, f"{what}.identity() must return a non-empty str, got {ident!r}"
    assert obj.identity() == ident, f"{what}.identity() is not stable between calls"


def check_segmenter(segmenter: Segmenter, *, size: int = 32, n: int = 3) -> None:
    """Segmentations: one per view, (H, W) bool target and segments, segments disjoint from
    the target, deterministic."""
    what = type(segmenter).__name__
    assert isinstance(segmenter, Segmenter), f"{what} does not implement the Segmenter protocol"
    assert isinstance(segmenter.needs_ground_truth, bool), f"{what}.needs_ground_truth must be a bool"
    images = sample_images(n, size)
    boxes, maps, cats = sample_ground_truth(n, size)
    kw = {"instance_maps": maps, "categories": cats} if segmenter.needs_ground_truth else {}
    out = segmenter.segment(images, boxes, **kw)
    assert isinstance(out, list) and len(out) == n, f"{what}.segment returned {type(out).__name__} of " \
        f"{len(out) if hasattr(out, '__len__') else '?'} items for {n} views; expected a list of {n}"
    again = segmenter.segment(images, boxes, **kw)
    for i, (s, t) in enumerate(zip(out, again, strict=True)):
        assert isinstance(s, Segmentation), f"{what}: view {i}: expected a Segmentation, got {type(s).__name__}"
        tm = np.asarray(s.target)
        assert tm.shape == (size, size) and tm.dtype == bool, \
            f"{what}: view {i}: target mask {tm.shape} {tm.dtype}; expected ({size}, {size}) bool"
        for j, seg in enumerate(s.segments):
            seg = np.asarray(seg)
            assert seg.shape == (size, size) and seg.dtype == bool, \
                f"{what}: view {i}, segment {j}: {seg.shape} {seg.dtype}; expected ({size}, {size}) bool"
            assert not (seg & tm).any(), f"{what}: view {i}, segment {j} contains target pixels"
        same = np.array_equal(tm, t.target) and len(s.segments) == len(t.segments) and all(
            np.array_equal(a, b) for a, b in zip(s.segments, t.segments, strict=True))
        assert same, f"{what}: view {i}: two calls on the same input gave different segmentations"
    _check_identity(segmenter, what)


def check_encoder(encoder: Encoder, *, size: int = 32, n: int = 3, atol: float = 1e-3) -> None:
    """Features: (N, feature_dim) float32, finite, deterministic, independent of the batch."""
    what = type(encoder).__name__
    assert isinstance(encoder, Encoder), f"{what} does not implement the Encoder protocol"
    d = encoder.feature_dim
    assert isinstance(d, int) and d > 0, f"{what}.feature_dim must be a positive int, got {d!r}"
    images = sample_images(n, size)
    f = encoder.encode(images)
    assert isinstance(f, np.ndarray) and f.shape == (n, d) and f.dtype == np.float32, \
        f"{what}.encode: got {getattr(f, 'shape', None)} {getattr(f, 'dtype', type(f))}; expected ({n}, {d}) float32"
    assert np.isfinite(f).all(), f"{what}.encode returned NaN or inf"
    assert np.array_equal(f, encoder.encode(images)), f"{what}.encode is not deterministic"
    one = encoder.encode(images[1:2])
    scale = max(1.0, float(np.abs(f).max()))
    assert np.allclose(one, f[1:2], atol=atol * scale, rtol=1e-3), \
        f"{what}.encode of one view differs from the same view inside a batch (batch-dependent features)"
    assert not np.allclose(f[0], f[1]), f"{what}.encode gives the same features for different images"
    _check_identity(encoder, what)


def check_classifier(classifier: Classifier, *, size: int = 32, n: int = 3) -> None:
    """Probabilities: (N, K) float32 in [0, 1], rows summing to 1, deterministic."""
    what = type(classifier).__name__
    assert isinstance(classifier, Classifier), f"{what} does not implement the Classifier protocol"
    classes = classifier.classes
    assert isinstance(classes, tuple) and classes and all(isinstance(c, str) for c in classes), \
        f"{what}.classes must be a non-empty tuple of str, got {classes!r}"
    images = sample_images(n, size)
    p = classifier.predict_proba(images)
    k = len(classes)
    assert isinstance(p, np.ndarray) and p.shape == (n, k) and p.dtype == np.float32, \
        f"{what}.predict_proba: got {getattr(p, 'shape', None)} {getattr(p, 'dtype', type(p))}; " \
        f"expected ({n}, {k}) float32"
    assert np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all(), f"{what}: probabilities outside [0, 1]"
    assert np.allclose(p.sum(1), 1.0, atol=1e-4), f"{what}: probabilities do not sum to 1 per view"
    assert np.array_equal(p, classifier.predict_proba(images)), f"{what}.predict_proba is not deterministic"
    _check_identity(classifier, what)

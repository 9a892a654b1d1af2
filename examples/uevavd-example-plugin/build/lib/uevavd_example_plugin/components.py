"""The example plugin's components. Builders are keyword-only, as uevavd's method configs expect."""

from __future__ import annotations

import numpy as np

from uevavd.perception.base import Segmentation


class ColorHistEncoder:
    """(N, H, W, 3) uint8 -> (N, 3 * bins) float32 normalised per-channel histograms."""

    def __init__(self, bins: int):
        self.bins = bins
        self.feature_dim = 3 * bins

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = np.asarray(images)
        n = images.shape[0]
        idx = (images.astype(np.int64) * self.bins) // 256  # (N, H, W, 3) bin per pixel
        out = np.zeros((n, 3, self.bins), np.float32)
        for c in range(3):
            flat = idx[..., c].reshape(n, -1) + np.arange(n)[:, None] * self.bins
            out[:, c] = np.bincount(flat.ravel(), minlength=n * self.bins).reshape(n, self.bins)
        out /= max(1, images.shape[1] * images.shape[2])
        return out.reshape(n, -1)

    def identity(self) -> str:
        return f"color_hist(bins={self.bins})"


def build_color_hist(*, bins: int = 16) -> ColorHistEncoder:
    if bins < 1:
        raise ValueError(f"bins={bins}: expected an integer >= 1")
    return ColorHistEncoder(bins)


class BoxSegmenter:
    needs_ground_truth = False

    def segment(self, images, boxes, *, instance_maps=None, categories=None):
        out = []
        for image, box in zip(np.asarray(images), np.asarray(boxes), strict=True):
            h, w = image.shape[:2]
            x1, y1, x2, y2 = (int(v) for v in box)
            target = np.zeros((h, w), bool)
            target[y1:y2, x1:x2] = True
            bands = []
            for sl in ((slice(0, y1), slice(None)), (slice(y2, h), slice(None)),
                       (slice(y1, y2), slice(0, x1)), (slice(y1, y2), slice(x2, w))):
                m = np.zeros((h, w), bool)
                m[sl] = True
                m &= ~target
                if m.any():
                    bands.append(m)
            out.append(Segmentation(target=target, segments=bands))
        return out

    def identity(self) -> str:
        return "box"


def build_box_segmenter() -> BoxSegmenter:
    return BoxSegmenter()

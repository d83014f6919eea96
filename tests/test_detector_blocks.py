"""The arrow's blobs are searched in the non-zero part of the block map only: that part, its
labels and their stats are those of the whole map, on maps of many blobs and odd sizes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from archery.services.detector.detect import _block_mean, _nonzero_blocks


def _maps(seed: int, shape: tuple[int, int], count: int) -> list[np.ndarray]:
    """Membership-like uint8 maps with up to 6 sparse blobs each, anywhere (borders too)."""
    rng = np.random.default_rng(seed)
    height, width = shape
    maps = []
    for _ in range(count):
        image = np.zeros(shape, np.uint8)
        for _ in range(int(rng.integers(0, 7))):
            h, w = (int(v) for v in rng.integers(1, 40, 2))
            y, x = int(rng.integers(0, height)), int(rng.integers(0, width))
            values = rng.integers(0, 256, (h, w)) * (rng.random((h, w)) < rng.uniform(0.2, 1.0))
            image[y : y + h, x : x + w] = values[: height - y, : width - x]
        maps.append(image)
    return maps


@pytest.mark.parametrize(
    ("shape", "block"), [((720, 1280), 3), ((721, 1283), 3), ((480, 640), 2), ((100, 130), 1)]
)
def test_the_part_labels_as_the_whole_map(shape: tuple[int, int], block: int) -> None:
    for image in _maps(block, shape, 150):
        whole = _block_mean(image, block)
        found = _nonzero_blocks(image, block)
        if found is None:
            assert not whole.any()
            continue
        part, bx0, by0 = found
        assert bx0 % 2 == 0 and by0 % 2 == 0
        window = (slice(by0, by0 + part.shape[0]), slice(bx0, bx0 + part.shape[1]))
        np.testing.assert_array_equal(part, whole[window])
        assert np.count_nonzero(part) == np.count_nonzero(whole)  # nothing outside it
        n_whole, labels_whole, stats_whole, _ = cv2.connectedComponentsWithStats(
            (whole > 0).astype(np.uint8), connectivity=8
        )
        n_part, labels_part, stats_part, _ = cv2.connectedComponentsWithStats(
            (part > 0).astype(np.uint8), connectivity=8
        )
        assert n_part == n_whole
        np.testing.assert_array_equal(labels_part, labels_whole[window])
        shifted = stats_part[1:] + np.array([bx0, by0, 0, 0, 0])
        np.testing.assert_array_equal(shifted, stats_whole[1:])


def test_a_float_map_is_searched_whole() -> None:
    image = _maps(7, (480, 640), 1)[0].astype(np.float32) * np.float32(0.7)
    part, bx0, by0 = _nonzero_blocks(image, 2) or (None, -1, -1)
    assert (bx0, by0) == (0, 0)
    np.testing.assert_array_equal(part, _block_mean(image, 2))

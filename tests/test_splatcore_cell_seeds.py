"""Textured-cell seeding against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.splatcore.cell_seeds import cell_points, cell_texture, textured_cells


def test_cell_texture_is_the_mean_sobel_magnitude_over_each_cell() -> None:
    import cv2

    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (37, 50), dtype=np.uint8)
    t = cell_texture(gray, (5, 7))
    g = gray.astype(np.float32)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    for i in range(5):
        for j in range(7):
            want = mag[8 * i : 8 * i + 8, 8 * j : 8 * j + 8].mean() if 8 * j + 8 <= 50 and 8 * i + 8 <= 37 else 0.0
            assert t[i, j] == pytest.approx(want, rel=1e-5, abs=1e-5)
    assert cell_texture(np.full((16, 16), 7, np.uint8), (2, 2)).max() == 0.0  # flat: no texture
    with pytest.raises(ValueError, match="gray must be"):
        cell_texture(np.zeros((8, 8, 3), np.uint8), (1, 1))


def test_textured_cells_keeps_the_highest_valid_scores_over_all_views() -> None:
    rng = np.random.default_rng(1)
    scores = [rng.random((4, 5)) for _ in range(3)]
    valid = [rng.random((4, 5)) > 0.3 for _ in range(3)]
    masks = textured_cells(scores, valid, 10)
    chosen = np.concatenate([s[m] for s, m in zip(scores, masks)])
    pool = np.concatenate([s[v] for s, v in zip(scores, valid)])
    assert len(chosen) == 10 and np.allclose(np.sort(chosen), np.sort(pool)[-10:])
    assert all(not (m & ~v).any() for m, v in zip(masks, valid))  # only valid cells
    every = textured_cells(scores, valid, 1000)  # more asked than there are: all valid cells
    assert all((m == v).all() for m, v in zip(every, valid))
    with pytest.raises(ValueError, match="differ"):
        textured_cells([np.zeros((2, 2))], [np.zeros((2, 3), bool)], 1)


def test_cell_points_take_each_cells_coordinate_and_the_colour_of_its_pixel() -> None:
    coords = np.arange(2 * 3 * 3, dtype=np.float64).reshape(2, 3, 3)
    rgb = np.random.default_rng(2).random((16, 24, 3))
    mask = np.array([[True, False, False], [False, False, True]])
    pts, cols = cell_points(coords, mask, rgb)
    assert np.array_equal(pts, coords[mask])
    assert np.array_equal(cols, np.stack([rgb[4, 4], rgb[12, 20]]))  # pixels (8j + 4, 8i + 4)

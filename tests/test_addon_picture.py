"""The README picture's script (scripts/render_addon_picture.py): which configurations it shows
and how it tiles them (the Cycles renders are tested in tests/osn/export/test_addon_render.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("render_addon_picture", REPO / "scripts" / "render_addon_picture.py")
pic = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pic)


def test_farthest_pair_is_the_pair_furthest_apart_in_log_scale() -> None:
    samples = np.array([[1.0, 0.5, 0.5], [1.0, 0.1, 2.0], [1.0, 0.6, 0.6], [1.0, 2.0, 0.1], [1.0, 2.0, 0.1]])
    # Rows 1 and 3 (and 1 and 4, the same configuration) are furthest apart: the lowest indices win.
    assert pic.farthest_pair(samples) == (1, 3)
    assert pic.farthest_pair(samples[[3, 0, 1]]) == (0, 2)


@pytest.mark.parametrize("bad", [np.ones((1, 3)), np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([[1.0, np.nan], [1.0, 1.0]])])
def test_farthest_pair_rejects_too_few_or_non_positive_scales(bad: np.ndarray) -> None:
    with pytest.raises(ValueError):
        pic.farthest_pair(bad)


def test_tile_picture_upscales_each_tile_under_its_caption() -> None:
    rng = np.random.default_rng(0)
    tiles = [[rng.random((4, 5, 3)), None], [rng.random((4, 5, 3)), rng.random((4, 5, 3))]]
    img = np.asarray(pic.tile_picture(tiles, [["a", "b"], ["c\nd", "e"]], zoom=3))
    h, w = 4 * 3, 5 * 3
    assert img.shape == (2 * (h + pic.LABEL_H), 2 * w, 3)
    for r, c in ((0, 0), (1, 0), (1, 1)):
        y, x = r * (h + pic.LABEL_H) + pic.LABEL_H, c * w
        want = np.repeat(np.repeat((tiles[r][c] * 255 + 0.5).astype(np.uint8), 3, 0), 3, 1)
        np.testing.assert_array_equal(img[y:y + h, x:x + w], want)
    assert (img[:pic.LABEL_H, :w] < 128).any()  # the caption is drawn
    with pytest.raises(ValueError, match="shape"):
        pic.tile_picture([[tiles[0][0], rng.random((2, 2, 3))]], [["a", "b"]])

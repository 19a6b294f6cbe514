"""The layered best-of-N search: its algebra against brute force, and its choices on a real run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from osn.evaluate.bestofn import EvalConfig, relative_scale_errors
from osn.evaluate.layered import Layer, composite_layers, masked_mse_matrix, nearest_level, scale_levels


def test_masked_mse_matrix_equals_brute_force():
    g = torch.Generator().manual_seed(0)
    n, G, P = 7, 4, 50
    x, y = torch.rand(n, P, 3, generator=g, dtype=torch.float64), torch.rand(G, P, 3, generator=g, dtype=torch.float64)
    m = torch.rand(G, P, generator=g) > 0.3
    got = masked_mse_matrix(x, y, m)
    for i in range(n):
        for j in range(G):
            d = ((x[i] - y[j]) ** 2)[m[j]]
            assert torch.isclose(got[i, j], d.mean(), rtol=1e-9, atol=1e-12)


def test_composite_of_opaque_layers_shows_the_nearest_object():
    P = 6
    def opaque(rgb: list[float], depth: list[float]) -> Layer:
        d = torch.tensor(depth)
        a = torch.isfinite(d).float()  # empty where the depth is infinite
        return Layer(a[:, None] * torch.tensor([rgb] * P), a, d)

    red = opaque([1.0, 0, 0], [1.0, 5, 1, 5, np.inf, 2])
    blue = opaque([0, 0, 1.0], [2.0, 3, np.inf, 1, np.inf, 2.5])
    empty_red = Layer(torch.zeros(P, 3), torch.zeros(P), torch.full((P,), np.inf))
    img = composite_layers([[red, empty_red], [blue]], np.array([[0, 0], [1, 0]]), np.array([0.0, 1.0, 0.0]))
    # Sample 0: red wherever red is nearer or blue is absent; pixel 4 (both empty) stays background.
    expect = ["r", "b", "r", "b", "g", "r"]
    colours = {"r": [1, 0, 0], "b": [0, 0, 1], "g": [0, 1, 0]}
    for p, c in enumerate(expect):
        assert torch.allclose(img[0, p], torch.tensor(colours[c], dtype=img.dtype)), (p, img[0, p])
    # Sample 1 uses red's empty level: blue where blue exists, background elsewhere.
    assert torch.allclose(img[1, 2], torch.tensor([0.0, 1.0, 0.0], dtype=img.dtype))
    assert torch.allclose(img[1, 0], torch.tensor([0.0, 0.0, 1.0], dtype=img.dtype))


def test_semi_transparent_layers_follow_the_over_operator():
    a = Layer(torch.tensor([[0.5, 0.0, 0.0]]), torch.tensor([0.5]), torch.tensor([1.0]))  # premultiplied
    b = Layer(torch.tensor([[0.0, 0.8, 0.0]]), torch.tensor([0.8]), torch.tensor([2.0]))
    img = composite_layers([[a], [b]], np.array([[0, 0]]), np.zeros(3))
    assert torch.allclose(img[0, 0], torch.tensor([0.5, 0.5 * 0.8, 0.0], dtype=img.dtype))


def test_scale_levels_cover_the_samples_in_log_space():
    sbar = np.array([[1.0, 0.2, 3.0], [1.0, 0.8, 3.0], [1.0, 0.4, 3.0]])
    grids = scale_levels(sbar, 5)
    assert len(grids[0]) == 1 and len(grids[2]) == 1  # constant columns: one level
    assert np.isclose(grids[1][0], 0.2) and np.isclose(grids[1][-1], 0.8)  # the ends are the samples' extremes
    assert np.all(np.diff(grids[1]) > 0)
    # Three samples evenly spaced in log-scale: their quantiles are the even log grid.
    assert np.allclose(np.diff(np.log(grids[1])), np.log(4) / 4)
    assert list(nearest_level(sbar[:, 1], grids[1])) == [0, 4, 2]
    assert len(scale_levels(np.repeat(sbar, 50, axis=0), 10)[0]) == 1


def test_scale_levels_go_where_the_samples_crowd():
    """Samples crowd the large end of their range (the valid set of the SfM demo: a tenth of them
    in the lower 60% of its log-range): the levels follow them, so a typical sample's nearest layer
    is far nearer its own scale than with an even log grid of as many levels (which 0.18 dB of
    the demo's best of 1000 was lost to, docs/metrics.md)."""
    rng = np.random.default_rng(0)
    s = np.concatenate([np.exp(rng.uniform(np.log(0.05), np.log(0.3), 100)), np.exp(rng.uniform(np.log(0.3), np.log(1.0), 900))])
    grid = scale_levels(s[:, None], 24)[0]
    assert len(grid) == 24 and np.isclose(grid[0], s.min()) and np.isclose(grid[-1], s.max())
    even = np.geomspace(s.min(), s.max(), 24)
    off = lambda g: np.abs(np.log(s) - np.log(g[nearest_level(s, g)]))  # noqa: E731
    assert np.median(off(grid)) < 0.6 * np.median(off(even)), (np.median(off(grid)), np.median(off(even)))
    assert np.all(np.diff(grid) > 0)


def test_relative_scale_errors_skip_the_anchor_and_index_truth_by_object_id():
    """Objects 0 (anchor), 2 and 3 were trained (object 1 was dropped); the truth is indexed by
    id, so object 3's column is the fourth. Worked by hand: (|0.5-0.4|/0.4 + |2-2.5|/2.5) / 2."""
    actual = np.array([[1.0, 0.5, 2.0], [1.0, 0.4, 2.5]])
    true = np.array([[1.0, 9.0, 0.4, 2.5], [1.0, 9.0, 0.4, 2.5]])
    err = relative_scale_errors(actual, true, ids=[0, 2, 3], anchor_id=0)
    assert err == pytest.approx([(0.25 + 0.2) / 2, 0.0])
    # the anchor may be any object: here object 2, so objects 0 and 3 are compared
    err = relative_scale_errors(actual, true, ids=[0, 2, 3], anchor_id=2)
    assert err == pytest.approx([(0.0 + 0.2) / 2, 0.0])
    assert relative_scale_errors(actual[:, :1], true, ids=[0], anchor_id=0) == []


@pytest.mark.parametrize("field, value, phrase", [
    ("max_views", -1, "max_views must be an integer >= 0, got -1"),
    ("levels", 1, "levels must be an integer >= 2, got 1"),
    ("topk", 0, "topk must be an integer >= 1, got 0"),
    ("lpips", "yes", "lpips must be true or false"),
    ("valid_points", 10, "valid_points must be an integer >= 1000"),
    ("seed", -3, "seed must be an integer >= 0"),
])
def test_eval_config_rejects_bad_values(field, value, phrase):
    with pytest.raises(ValueError, match=f"evaluate config: {phrase}"):
        EvalConfig(**{field: value})
    EvalConfig(max_views=0, levels=2, topk=1, lpips=False, valid_points=1000)  # the smallest accepted values

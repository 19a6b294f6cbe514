"""Drawing from a learned valid set far too small for uniform draws (scenecore.scale_space)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from scenecore.scale_space import climb_into_set, hit_and_run, learned_intervals


def _box_set(lo: np.ndarray, hi: np.ndarray):
    """Score 1 inside the box [lo, hi), 0 outside."""
    return lambda x: np.all((x >= lo) & (x < hi), axis=1).astype(np.float64)


def test_hit_and_run_draws_a_millionth_of_the_box_uniformly() -> None:
    """A 6-D box of side 0.1 (1e-6 of the domain): a million uniform draws hit it about once;
    hit-and-run from one point inside gives points all inside and uniform over it (each
    coordinate's marginal passes a Kolmogorov-Smirnov test against the uniform law)."""
    rng = np.random.default_rng(0)
    lo = np.array([0.05, 0.3, 0.62, 0.11, 0.8, 0.45])
    hi = lo + 0.1
    score = _box_set(lo, hi)
    start = (lo + 0.01)[None]  # a corner: the chains must spread from it
    x = hit_and_run(score, start, 3000, 0.5, rng)
    assert x.shape == (3000, 6) and (score(x) == 1).all()
    for k in range(6):
        assert stats.kstest((x[:, k] - lo[k]) / 0.1, "uniform").pvalue > 1e-3, k
    again = hit_and_run(score, start, 3000, 0.5, np.random.default_rng(0))
    assert np.array_equal(x, again)  # deterministic given the generator


def test_hit_and_run_reaches_every_part_of_a_non_convex_set() -> None:
    """An L of two arms: chains started at the far end of one arm fill both in proportion to their areas."""
    def score(x: np.ndarray) -> np.ndarray:
        horizontal = (x[:, 0] < 0.5) & (x[:, 1] < 0.05)
        vertical = (x[:, 0] < 0.05) & (x[:, 1] >= 0.05) & (x[:, 1] < 0.5)
        return (horizontal | vertical).astype(np.float64)

    x = hit_and_run(score, np.array([[0.45, 0.02]]), 4000, 0.5, np.random.default_rng(1))
    assert (score(x) == 1).all()
    area_h, area_v = 0.5 * 0.05, 0.05 * 0.45
    assert (x[:, 1] >= 0.05).mean() == pytest.approx(area_v / (area_h + area_v), abs=0.05)


def test_climbing_finds_a_set_that_uniform_draws_miss() -> None:
    """A smooth bump whose top (score > 0.9) is about 1e-8 of a 5-D box: none of the best uniform
    draws is inside; climbing from them enters it, and nothing returned is outside."""
    centre = np.array([0.71, 0.22, 0.5, 0.93, 0.37])
    score = lambda x: np.exp(-np.sum((x - centre) ** 2, axis=1) / (2 * 0.01**2))  # noqa: E731
    rng = np.random.default_rng(2)
    draws = rng.random((20_000, 5))
    p = score(draws)
    assert (p > 0.9).sum() == 0
    found = climb_into_set(score, draws[np.argsort(-p)[:16]], 0.9, rng)
    assert len(found) >= 1 and (score(found) > 0.9).all()
    assert len(climb_into_set(lambda x: np.zeros(len(x)), draws[:4], 0.5, rng, steps=5)) == 0


def test_learned_intervals_of_a_tiny_set_are_its_box() -> None:
    """A scale network (in the export's layout) valid only on a slab 1e-3 wide across the first of
    three free axes: a few of 20,000 uniform draws land in it, too few to span the slab's other
    axes; with hit-and-run the learned intervals are the slab's."""
    a, b = 0.4, 0.401
    # logit = 1e4 * min(x0 - a, b - x0) = 1e4 * ((x0 - a + 10) - 10 - relu(2 x0 - a - b)): positive on the slab only.
    w1, b1 = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), np.array([10.0 - a, -a - b])
    w2, b2 = np.array([[1e4, -1e4]]), np.array([-1e5])
    ranges = np.array([[1.0, 1.0], [1.0, 2.0], [1.0, 2.0], [1.0, 2.0]])
    iv = learned_intervals([(w1, b1), (w2, b2)], ranges, 0, draws=20_000)
    assert iv[0].tolist() == [1.0, 1.0]
    assert iv[1, 0] == pytest.approx(1.0 + a, abs=2e-4) and iv[1, 1] == pytest.approx(1.0 + b, abs=2e-4)
    assert iv[2, 0] < 1.01 and iv[2, 1] > 1.99 and iv[3, 0] < 1.01 and iv[3, 1] > 1.99
    from scenecore.errors import EmptyValidSet

    with pytest.raises(EmptyValidSet, match="accepts none of 2000 uniform draws, nor a point climbing"):
        learned_intervals([(w1, b1), (w2, np.array([-1e9]))], ranges, 0, draws=2000)


def test_configurations_inside_intervals_are_drawn_even_where_the_set_fills_little_of_them() -> None:
    """The add-on's sampler: a valid set that is a thin diagonal band of its intervals' box (0.4%
    of it) gives a few of 4096 draws; the rest come from hit-and-run, all valid, spread along the
    whole band; a network that accepts nothing is one error."""
    from scenecore.errors import EmptyValidSet
    from scenecore.scale_space import sample_valid_configurations

    def score(s: np.ndarray) -> np.ndarray:
        return (np.abs(s[:, 1] - s[:, 2]) < 0.002).astype(np.float64)

    intervals = np.array([[1.0, 1.0], [1.0, 2.0], [1.0, 2.0]])
    out = sample_valid_configurations(score, intervals, 0.5, 500, seed=0, max_draws=4096)
    assert out.shape == (500, 3) and (score(out) == 1).all() and (out[:, 0] == 1.0).all()
    assert stats.kstest(out[:, 1] - 1.0, "uniform").pvalue > 1e-3
    with pytest.raises(EmptyValidSet, match="no valid configuration in 4096 draws"):
        sample_valid_configurations(lambda s: np.zeros(len(s)), intervals, 0.5, 5, seed=0, max_draws=4096)

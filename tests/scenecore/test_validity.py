import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from scenecore.validity import EmptyRegionError, ValidRegion, accumulate_ratio_bounds


def test_intervals_from_chain():
    # 0 = anchor (room), 1 in front of 0 with depth ratio 2, 2 in front of 1 with ratio 1.5.
    B = np.full((3, 3), np.inf)
    B[1, 0] = 2.0  # s1 / s0 < 2
    B[2, 1] = 1.5  # s2 / s1 < 1.5
    r = ValidRegion.from_bounds(B, anchor=0)
    assert r.intervals[1] == pytest.approx([0.0, 2.0])
    assert r.intervals[2] == pytest.approx([0.0, 3.0])  # through the chain
    assert r.contains(np.array([1.0, 1.9, 2.8]))
    assert not r.contains(np.array([1.0, 1.0, 1.6]))  # s2/s1 = 1.6 > 1.5
    assert not r.contains(np.array([1.0, 2.0, 1.0]))  # boundary is excluded (strict)


def test_empty_region_detected():
    B = np.full((2, 2), np.inf)
    B[0, 1] = 0.5  # s0 < 0.5 s1
    B[1, 0] = 1.5  # s1 < 1.5 s0  -> s0 < 0.75 s0: empty
    with pytest.raises(EmptyRegionError, match="empty"):
        ValidRegion.from_bounds(B)
    B[1, 0] = 2.0  # cycle weight exactly 0: strictly empty
    with pytest.raises(EmptyRegionError):
        ValidRegion.from_bounds(B)


def test_accumulate_bounds_from_depths():
    K, H, W = 2, 2, 3
    alone = np.full((K, H, W), np.inf)
    alone[0] = 10.0  # background everywhere
    alone[1, 0, :] = [2.0, 4.0, 5.0]  # object in the first row
    visible = np.where(np.isfinite(alone[1]), 1, 0)
    B = accumulate_ratio_bounds(np.full((K, K), np.inf), visible, alone)
    assert B[1, 0] == pytest.approx(2.0)  # min 10/5
    assert np.isinf(B[0, 1])  # object 1 never behind the background where 0 is visible


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-690, 690), min_size=3, max_size=3), st.integers(2, 16))
def test_extreme_scales_finite(log_s, K):
    # Bounds and scales spanning 1e-300..1e300 stay finite in log space.
    rng = np.random.default_rng(K)
    B = np.exp(rng.uniform(0.01, 690, (K, K)))
    r = ValidRegion.from_bounds(B)
    assert np.all(np.isfinite(np.log(r.intervals[:, 1])))
    s = np.exp(np.resize(np.array(log_s), K))
    s[0] = 1.0
    m = r.log_margin(s)
    assert np.isfinite(m)
    assert r.log_margin(np.r_[1.0, np.zeros(K - 1)]) == -np.inf


def test_single_object_unconstrained():
    r = ValidRegion.from_bounds(np.full((1, 1), np.inf))
    assert r.contains(np.array([1.0])) and r.log_margin(np.array([1.0])) == np.inf


def test_box_share_matches_the_exact_area_and_stays_measurable_when_tiny():
    from scenecore.validity import box_share

    # Anchor 0 at 1; objects 1, 2 free with s1 < 2, s2 < 3 and s1 / s2 < 1 (object 1 in front of 2).
    B = np.full((3, 3), np.inf)
    B[1, 0], B[2, 0], B[1, 2] = 2.0, 3.0, 1.0
    region = ValidRegion.from_bounds(B)
    box = np.array([[1, 1], [0.0, 4.0], [0.0, 4.0]])
    # Exact valid area inside [0, 4]^2: {s1 < 2, s2 < 3, s1 < s2} = 2 * 3 - 2 * 2 / 2 = 4 of 16.
    share, err = box_share(region, box, samples=400_000)
    assert abs(share - 0.25) < 4 * err and err < 2e-3
    # A box a million times wider than the region: uniform sampling of the box would see nothing,
    # sampling the region's intervals keeps the relative error small.
    wide = np.array([[1, 1], [0.0, 4000.0], [0.0, 4000.0]])
    share, err = box_share(region, wide, samples=100_000)
    assert abs(share - 4 / 4000.0**2) < 4 * err and err < 0.01 * share
    # No overlap -> exactly 0; a bad box -> one-line error.
    assert box_share(region, np.array([[1, 1], [2.5, 4.0], [0.0, 4.0]])) == (0.0, 0.0)
    with pytest.raises(ValueError, match="lo < hi"):
        box_share(region, np.array([[1, 1], [4.0, 1.0], [0.0, 4.0]]))

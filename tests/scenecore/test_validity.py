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


def test_set_accuracy_resolves_a_region_of_a_millionth_of_the_box():
    """Eight objects: every free one below half the anchor's scale and object 2 in front of 1
    fill (0.5 / 4)^7 / 2 = 2.4e-7 of the box [0, 4]^7, where 20000 uniform points find nothing.
    The stratified points measure it, and a learned set equal to the region's interval box (the
    pair constraint missed) has IoU and precision 1/2, recall 1; the region itself has IoU 1."""
    from scenecore.validity import set_accuracy, set_samples

    K = 8
    B = np.full((K, K), np.inf)
    B[1:, 0] = 0.5
    B[2, 1] = 1.0
    region = ValidRegion.from_bounds(B)
    box = np.array([[1.0, 1.0]] + [[0.0, 4.0]] * (K - 1))
    pts = set_samples(region, box, 20_000, seed=0)
    assert not region.contains(pts.uniform).any()  # what a uniform estimate would have to go on
    assert pts.inner_volume == pytest.approx((0.5 / 4) ** 7)

    def acc(learned):
        return set_accuracy(pts, *(learned(x) for x in pts.strata))

    exact = acc(region.contains)
    assert exact["iou"] == exact["precision"] == exact["recall"] == 1.0
    assert exact["exact_fraction"] == pytest.approx((0.5 / 4) ** 7 / 2, rel=0.03)
    box_only = acc(lambda s: np.all(s[:, 1:] < 0.5, axis=1))
    assert box_only["recall"] == 1.0 and box_only["iou"] == pytest.approx(0.5, abs=0.02)
    assert box_only["precision"] == pytest.approx(box_only["iou"])
    # A learned set reaching outside the interval box is counted through the uniform points.
    outside = acc(lambda s: np.all(s[:, 1:] < 0.5, axis=1) | (s[:, 1] > 2.0))
    assert outside["learned_fraction"] == pytest.approx(0.5 + box_only["learned_fraction"], abs=0.02)
    assert outside["precision"] < 1e-5 and outside["recall"] == 1.0
    empty = acc(lambda s: np.zeros(len(s), bool))
    assert empty["iou"] == empty["precision"] == empty["recall"] == 0.0
    # A region that misses the box: nothing to measure against, NaN rather than a number.
    far = set_samples(region, np.array([[1.0, 1.0]] + [[1.0, 4.0]] * (K - 1)), 1000)
    missed = set_accuracy(far, *(region.contains(x) for x in far.strata))
    assert far.inner_volume == 0.0 and missed["exact_points"] == 0 and np.isnan(missed["iou"]) and np.isnan(missed["recall"])
    # An object the learned set does not model is held at its box value (lo == hi).
    held = box.copy()
    held[3] = [0.25, 0.25]
    pts3 = set_samples(region, held, 5000)
    assert all(np.all(x[:, 3] == 0.25) for x in pts3.strata)


def test_limiting_bounds_charge_misses_and_excess_to_the_pair_that_is_off():
    """A learned set with one bound 10% too loose (s_1 < 1.1 instead of 1) and another 10% too
    tight (s_2 < 1.35 s_1 instead of 1.5 s_1): its excess is all beyond the loose bound, its misses
    mostly at the tight one, and the charges add up to set_accuracy's precision and recall."""
    from scenecore.validity import limiting_bounds, set_accuracy, set_samples

    B = np.full((3, 3), np.inf)
    B[1, 0], B[2, 0], B[2, 1] = 1.0, 2.0, 1.5
    region = ValidRegion.from_bounds(B)
    pts = set_samples(region, np.array([[1.0, 1.0], [0.0, 3.0], [0.0, 3.0]]), 20_000, seed=1)

    def learned(s):
        return (s[:, 1] < 1.1) & (s[:, 2] < 2.0) & (s[:, 2] < 1.35 * s[:, 1])

    lu, li, ln = (learned(x) for x in pts.strata)
    acc = set_accuracy(pts, lu, li, ln)
    lim = {(e["i"], e["j"]): e for e in limiting_bounds(region, pts, lu, li, ln)}
    assert set(lim) == {(1, 0), (2, 0), (2, 1)} and lim[(2, 1)]["bound"] == 1.5
    assert sum(e["missed"] for e in lim.values()) == pytest.approx(1.0 - acc["recall"], rel=1e-9)
    outside = (acc["learned_fraction"] - acc["precision"] * acc["learned_fraction"]) / acc["exact_fraction"]
    assert sum(e["excess"] for e in lim.values()) == pytest.approx(outside, rel=1e-9)
    assert acc["recall"] < 0.95 and acc["precision"] < 0.95  # both errors are there to find
    assert lim[(1, 0)]["excess"] == pytest.approx(outside) and lim[(2, 1)]["excess"] == 0.0
    assert lim[(2, 1)]["missed"] > 0.8 * (1.0 - acc["recall"])
    # Too loose inside the region's interval box (s_2 < 1.7 s_1): charged through the inner points.
    def loose(s):
        return region.contains(s) | ((s[:, 1] < 1.0) & (s[:, 2] < 1.7 * s[:, 1]) & (s[:, 2] < 2.0))

    lu, li, ln = (loose(x) for x in pts.strata)
    acc = set_accuracy(pts, lu, li, ln)
    lim = {(e["i"], e["j"]): e for e in limiting_bounds(region, pts, lu, li, ln)}
    outside = (acc["learned_fraction"] - acc["precision"] * acc["learned_fraction"]) / acc["exact_fraction"]
    assert acc["recall"] == 1.0 and outside > 0.05 and lim[(2, 1)]["excess"] == pytest.approx(outside, rel=1e-9)
    # The region itself: nothing to charge; a region that misses the box: no entries.
    exact = limiting_bounds(region, pts, *(region.contains(x) for x in pts.strata))
    assert all(e["missed"] == 0.0 and e["excess"] == 0.0 for e in exact)
    far = set_samples(region, np.array([[1.0, 1.0], [2.0, 3.0], [0.0, 3.0]]), 1000)
    assert limiting_bounds(region, far, *(x[:, 0] > 0 for x in far.strata)) == []


def test_limiting_bounds_leave_out_pairs_whose_scales_are_all_held():
    """An object a run does not model is held at scale 1 like the anchor; where it stands on the
    anchor (``s_3 < 1.0001``) its slack is 1e-4 at every point, which made it every miss's nearest
    bound. The misses are the tight bound's."""
    from scenecore.validity import limiting_bounds, set_accuracy, set_samples

    B = np.full((4, 4), np.inf)
    B[1, 0], B[2, 0], B[2, 1], B[3, 0] = 1.0, 2.0, 1.5, 1.0001
    region = ValidRegion.from_bounds(B)
    pts = set_samples(region, np.array([[1.0, 1.0], [0.0, 3.0], [0.0, 3.0], [1.0, 1.0]]), 20_000, seed=1)

    def learned(s):
        return (s[:, 1] < 1.0) & (s[:, 2] < 1.35 * s[:, 1])

    lu, li, ln = (learned(x) for x in pts.strata)
    lim = {(e["i"], e["j"]): e for e in limiting_bounds(region, pts, lu, li, ln)}
    assert (3, 0) not in lim and set(lim) == {(1, 0), (2, 0), (2, 1)}
    assert sum(e["missed"] for e in lim.values()) == pytest.approx(1.0 - set_accuracy(pts, lu, li, ln)["recall"], rel=1e-9)
    assert lim[(2, 1)]["missed"] > 0.8 * sum(e["missed"] for e in lim.values())


def test_near_stratum_measures_a_set_that_reaches_just_past_the_region():
    """Where learned sets err, a few per cent past a bound, the uniform points of a large box are
    too sparse: the near stratum measures that excess. A region of 1% of the box [0, 10]^2 and a set
    5% past one of its bounds: precision 1 / 1.05 within 0.01 on every seed of 20000 points, where
    the uniform points alone hold about 10 of the excess."""
    from scenecore.validity import set_accuracy, set_samples

    B = np.full((3, 3), np.inf)
    B[1, 0], B[2, 0] = 1.0, 1.0
    region = ValidRegion.from_bounds(B)
    box = np.array([[1.0, 1.0], [0.0, 10.0], [0.0, 10.0]])
    for seed in range(5):
        pts = set_samples(region, box, 20_000, seed=seed)
        assert pts.near_volume == pytest.approx(0.04) and pts.inner_volume == pytest.approx(0.01)
        acc = set_accuracy(pts, *((x[:, 1] < 1.05) & (x[:, 2] < 1.0) for x in pts.strata))
        assert acc["recall"] == 1.0
        assert acc["precision"] == pytest.approx(1 / 1.05, abs=0.01), (seed, acc)
        assert acc["learned_fraction"] == pytest.approx(0.0105, rel=0.01)
        # Far from the region (s_1 > 9): the uniform points still count it.
        far = set_accuracy(pts, *((x[:, 1] > 9.0) | (x[:, 1] < 1.0) & (x[:, 2] < 1.0) for x in pts.strata))
        assert far["learned_fraction"] == pytest.approx(0.11, rel=0.05)

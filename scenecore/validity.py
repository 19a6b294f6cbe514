"""The exact region of valid scale configurations (numpy only).

A configuration scales object k by ``s_k`` about the training camera centre of every timestamp.
The training video is unchanged iff no visibility order flips on any training pixel:

    valid  <=>  s_i / s_j < B_ij  for every ordered pair (i, j),
    B_ij = min over training pixels p with visible object i and object j also covering p
           of d_j(p) / d_i(p)            (+inf when no pixel constrains the pair)

where ``d_k`` is the planar depth of object k rendered alone. In log coordinates
``x_k = log s_k`` this is the polyhedron ``x_i - x_j < log B_ij`` (difference constraints).
With the anchor fixed at ``x_a = 0``, the tightest interval of each object follows from all-pairs
shortest paths over the constraint graph (Floyd-Warshall on ``log B``).

All computations are done in log space so ratios from 1e-300 to 1e300 stay finite and exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class EmptyRegionError(ValueError):
    """The constraints admit no configuration (a negative cycle in the constraint graph)."""


def accumulate_ratio_bounds(
    bounds: np.ndarray, visible: np.ndarray, alone_depths: np.ndarray, where: str = "frame"
) -> np.ndarray:
    """Tighten ratio bounds ``B (K, K)`` with one training frame, in place; returns ``B``.

    Args:
        bounds: ``(K, K)`` current bounds, ``+inf`` where unconstrained.
        visible: ``(H, W)`` integer id of the visible object per pixel (``>= K`` for none).
        alone_depths: ``(K, H, W)`` planar depth of each object rendered alone, ``+inf`` (or a
            non-positive value) where the object does not cover the pixel.
        where: names the frame in errors.

    Ratios are taken in float64 (float32 depths of 1e-30 and 1e30 give a ratio of 1e60, which
    float32 would turn into ``inf``, i.e. "unconstrained").

    Raises:
        ValueError: a depth is NaN (a NaN would otherwise drop the pair's bound silently and
            leave the region unbounded), or the visible object does not cover its own pixel.
    """
    K = bounds.shape[0]
    depths = np.asarray(alone_depths, dtype=np.float64)
    nan = np.isnan(depths)
    if nan.any():
        k = int(np.argwhere(nan.reshape(K, -1).any(axis=1))[0, 0])
        raise ValueError(f"{where}: the depth of object {k} rendered alone is NaN at {int(nan[k].sum())} pixels")
    covered = np.isfinite(depths) & (depths > 0)
    for i in range(K):
        sel = visible == i
        if not sel.any():
            continue
        if not covered[i][sel].all():
            raise ValueError(f"{where}: object {i} is visible at {int((~covered[i][sel]).sum())} pixels "
                             "where its own depth is not finite and positive")
        d_i = depths[i][sel]
        for j in range(K):
            if j == i:
                continue
            cov = covered[j][sel]
            if not cov.any():
                continue
            ratio = np.min(depths[j][sel][cov] / d_i[cov])
            if ratio < bounds[i, j]:
                bounds[i, j] = ratio
    return bounds


@dataclass
class ValidRegion:
    """The exact valid region: ``s_i / s_j < ratio_bounds[i, j]`` for all ``i != j``.

    Attributes:
        anchor: id of the object whose scale is fixed at 1.
        ratio_bounds: ``(K, K)`` float64, ``+inf`` where a pair is unconstrained; diagonal ``+inf``.
        intervals: ``(K, 2)`` open interval ``(lo, hi)`` of each object's scale with the anchor
            at 1 and the others free (the projection of the region); ``lo`` may be 0, ``hi`` inf.
    """

    anchor: int
    ratio_bounds: np.ndarray
    intervals: np.ndarray

    @classmethod
    def from_bounds(cls, ratio_bounds: np.ndarray, anchor: int = 0) -> "ValidRegion":
        """Build the region, deriving per-object intervals by shortest paths.

        Raises:
            EmptyRegionError: when no configuration satisfies every constraint, naming a cycle.
        """
        B = np.array(ratio_bounds, dtype=np.float64)
        if B.ndim != 2 or B.shape[0] != B.shape[1]:
            raise ValueError(f"ratio bounds must be a square matrix, got shape {B.shape}")
        K = B.shape[0]
        if K == 0:
            raise ValueError("a valid region needs at least one object, got none")
        if not 0 <= anchor < K:
            raise ValueError(f"anchor {anchor} is not one of the {K} objects")
        if np.any(np.isnan(B)) or np.any(B <= 0):
            raise ValueError("ratio bounds must be positive (NaN or <= 0 found)")
        np.fill_diagonal(B, np.inf)
        # Edge j -> i with weight log B_ij encodes x_i <= x_j + log B_ij.
        with np.errstate(divide="ignore"):
            W = np.log(B)
        np.fill_diagonal(W, 0.0)
        dist = W.copy()
        for m in range(K):
            dist = np.minimum(dist, dist[:, m : m + 1] + dist[m : m + 1, :])
        # dist[i, j] is the tightest bound on x_i - x_j. The inequalities are strict, so the region
        # is empty iff some cycle has total weight <= 0: dist[i, j] + dist[j, i] <= 0 for i != j.
        cycle = dist + dist.T
        np.fill_diagonal(cycle, np.inf)
        bad = sorted(set(np.argwhere(cycle <= 0).ravel().tolist()))
        if bad:
            raise EmptyRegionError(
                f"the valid region is empty: the depth-order constraints of objects {bad} contradict each other"
            )
        hi = np.exp(dist[:, anchor])  # x_k - x_a <= dist[k, a]
        lo = np.exp(-dist[anchor, :])  # x_a - x_k <= dist[a, k]
        intervals = np.stack([lo, hi], axis=1)
        intervals[anchor] = 1.0
        return cls(anchor=anchor, ratio_bounds=B, intervals=intervals)

    @property
    def num_objects(self) -> int:
        return self.ratio_bounds.shape[0]

    def log_margin(self, scales: np.ndarray) -> np.ndarray:
        """Smallest slack ``min_ij log B_ij - (log s_i - log s_j)`` per scale vector.

        ``scales`` is ``(K,)`` or ``(N, K)``; positive means strictly valid. Returns ``()`` or
        ``(N,)``. Non-positive or non-finite scales are reported as ``-inf`` (invalid).
        """
        s = np.asarray(scales, dtype=np.float64)
        single = s.ndim == 1
        s = np.atleast_2d(s)
        if s.shape[1] != self.num_objects:
            raise ValueError(f"expected {self.num_objects} scales, got {s.shape[1]}")
        ok = np.all(np.isfinite(s) & (s > 0), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.log(np.where(s > 0, s, 1.0))
            logB = np.log(self.ratio_bounds)
        slack = logB[None] - (x[:, :, None] - x[:, None, :])
        K = self.num_objects
        slack[:, np.arange(K), np.arange(K)] = np.inf
        m = slack.reshape(len(s), -1).min(axis=1)
        m = np.where(ok, m, -np.inf)
        return m[0] if single else m

    def contains(self, scales: np.ndarray, log_margin: float = 0.0) -> np.ndarray | bool:
        """Whether scale vector(s) are valid, optionally with a safety margin in log space.

        The anchor's entry is used as given; pass it as 1 for the usual convention.
        """
        m = self.log_margin(scales)
        return m > log_margin


@dataclass
class _InnerBox:
    """The product of a region's intervals cut to a scale box: it holds the whole region inside
    the box. ``free``: the objects sampled (all but the anchor and those with ``lo == hi`` in the
    box, held at that scale, e.g. an object a run does not model); ``base``: the scales of the
    others (anchor 1); ``volume``: its share of the box's volume (0 when the region misses it)."""

    free: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    base: np.ndarray
    volume: float

    def draw(self, n: int, rng: np.random.Generator, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
        """``n`` scale vectors ``(n, K)`` uniform in the inner box (or in ``[lo, hi]`` per object)."""
        lo = self.lo if lo is None else lo
        hi = self.hi if hi is None else hi
        s = np.repeat(self.base[None], n, 0)
        f = self.free
        s[:, f] = lo[f] + (hi[f] - lo[f]) * rng.random((n, int(f.sum())))
        return s


def _volume_share(lo: np.ndarray, hi: np.ndarray, box: np.ndarray, free: np.ndarray) -> float:
    """The share of ``box (K, 2)``'s volume that ``[lo, hi]`` holds on the ``free`` axes (in log
    space: 7 factors of 1e-1 stay exact)."""
    return float(np.exp(np.sum(np.log((hi[free] - lo[free]) / (box[free, 1] - box[free, 0])))))


def _inner_box(region: ValidRegion, box: np.ndarray) -> _InnerBox:
    """:class:`_InnerBox` of ``region`` in ``box (K, 2)``; one-line error for a malformed box."""
    box = np.asarray(box, dtype=np.float64)
    others = np.array([k != region.anchor for k in range(region.num_objects)])
    if box.shape != (region.num_objects, 2) or not np.all(box[others, 1] >= box[others, 0]):
        raise ValueError(f"box must be ({region.num_objects}, 2) with lo < hi for every free object, got {box.tolist()}")
    free = others & (box[:, 1] > box[:, 0])
    if not free.any():
        raise ValueError(f"box {box.tolist()} leaves no object free")
    lo = np.maximum(box[:, 0], region.intervals[:, 0])
    hi = np.minimum(box[:, 1], region.intervals[:, 1])
    base = np.where(others & ~free, box[:, 0], 1.0)
    if np.any(hi[free] <= lo[free]):
        return _InnerBox(free, lo, hi, base, 0.0)
    return _InnerBox(free, lo, hi, base, _volume_share(lo, hi, box, free))


def box_share(region: ValidRegion, box: np.ndarray, samples: int = 200_000, seed: int = 0, chunk: int = 50_000) -> tuple[float, float]:
    """Share of a scale box that is valid, under the uniform (linear) measure a sampler draws from.

    Args:
        region: the exact region (the anchor's scale fixed at 1).
        box: ``(K, 2)`` per-object ``[lo, hi]`` ranges, e.g. Eq. 1's (the anchor's row is ignored).
        samples: Monte Carlo points; ``seed`` makes the estimate reproducible.

    Returns:
        ``(share, standard_error)``. The region lies inside the product of its intervals, so the
        points are drawn in that product cut to the box and the hit rate is multiplied by the
        sub-box's share of the box's volume: shares of 1e-6 and below stay measurable.
    """
    inner = _inner_box(region, box)
    if inner.volume == 0.0:
        return 0.0, 0.0
    rng = np.random.default_rng(seed)
    hits = 0
    for start in range(0, samples, chunk):
        hits += int(np.count_nonzero(region.contains(inner.draw(min(chunk, samples - start), rng))))
    p = hits / samples
    return inner.volume * p, inner.volume * float(np.sqrt(p * (1 - p) / samples))


#: How far the "near" stratum reaches past the region's interval box: this many of the box's own
#: widths on each side of every free axis (cut to the scale box). A learned set errs mostly just
#: past the region's bounds; there the uniform points are too sparse: so few fall in a learned
#: set's excess that its IoU would vary with the points' seed.
NEAR_WIDTHS = 1.0


@dataclass
class SetSamples:
    """Fixed points for measuring a learned valid set against the exact region (see :func:`set_accuracy`).

    Three nested strata: the region's interval box cut to the scale box (inner), that box widened by
    :data:`NEAR_WIDTHS` of its widths on each side (near, cut to the scale box), and the scale box.

    Attributes:
        uniform: ``(n, K)`` scales uniform in the box (the anchor at 1).
        inner: ``(n, K)`` scales uniform in the inner box (the region's intervals cut to the box).
        near: ``(n, K)`` scales uniform in the near box.
        in_near: ``(n,)`` which ``uniform`` points lie in the near box.
        near_in_inner: ``(n,)`` which ``near`` points lie in the inner box.
        exact: ``(n,)`` which ``inner`` points lie in the region.
        inner_volume: the inner box's share of the box's volume (0 when the region misses the box).
        near_volume: the near box's share of the box's volume (0 when the region misses the box).
    """

    uniform: np.ndarray
    inner: np.ndarray
    near: np.ndarray
    in_near: np.ndarray
    near_in_inner: np.ndarray
    exact: np.ndarray
    inner_volume: float
    near_volume: float

    @property
    def strata(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(uniform, inner, near)``: the points a learned set is evaluated at, in
        :func:`set_accuracy`'s argument order."""
        return self.uniform, self.inner, self.near


def _inside(points: np.ndarray, free: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which points ``(n, K)`` lie strictly inside ``[lo, hi]`` on the ``free`` axes."""
    return np.all((points[:, free] > lo[free]) & (points[:, free] < hi[free]), axis=1)


def set_samples(region: ValidRegion, box: np.ndarray, samples: int, seed: int = 0) -> SetSamples:
    """``samples`` points uniform in ``box (K, 2)``, as many in the inner box and as many in the
    near box (stratified).

    A learned set is compared with a region that may fill 1e-6 of the box (8 objects): uniform
    points alone would hold none of it. Every region point lies in the inner box, so drawing there
    measures the region and its overlap with the learned set at a rate ``1 / inner_volume`` higher;
    the near box does the same for a learned set that reaches a little past the region.
    """
    ib = _inner_box(region, box)
    box = np.asarray(box, dtype=np.float64)
    rng = np.random.default_rng(seed)
    uniform = ib.draw(samples, rng, box[:, 0], box[:, 1])
    if ib.volume == 0.0:
        none = np.zeros(samples, dtype=bool)
        return SetSamples(uniform, uniform.copy(), uniform.copy(), none, none.copy(), none.copy(), 0.0, 0.0)
    inner = ib.draw(samples, rng)
    f = ib.free
    pad = NEAR_WIDTHS * (ib.hi - ib.lo)
    near_lo, near_hi = np.maximum(box[:, 0], ib.lo - pad), np.minimum(box[:, 1], ib.hi + pad)
    near = ib.draw(samples, rng, near_lo, near_hi)
    near_volume = _volume_share(near_lo, near_hi, box, f)
    return SetSamples(uniform, inner, near, _inside(uniform, f, near_lo, near_hi), _inside(near, f, ib.lo, ib.hi), np.asarray(region.contains(inner), dtype=bool), ib.volume, near_volume)


def _learned_share(samples: SetSamples, lu: np.ndarray, li: np.ndarray, ln: np.ndarray) -> float:
    """The learned set's share of the box: outside the near box from the uniform points, between
    the near and inner boxes from the near points, inside the inner box from the inner points."""
    return (float(np.mean(lu & ~samples.in_near)) + samples.near_volume * float(np.mean(ln & ~samples.near_in_inner))
            + samples.inner_volume * float(np.mean(li)))


def set_accuracy(samples: SetSamples, learned_uniform: np.ndarray, learned_inner: np.ndarray,
                 learned_near: np.ndarray) -> dict[str, float]:
    """Precision, recall and IoU of a learned set (its membership at ``samples.uniform``,
    ``samples.inner`` and ``samples.near``, ``(n,)`` bool each) against the exact region, as
    shares of the box.

    Unbiased stratified estimates: the learned set's share is its share outside the near box
    (uniform points), plus ``near_volume`` times its share of the near box outside the inner box
    (near points), plus ``inner_volume`` times its share of the inner box (inner points); the
    region and the overlap lie inside the inner box, so they come from the inner points only. An
    empty learned set has precision 0. ``exact_points`` (region points drawn) says how well the
    region was resolved; with none of them recall and IoU are NaN, not a number that looks measured.
    """
    v = samples.inner_volume
    lu, li, ln = (np.asarray(x, bool) for x in (learned_uniform, learned_inner, learned_near))
    learned = _learned_share(samples, lu, li, ln)
    exact = v * float(np.mean(samples.exact))
    both = v * float(np.mean(li & samples.exact))
    points = int(np.count_nonzero(samples.exact))
    nan = float("nan")
    return {
        "precision": both / learned if learned > 0 else 0.0,
        "recall": both / exact if points else nan,
        "iou": both / (learned + exact - both) if points else nan,
        "exact_fraction": exact,
        "learned_fraction": learned,
        "exact_points": points,
    }


def limiting_bounds(region: ValidRegion, samples: SetSamples, learned_uniform: np.ndarray, learned_inner: np.ndarray,
                    learned_near: np.ndarray, chunk: int = 50_000) -> list[dict[str, float]]:
    """Which of the region's bounds ``s_i / s_j < B_ij`` a learned set gets wrong, and by how much.

    Every region point the learned set misses is charged to the bound it lies nearest (smallest
    log slack): the learned set cuts that bound too tight. Every learned point outside the region
    is charged to the bound it violates most: the learned set reaches past it. Both are volumes
    in units of the region's (:func:`set_accuracy`'s stratified estimates), so over all pairs
    ``missed`` sums to ``1 - recall`` and ``excess`` to the learned set's volume outside the
    region over the region's (``recall / precision - recall``).

    Returns one entry per ordered pair with a finite bound of which at least one object's scale
    varies over the samples: ``i``, ``j``, ``bound`` (``B_ij``), ``missed``, ``excess``; empty
    when no region point was drawn (nothing to charge against). A pair of objects both held at
    one scale (the anchor, an object a run does not model) has the same slack at every point, so
    it limits nothing; near 0 (an object standing on the anchor) it would otherwise be every
    miss's nearest bound.
    """
    B = region.ratio_bounds
    varies = samples.uniform.min(0) < samples.uniform.max(0)
    pairs = np.argwhere(np.isfinite(B) & ~np.eye(region.num_objects, dtype=bool) & (varies[:, None] | varies[None, :]))
    exact_points = int(np.count_nonzero(samples.exact))
    if not exact_points or not len(pairs):
        return []
    logB = np.log(B[pairs[:, 0], pairs[:, 1]])

    def charge(points: np.ndarray) -> np.ndarray:
        """Points per pair whose log slack ``log B_ij - (log s_i - log s_j)`` is the smallest:
        the nearest bound inside the region, the most violated one outside."""
        counts = np.zeros(len(pairs))
        for a in range(0, len(points), chunk):
            with np.errstate(divide="ignore"):  # a scale of exactly 0 (box edge): slack -inf, still a pick
                x = np.log(points[a:a + chunk])
            sl = logB[None] - (x[:, pairs[:, 0]] - x[:, pairs[:, 1]])
            np.add.at(counts, sl.argmin(1), 1.0)
        return counts

    n = len(samples.inner)
    lu, li, ln = (np.asarray(x, bool) for x in (learned_uniform, learned_inner, learned_near))
    v = samples.inner_volume
    exact = v * exact_points / n
    missed = charge(samples.inner[samples.exact & ~li]) * v / n
    # Learned points outside the region, from the same strata as set_accuracy: inside the inner box
    # from the inner points, between it and the near box from the near points, beyond that from
    # the uniform points.
    excess = (charge(samples.inner[~samples.exact & li]) * v / n
              + charge(samples.near[ln & ~samples.near_in_inner]) * samples.near_volume / len(samples.near)
              + charge(samples.uniform[lu & ~samples.in_near]) / len(samples.uniform))
    return [{"i": int(i), "j": int(j), "bound": float(B[i, j]), "missed": float(m / exact), "excess": float(e / exact)}
            for (i, j), m, e in zip(pairs, missed, excess)]

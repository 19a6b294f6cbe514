"""Soft Z-buffer (paper Eq. 16-18) and per-sample validity labels (Eq. 13).

Each object's depth is rendered once per ray, independently and in its own unit; a scale vector
``sbar`` then implies the segmentation ``softmax_k(-sbar_k d_k)`` over the objects that cover the
ray. ``H`` scale samples therefore cost ``H`` cheap tensor operations instead of ``H`` composite
renders.

Everything is float64. The hard segmentation compares ``log sbar_k + log d_k`` (sums of logs
cannot overflow for any positive finite inputs); the soft one is a ``log_softmax`` so it is
returned as finite log-probabilities even when ``sbar * d`` spans many orders of magnitude.

Labels are per scale *sample*, as in the public code: a sample is valid when the segmentation it
implies matches the masks on (nearly) all contested rays of the batch (rays where at least two
objects are present, the only ones a scale can get wrong). Per-ray labels would instead teach
the network the fraction of rays a sample gets right.

:class:`OrderConstraints` is the same test in closed form for a large ray pool: a ray labelled
``i`` that object ``j`` also covers is explained by ``sbar`` iff ``log sbar_i - log sbar_j <
log d_j - log d_i``, so per object pair the rays are one sorted array of thresholds and the
number of rays a scale vector gets wrong is a ``searchsorted``. Scoring ``H`` samples against
every contested training pixel then costs ``O(pairs * H log R)`` instead of ``O(H R K)``, so
labels need no random ray batch (whose luck decides whether the few rays that bound a scale are
in it).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


def scaled_log_depth(depth: torch.Tensor, covered: torch.Tensor, sbar: torch.Tensor) -> torch.Tensor:
    """``log(sbar_k d_k)`` of shape ``(H, R, K)``; ``+inf`` where object k does not cover the ray.

    Args:
        depth: ``(R, K)`` independent planar depths in each object's unit (any value where not covered).
        covered: ``(R, K)`` bool, object k is hit by the ray.
        sbar: ``(H, K)`` positive scale vectors.
    """
    d = torch.where(covered, depth.double(), torch.ones_like(depth, dtype=torch.float64))
    logd = torch.log(d.clamp_min(1e-300))
    z = torch.log(sbar.double())[:, None, :] + logd[None]
    return torch.where(covered[None], z, torch.full_like(z, float("inf")))


def implied_segmentation(depth: torch.Tensor, covered: torch.Tensor, sbar: torch.Tensor) -> torch.Tensor:
    """Hard segmentation ``(H, R)``: the covering object with the smallest scaled depth.

    ``depth (R, K)``, ``covered (R, K)`` and ``sbar (H, K)`` as in :func:`scaled_log_depth`.
    """
    return scaled_log_depth(depth, covered, sbar).argmin(-1)


def soft_segmentation_log(depth: torch.Tensor, covered: torch.Tensor, sbar: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Eq. 18 as log-probabilities ``(H, R, K)``: ``log_softmax_k(-sbar_k d_k / temperature)``
    of ``depth (R, K)``, ``covered (R, K)`` and ``sbar (H, K)`` (see :func:`scaled_log_depth`).

    Objects that do not cover the ray get ``-inf``. Rays that no object covers get a uniform
    distribution. The argmax equals :func:`implied_segmentation` (up to exact ties).

    Limit: a scaled depth ``sbar_k d_k`` beyond float64's range (~1.8e308, far outside any
    scene) is clamped to the largest float, so two such objects tie instead of giving NaN.
    """
    log_z = scaled_log_depth(depth, covered, sbar)
    big = torch.finfo(torch.float64).max
    logits = torch.where(covered[None], (-torch.exp(log_z) / temperature).clamp_min(-big), torch.full_like(log_z, float("-inf")))
    none = ~covered.any(-1)
    logits = torch.where(none[None, :, None], torch.zeros_like(logits), logits)
    return torch.log_softmax(logits, dim=-1)


def sample_accuracy(seg: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Fraction ``(H,)`` of rays whose implied segmentation ``seg (H, R)`` equals ``gt (R,)``."""
    if seg.shape[1] == 0:
        return torch.ones(seg.shape[0], dtype=torch.float64, device=seg.device)
    return (seg == gt[None]).double().mean(1)


def validity_labels(accuracy: torch.Tensor, tolerance: float = 0.0, topk: int = 1, noise_floor: float = 0.0) -> tuple[torch.Tensor, bool]:
    """0/1 label ``(H,)`` per scale sample from its accuracy ``(H,)`` on the batch's contested rays (Eq. 13).

    A sample is valid when its error rate ``1 - accuracy`` is at most ``noise_floor +
    tolerance``. ``noise_floor`` is the error rate no scale vector avoids (learned geometry is
    not exact: rays that contradict each other); with exact depths it is 0. When no sample
    passes, the ``topk`` best samples are labelled valid (the public code's fallback: the
    network keeps a positive class). Returns ``(labels, fell_back)``.
    """
    labels = (1.0 - accuracy <= noise_floor + tolerance + 1e-12).to(torch.float32)
    if labels.sum() > 0 or topk <= 0:
        return labels, False
    idx = torch.topk(accuracy, min(topk, accuracy.numel())).indices
    labels[idx] = 1.0
    return labels, True


def softz_labels(
    depth: torch.Tensor,
    covered: torch.Tensor,
    gt: torch.Tensor,
    sbar: torch.Tensor,
    tolerance: float = 0.0,
    topk: int = 1,
    noise_floor: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Labels of ``H`` scale samples ``sbar (H, K)`` from one depth render of a ray batch:
    ``depth (R, K)``, ``covered (R, K)`` and the mask label ``gt (R,)`` per ray.

    Only contested rays count: the ground-truth object covers the ray and at least one other
    object does too. Returns ``(labels (H,), accuracy (H,), fell_back)``.
    """
    gt_cov = covered.gather(1, gt.clamp(0, covered.shape[1] - 1)[:, None])[:, 0] & (gt < covered.shape[1])
    contested = gt_cov & (covered.sum(1) >= 2)
    seg = implied_segmentation(depth[contested], covered[contested], sbar)
    acc = sample_accuracy(seg, gt[contested])
    labels, fell_back = validity_labels(acc, tolerance, topk, noise_floor)
    return labels, acc, fell_back


@dataclass
class OrderConstraints:
    """Depth-order constraints of labelled rays, grouped by ordered object pair.

    Attributes:
        pairs: ``(i, j)`` = (labelled object, another object covering the ray).
        thresholds: per pair the sorted ``log d_j - log d_i`` (float64) of its rays.
        rays: number of rays the constraints come from.
    """

    pairs: list[tuple[int, int]]
    thresholds: list[torch.Tensor]
    rays: int

    @property
    def count(self) -> int:
        """Number of (ray, other object) constraints."""
        return int(sum(len(t) for t in self.thresholds))

    def violations(self, sbar: torch.Tensor) -> torch.Tensor:
        """Violated constraints ``(H,)`` of scale vectors ``sbar (H, K)``.

        On a ray covered by exactly two objects a violation is the implied segmentation
        (:func:`implied_segmentation`) disagreeing with the label; a ray with more covering
        objects counts once per object it puts in front of the labelled one.
        """
        return self.pair_violations(sbar).sum(1)

    def pair_violations(self, sbar: torch.Tensor) -> torch.Tensor:
        """Violated constraints per pair ``(H, len(pairs))`` of scale vectors ``sbar (H, K)``."""
        log_s = torch.log(sbar.double())
        out = torch.zeros(sbar.shape[0], len(self.pairs), dtype=torch.float64, device=sbar.device)
        for p, ((i, j), thr) in enumerate(zip(self.pairs, self.thresholds)):
            delta = (log_s[:, i] - log_s[:, j]).contiguous()
            out[:, p] = torch.searchsorted(thr, delta, right=True).double()
        return out

    def sizes(self) -> torch.Tensor:
        """Constraints per pair ``(len(pairs),)``."""
        return torch.tensor([len(t) for t in self.thresholds], dtype=torch.float64)


def order_constraints(depth: torch.Tensor, covered: torch.Tensor, gt: torch.Tensor) -> OrderConstraints:
    """Constraints of rays with label ``gt (R,)``, depths ``(R, K)`` and coverage ``(R, K)``.

    Rays whose labelled object does not cover them, or that no other object covers, constrain
    nothing and are left out.
    """
    K = covered.shape[1]
    logd = torch.log(depth.double().clamp_min(1e-300))
    valid = (gt >= 0) & (gt < K)
    g = gt.clamp(0, K - 1)
    own = covered.gather(1, g[:, None])[:, 0] & valid
    pairs, thresholds = [], []
    for i in range(K):
        rows = own & (g == i)
        if not bool(rows.any()):
            continue
        for j in range(K):
            if j == i:
                continue
            m = rows & covered[:, j]
            if bool(m.any()):
                pairs.append((i, j))
                thresholds.append(torch.sort(logd[m, j] - logd[m, i]).values.contiguous())
    return OrderConstraints(pairs, thresholds, int((own & (covered.sum(1) >= 2)).sum()))


def trimmed_labels(pair_violations: torch.Tensor, sizes: torch.Tensor, trim: float) -> torch.Tensor:
    """0/1 labels ``(H,)`` from per-pair violation counts ``(H, P)`` (:meth:`OrderConstraints.pair_violations`).

    A sample is valid when, on every object pair, it violates at most what the best sample (fewest
    violations in all) violates there plus ``trim`` of the pair's rays. The best sample's
    violations are the noise floor: rays no scale vector explains together with the rest
    (floaters, a silhouette that bleeds). ``trim`` drops the few rays of a pair whose learned
    depths are off; the bound a pair sets is decided by its handful of tightest rays, so a
    single global tolerance would let one pair's noise decide for all. The best sample is
    always valid, so the network always keeps a positive class.
    """
    if pair_violations.shape[1] == 0:
        return torch.ones(pair_violations.shape[0], dtype=torch.float32, device=pair_violations.device)
    floor = pair_violations[pair_violations.sum(1).argmin()]
    allow = floor + torch.floor(trim * sizes.to(pair_violations))
    return (pair_violations <= allow[None]).all(1).to(torch.float32)

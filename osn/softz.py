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
"""

from __future__ import annotations

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
    """Hard segmentation ``(H, R)``: the covering object with the smallest scaled depth."""
    return scaled_log_depth(depth, covered, sbar).argmin(-1)


def soft_segmentation_log(depth: torch.Tensor, covered: torch.Tensor, sbar: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Eq. 18 as log-probabilities ``(H, R, K)``: ``log_softmax_k(-sbar_k d_k / temperature)``.

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
    """0/1 label per scale sample from its accuracy on the batch's contested rays (Eq. 13).

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
    """Labels of ``H`` scale samples from one depth render of a ray batch.

    Only contested rays count: the ground-truth object covers the ray and at least one other
    object does too. Returns ``(labels (H,), accuracy (H,), fell_back)``.
    """
    gt_cov = covered.gather(1, gt.clamp(0, covered.shape[1] - 1)[:, None])[:, 0] & (gt < covered.shape[1])
    contested = gt_cov & (covered.sum(1) >= 2)
    seg = implied_segmentation(depth[contested], covered[contested], sbar)
    acc = sample_accuracy(seg, gt[contested])
    labels, fell_back = validity_labels(acc, tolerance, topk, noise_floor)
    return labels, acc, fell_back

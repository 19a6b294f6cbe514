"""Depth-order constraints and per-sample validity labels (the paper's Eq. 11-13, hard limit).

Each object's depth is rendered once per ray, independently and in its own unit. A scale vector
``sbar`` explains a ray labelled ``i`` that object ``j`` also covers iff ``i`` stays in front:
``log sbar_i - log sbar_j < log d_j - log d_i``. That is the argmax of the paper's soft
Z-buffer (Eq. 16-18, ``softmax_k(-sbar_k d_k)``) compared with the mask, i.e. its hard limit:
the labels are 0/1 and never differentiated, so the soft weights add nothing to them, and the
hard form can be evaluated exactly on every contested training pixel instead of a ray batch.

:class:`OrderConstraints` holds, per object pair, one sorted array of thresholds, so the number of
rays a scale vector gets wrong is a ``searchsorted``: scoring ``H`` samples against ``R`` rays
costs ``O(pairs * H log R)`` instead of ``O(H R K)``. Labels are per scale *sample*, as in the
public code (per-ray labels would teach the network the fraction of rays a sample gets right);
:func:`trimmed_labels` allows each pair the noise floor of the best sample plus a small share.
Everything is float64 log-depth, so depth ratios over any finite range stay exact.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import torch


@dataclass
class OrderConstraints:
    """Depth-order constraints of labelled rays, grouped by ordered object pair.

    Attributes:
        pairs: ``(i, j)`` = (labelled object, another object covering the ray).
        thresholds: per pair the sorted ``log d_j - log d_i`` (float64) of its rays.
        rays: number of rays the constraints come from.
        dropped: the pairs :func:`minority_pairs` left out, with their ray counts.
    """

    pairs: list[tuple[int, int]]
    thresholds: list[torch.Tensor]
    rays: int
    dropped: dict[tuple[int, int], int] = field(default_factory=dict)

    @property
    def count(self) -> int:
        """Number of (ray, other object) constraints."""
        return int(sum(len(t) for t in self.thresholds))

    def violations(self, sbar: torch.Tensor) -> torch.Tensor:
        """Violated constraints ``(H,)`` of scale vectors ``sbar (H, K)``.

        On a ray covered by exactly two objects a violation is the hard Z-buffer (the covering
        object of smallest ``sbar_k d_k``) disagreeing with the label; a ray with more covering
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


def order_constraints(depth: torch.Tensor, covered: torch.Tensor, gt: torch.Tensor, minority: float = 0.0) -> OrderConstraints:
    """Constraints of rays with label ``gt (R,)``, depths ``(R, K)`` and coverage ``(R, K)``.

    Rays whose labelled object does not cover them, or that no other object covers, constrain
    nothing and are left out. A pair ``(i, j)`` with fewer than ``minority`` times the rays of
    its opposite ``(j, i)`` is left out too (:func:`minority_pairs`).
    """
    K = covered.shape[1]
    logd = torch.log(depth.double().clamp_min(1e-300))
    valid = (gt >= 0) & (gt < K)
    g = gt.clamp(0, K - 1)
    own = covered.gather(1, g[:, None])[:, 0] & valid
    found: dict[tuple[int, int], torch.Tensor] = {}
    for i in range(K):
        rows = own & (g == i)
        if not bool(rows.any()):
            continue
        for j in range(K):
            if j == i:
                continue
            m = rows & covered[:, j]
            if bool(m.any()):
                found[(i, j)] = torch.sort(logd[m, j] - logd[m, i]).values.contiguous()
    drop = minority_pairs({p: len(t) for p, t in found.items()}, minority)
    pairs = [p for p in found if p not in drop]
    return OrderConstraints(pairs, [found[p] for p in pairs], int((own & (covered.sum(1) >= 2)).sum()),
                            {p: len(found[p]) for p in found if p in drop})


def minority_pairs(counts: dict[tuple[int, int], int], minority: float) -> set[tuple[int, int]]:
    """The pairs ``(i, j)`` whose ray count is below ``minority`` times that of ``(j, i)``.

    On the pixels two objects share, one of them is in front. When ``j`` covers many pixels
    labelled ``i`` ("``i`` in front") and ``i`` covers a few labelled ``j``, those few are almost
    always ``i``'s field filling a gap it cannot resolve (the table seen between a chair's legs,
    a silhouette one pixel too wide) rather than the two objects interleaving: measured on
    dining-table and chessboard at 64 px, every such minority pair was violated on all its rays by
    every exact configuration, and kept, it empties the learned valid set. Dropping a genuine
    minority pair only loosens a bound.
    """
    if minority <= 0:
        return set()
    return {(i, j) for (i, j), n in counts.items() if n < minority * counts.get((j, i), 0)}


def in_front_pairs(pairs: Iterable[tuple[int, int]]) -> frozenset[tuple[int, int]]:
    """The constrained pairs ``(i, j)`` ("``i`` in front of ``j``") whose opposite ``(j, i)`` is not
    among them: wherever the two objects overlap, ``i`` is the one in front (the opposite had no
    rays, or so few that :func:`minority_pairs` dropped them as a bleeding silhouette)."""
    ps = set(pairs)
    return frozenset((i, j) for i, j in ps if (j, i) not in ps)


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

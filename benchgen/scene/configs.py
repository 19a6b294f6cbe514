"""Choosing G ground-truth configurations inside the valid region (numpy only).

Candidates are drawn uniformly (seeded) in log-scale space from the box given by each object's
valid interval, the room limit and ``scale_range``, all shrunk by the log margin; candidates
whose pairwise slack ``ValidRegion.log_margin`` is not above the margin are dropped. Greedy
farthest-point sampling in log space then picks G spread-out ones, starting from the authored
scene (all ones) when it qualifies; each pick is checked for plausibility and skipped if not.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from scenecore.validity import ValidRegion


class ConfigurationError(ValueError):
    """G configurations cannot be found with the requested margin."""


def candidate_box(region: ValidRegion, room_limits: np.ndarray, scale_range: tuple[float, float], margin: float) -> np.ndarray:
    """``(K, 2)`` log-scale sampling box per object (the anchor's is ``[0, 0]``)."""
    lo = np.maximum(region.intervals[:, 0], scale_range[0])
    hi = np.minimum(np.minimum(region.intervals[:, 1], room_limits), scale_range[1])
    with np.errstate(divide="ignore"):
        box = np.stack([np.log(lo) + margin, np.log(hi) - margin], axis=1)
    box[region.anchor] = 0.0
    return box


def choose_configurations(
    region: ValidRegion,
    room_limits: np.ndarray,
    plausibility: Callable[[np.ndarray], str | None],
    count: int,
    margin: float,
    scale_range: tuple[float, float],
    candidates: int,
    seed: int,
    names: list[str] | None = None,
) -> np.ndarray:
    """``(count, K)`` scale vectors strictly inside ``region`` with ``margin``, plausible, spread out.

    Raises:
        ConfigurationError: an object has no room for the margin, or fewer than ``count``
            plausible candidates exist.
    """
    K = region.num_objects
    names = names or [str(k) for k in range(K)]
    box = candidate_box(region, room_limits, scale_range, margin)
    for k in range(K):
        if k != region.anchor and not box[k, 0] < box[k, 1]:
            lo, hi = np.exp(box[k] + [-margin, margin])
            raise ConfigurationError(
                f"object {names[k]!r} can only be scaled within ({lo:.4g}, {hi:.4g}): no room for a log margin of {margin}"
            )
    rng = np.random.default_rng(seed)
    x = rng.uniform(box[:, 0], box[:, 1], size=(candidates, K))
    x[:, region.anchor] = 0.0
    x = np.concatenate([np.zeros((1, K)), x])  # the authored scene first
    s = np.exp(x)
    keep = region.contains(s, log_margin=margin) & np.all((x >= box[:, 0]) & (x <= box[:, 1]), axis=1)
    x, s = x[keep], s[keep]
    if len(x) == 0:
        raise ConfigurationError(f"no candidate lies inside the valid region with a log margin of {margin}; lower the margin")
    chosen: list[int] = []
    dist = np.full(len(x), np.inf)
    rejected = 0
    order_key = -region.log_margin(s)  # first pick: the authored scene, else the deepest candidate
    first = 0 if np.allclose(x[0], 0.0) else int(np.argmin(order_key))
    pick = first
    while len(chosen) < count:
        reason = plausibility(s[pick])
        if reason is None:
            chosen.append(pick)
            dist = np.minimum(dist, np.linalg.norm(x - x[pick], axis=1))
        else:
            rejected += 1
        dist[pick] = -np.inf
        if len(chosen) < count:
            if not np.any(dist > 0):
                raise ConfigurationError(
                    f"only {len(chosen)} of {count} configurations fit (valid with log margin {margin}, plausible; "
                    f"{rejected} candidates rejected as implausible); lower --configs or the margin"
                )
            pick = int(np.argmax(dist))
    return s[chosen]

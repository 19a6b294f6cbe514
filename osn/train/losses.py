"""The stage-1 terms that are more than a mean squared error, as functions of rendered rays.

Each takes what :func:`osn.model.volume.render` returns and gives a scalar
loss; :class:`osn.train.trainer.Trainer` picks the rays and weights them (docs/training.md, Schedule).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F



def sparse_depth_loss(depth: torch.Tensor, target: torch.Tensor, robust: float = 0.0) -> torch.Tensor:
    """Mean loss of rendered depths ``(P,)`` against sparse depths ``(P,)`` (object units).

    ``robust`` 0: squared error. ``k > 0``: Cauchy, ``c^2 log(1 + r^2 / c^2)`` with the scale ``c``
    ``k`` times the batch's median absolute residual ``r`` (not differentiated): the squared error
    while the field is far from every depth (early: all residuals large), and a bounded pull from
    the few depths far from the rest once it fits them. SfM gives such depths on repeated texture
    (gnome-house's checker floor: many of the room's sparse depths near half the true depth,
    docs/preprocess.md), and a squared error moves the surface toward them.
    """
    if not target.numel():
        return depth.sum() * 0.0
    if robust <= 0:
        return F.mse_loss(depth, target)  # the plain squared error, bit for bit
    r2 = (depth - target).square()
    # Floored so a batch that fits exactly (median residual 0) stays finite: log1p(0 / tiny) = 0.
    c2 = (robust * robust * r2.detach().median()).clamp_min(1e-12)
    return (c2 * torch.log1p(r2 / c2)).mean()


#: How far a silhouette ray's log depth may exceed its inner neighbour's before
#: :func:`edge_excess` counts it: a 2% step, about what a curved surface's edge shows at one pixel.
EDGE_SLOPE = 0.02


def edge_excess(depth: torch.Tensor, acc: torch.Tensor, inner_depth: torch.Tensor, inner_acc: torch.Tensor,
                slope: float = EDGE_SLOPE) -> torch.Tensor:
    """Mean squared excess of silhouette rays' log depth over their inner neighbours' (held fixed)
    beyond ``slope``; depths ``(n,)`` are the renderer's unnormalised ``sum w t`` with opacity ``acc``.

    On a silhouette ray the field's soft edge is crossed only partly, and the opacity term then
    puts the rest of the ray's weight behind the surface: the edge reads farther than the object
    and the contact bounds it sets come out tight (docs/training.md). One-sided, so an edge may
    read nearer than inside (a rim in front); only rays where both hit the object (``acc > 0.5``)
    count, an empty ray having no depth. 0 (with a gradient path) when none does.
    """
    hit = (acc > 0.5) & (inner_acc > 0.5)
    if not bool(hit.any()):
        return acc.sum() * 0.0
    d = torch.log(depth[hit] / acc[hit])
    d_in = torch.log(inner_depth[hit] / inner_acc[hit]).detach()
    return F.relu(d - d_in - slope).square().mean()


def disparity_curvature(depth: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
    """Mean squared second difference of disparity along pixel strips, relative to the middle
    pixel's (held fixed): ``depth``, ``acc`` ``(S, L)`` the renderer's ``sum w t`` and opacity on
    ``S`` strips of ``L`` adjacent pixels. ``(,)``; 0 (with a gradient path) when no triple of
    adjacent rays all hit something (``acc > 0.5``).

    Along an image line, a plane's disparity (inverse planar depth) is affine in the pixel
    coordinate, so this is 0 on any plane: a floor or wall continued behind an object costs
    nothing, while a hidden surface that leaves the visible one around it (the room's fog behind
    the gnome's feet, in front of the floor it hides: docs/training.md) does.
    """
    hit = (acc[:, :-2] > 0.5) & (acc[:, 1:-1] > 0.5) & (acc[:, 2:] > 0.5)
    if not bool(hit.any()):
        return acc.sum() * 0.0
    disp = acc / depth.clamp_min(1e-12)  # 1 / (depth / acc); depth > 0 wherever acc > 0.5
    # Only opaque triples: an empty middle ray (disparity 0) would divide by zero, and its NaN
    # would reach the gradient even with the triple masked out afterwards.
    before, mid, after = disp[:, :-2][hit], disp[:, 1:-1][hit], disp[:, 2:][hit]
    return ((before - 2.0 * mid + after) / mid.detach()).square().mean()

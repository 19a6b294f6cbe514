"""Volume rendering of one object alone or of K scaled objects composited (Total-Recon style).

Rays are given in the *camera frame* of a training frame (or any camera expressed relative to
one): ``dirs_cam (R, 3)`` from :func:`scenecore.cameras.pixel_rays` with unit camera z, so the ray
parameter ``t`` is the planar depth. For a configuration ``sbar`` (``sbar_anchor = 1``, scene
unit = anchor unit) object k sees the ray ``o_k + t * v_k`` with ``o_k = cam_to_obj_k[:3, 3]`` and
``v_k = R_k dirs_cam / sbar_k`` (see :mod:`osn.preprocess.inputs`), so a single ``t`` is shared by all
objects and is the scene-space planar depth.

Composite rendering follows Total-Recon: total density is the sum of the objects' densities and
colour the density-weighted mix. Each object is sampled only inside its own box interval (empty
space and absent objects cost nothing) and the union of all samples is merged in ``t`` order;
because each sample carries one object's density, the merged quadrature is exactly the
density-sum / density-weighted-colour rule. The segmentation is each object's share of the
weights, returned as log-probabilities so a cross-entropy never takes the log of a probability.

Transmittance is ``exp(-exclusive_cumsum(sigma * delta))`` with optical thicknesses clamped to
a finite range, so huge densities, empty rays and zero-length intervals stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch

from osn.model.fields import Field

#: Optical thickness of one sample is clamped here: exp(-1e4) is already 0, inf would give NaN.
MAX_OPTICAL = 1e4
#: Floor of a segmentation probability (keeps the log finite on rays no object reaches).
SEG_EPS = 1e-8
#: The ``skip_occluded`` of every render of training and of a run: samples behind a transmittance
#: below it are not shaded, which changes a ray's opacity by less than it (far below an 8-bit
#: level; docs/experiments/2026-11-26-render-each-ray-with-objects-it-hits.md). A shortcut for speed.
SKIP_OCCLUDED = 1e-3


@dataclass
class RenderOutput:
    """Per-ray results. ``depth`` is the weight-summed planar depth (not divided by ``acc``).

    Attributes:
        rgb: ``(R, 3)`` colour composited over the background.
        depth: ``(R,)`` expected planar depth ``sum_i w_i t_i`` in the rays' ``t`` unit.
        acc: ``(R,)`` accumulated opacity in [0, 1].
        log_seg: ``(R, K)`` log of each object's share of the weights (soft segmentation).
        distortion: ``(R,)`` the weights' spread along the ray (:func:`distortion`), when asked for.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    acc: torch.Tensor
    log_seg: torch.Tensor
    distortion: torch.Tensor | None = None

    def normalised_depth(self, min_acc: float = 1e-6) -> torch.Tensor:
        """Depth ``(R,)`` of the visible surface, ``depth / acc``; ``+inf`` where ``acc <= min_acc``.

        A ray that hits nothing has no surface: ``+inf`` (behind everything) rather than 0,
        which would put a surface at the camera centre and in front of every other object.
        """
        miss = self.acc <= min_acc  # False for a NaN opacity, so NaN stays NaN
        safe = torch.where(miss, torch.ones_like(self.acc), self.acc)
        return torch.where(miss, torch.full_like(self.depth, float("inf")), self.depth / safe)


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, bbox: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab intersection of rays ``o + t v`` (``origins``, ``dirs`` ``(R, 3)``) with an axis-aligned
    box ``bbox (2, 3)`` (min and max corner).

    Returns ``(t0 (R,), t1 (R,))``; the ray misses when ``t1 <= t0``. Zero direction components are
    replaced by a tiny value of the same sign so the slab test stays finite.
    """
    tiny = 1e-12
    v = torch.where(dirs.abs() < tiny, torch.full_like(dirs, tiny) * torch.where(dirs < 0, -1.0, 1.0), dirs)
    ta = (bbox[0] - origins) / v
    tb = (bbox[1] - origins) / v
    t0 = torch.minimum(ta, tb).amax(-1)
    t1 = torch.maximum(ta, tb).amin(-1)
    return t0, t1


def transmittance_weights(optical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights ``(R, S)`` and log-weights ``(R, S)`` of ordered samples with optical thickness ``(R, S)`` (>= 0).

    ``w_i = T_i (1 - exp(-tau_i))`` with ``log T_i = -sum_{j<i} tau_j`` (exclusive cumsum, no
    subtraction so no ``inf - inf``). ``log_w`` is floored at ``log(1e-30)`` for the opacity
    term, so it is finite and its gradient never meets ``log(0)`` (``0 * inf = NaN``).
    ``+inf`` is clamped to :data:`MAX_OPTICAL` (an opaque sample); a NaN stays NaN and reaches
    the loss, where training stops with ``TrainingDiverged`` (read as empty space it would hide
    a diverged field).
    """
    tau = optical.clamp(0.0, MAX_OPTICAL)  # clamp keeps NaN
    csum = torch.cumsum(tau, dim=-1)
    log_t = -torch.cat([torch.zeros_like(csum[..., :1]), csum[..., :-1]], dim=-1)
    alpha = -torch.expm1(-tau)
    w = torch.exp(log_t) * alpha
    log_w = log_t + torch.log(alpha.clamp_min(1e-30))
    return w, log_w


@dataclass
class ObjectRays:
    """One object's view of a ray batch.

    Attributes:
        field: the object's field.
        cam_to_obj: ``(R, 4, 4)`` similarity from each ray's camera frame (ray units) to the
            object, e.g. ``cam_to_obj_k[n] @ diag(1/sbar_k)`` for training frame n, or
            :func:`osn.model.placement.object_transforms` for a novel camera; any value where absent.
        present: ``(R,)`` bool, False where the object has no pose in the ray's frame.
        t_range: ``(R, 2)`` or ``(2,)`` planar-depth range (ray units) the object is sampled in,
            intersected with its box.
        guide: when > 0, a gradient-free pass of this many density samples first finds where
            the object's weights lie on each ray, and the stratified samples follow them
            (:func:`guided_positions`) instead of spreading evenly over its box.
    """

    field: Field
    cam_to_obj: torch.Tensor
    present: torch.Tensor
    t_range: torch.Tensor
    guide: int = 0

    def take(self, rows: torch.Tensor) -> "ObjectRays":
        """The same object on the rays ``rows`` (indices into the batch)."""
        return ObjectRays(self.field, self.cam_to_obj[rows], self.present[rows],
                          self.t_range if self.t_range.dim() == 1 else self.t_range[rows], self.guide)


def _box_interval(obj: ObjectRays, dirs_cam: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ray origin ``o (R, 3)`` and direction ``v (R, 3)`` in the object's frame, the interval
    ``t0, t1 (R,)`` of ``t`` inside its box and depth range, and ``ok (R,)``: posed and hit."""
    A = obj.cam_to_obj[:, :3, :3]
    o = obj.cam_to_obj[:, :3, 3]
    v = torch.einsum("rij,rj->ri", A, dirs_cam)
    t0, t1 = ray_box(o, v, obj.field.bbox)
    rng = obj.t_range.expand(dirs_cam.shape[0], 2)
    t0 = torch.maximum(t0, rng[:, 0])
    t1 = torch.minimum(t1, rng[:, 1])
    return o, v, t0, t1, obj.present & (t1 > t0)


#: Share of a guided ray's samples spread evenly over its interval whatever the weights say
#: (:func:`guided_positions`): surfaces the guide pass does not see yet still get samples.
GUIDE_EVEN_SHARE = 0.25


@torch.no_grad()
def guided_positions(field: Field, o: torch.Tensor, v: torch.Tensor, ok: torch.Tensor, u: torch.Tensor, m: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample positions ``x (R, S)`` in [0, 1] along each ray's interval and the length ``dx (R, S)``
    of the stratum each stands for, placed by the object's own weights.

    ``m`` midpoint density samples of ``field`` along ``o + x v`` (``(R, 3)``; ``v`` spans the
    whole interval, so ``x`` in [0, 1]) give each ray a piecewise-constant density of positions:
    :data:`GUIDE_EVEN_SHARE` even, the rest proportional to the object's weights. The strata are
    this density's quantiles ``[i/S, (i+1)/S]`` and ``u (R, S)`` (in [0, 1)) places one sample in
    each, so ``sum dx = 1`` and an even density gives the even stratified samples back. A box as
    deep as a room, sampled evenly, puts its samples far apart at the depths it is seen from: a
    surface then has to spread over a step to be seen at every jitter (docs/training.md). Rays without a
    finite weight (missed, or a non-finite density, which the render's own samples then meet)
    are sampled evenly.
    """
    R, S = u.shape
    dev = u.device
    xc = (torch.arange(m, device=dev) + 0.5) / m
    sig = torch.zeros(R, m, device=dev)
    if ok.any():
        pts = o[ok, None, :] + xc[None, :, None] * v[ok, None, :]
        sig[ok] = field.density(pts.reshape(-1, 3)).view(-1, m)
    w, _ = transmittance_weights(sig * (v.norm(dim=-1) / m)[:, None])
    # Each bin also takes its neighbours' weight (Mip-NeRF's max filter): an opaque surface's
    # weight lies in the bin where it starts, and the samples must also cover the bin behind it,
    # where its optical depth is still growing (without, part of its opacity leaks through).
    w = torch.nn.functional.max_pool1d(w[:, None], 3, stride=1, padding=1)[:, 0]
    total = w.sum(1, keepdim=True)
    weighted = ok[:, None] & torch.isfinite(total) & (total > 0)
    share = torch.where(weighted, w / torch.where(weighted, total, torch.ones_like(total)), torch.zeros_like(w))
    pdf = torch.where(weighted, (1.0 - GUIDE_EVEN_SHARE) * share + GUIDE_EVEN_SHARE / m, torch.full_like(w, 1.0 / m))
    cdf = torch.cumsum(pdf, 1)
    pdf, cdf = pdf / cdf[:, -1:], torch.cat([torch.zeros(R, 1, device=dev), cdf / cdf[:, -1:]], 1)  # ends at 1 exactly

    def position(q: torch.Tensor) -> torch.Tensor:
        """The inverse of the piecewise-linear cdf at quantiles ``q (R, n)``: positions in [0, 1]."""
        j = (torch.searchsorted(cdf, q.contiguous(), right=True) - 1).clamp(0, m - 1)
        frac = (q - torch.gather(cdf, 1, j)) / torch.gather(pdf, 1, j)  # pdf >= GUIDE_EVEN_SHARE / m > 0
        return ((j + frac.clamp(0.0, 1.0)) / m).clamp(0.0, 1.0)

    edges = position(torch.arange(S + 1, device=dev, dtype=u.dtype).expand(R, S + 1) / S)
    x = position((torch.arange(S, device=dev, dtype=u.dtype) + u) / S)
    # Keep each sample inside its stratum even where rounding nudges it out.
    x = torch.minimum(torch.maximum(x, edges[:, :-1]), edges[:, 1:])
    return x, edges[:, 1:] - edges[:, :-1]


def _object_samples(
    obj: ObjectRays, dirs_cam: torch.Tensor, n_samples: int, generator: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stratified samples of one object: ``(t (R,S), delta_len (R,S), points (R,S,3), view (R,3), ok (R,))``.

    ``delta_len`` is each sample's interval length in the object's own unit of length, so a
    field's opacity does not change when the object is scaled. Evenly spread over the object's
    interval, or placed by its weights when ``obj.guide > 0`` (:func:`guided_positions`).
    """
    o, v, t0, t1, ok = _box_interval(obj, dirs_cam)
    t1 = torch.where(ok, t1, t0)  # zero-length interval where missed: all samples collapse
    R = dirs_cam.shape[0]
    if generator is None:
        u = torch.full((R, n_samples), 0.5, device=dirs_cam.device)
    else:
        u = torch.rand(R, n_samples, generator=generator, device=generator.device).to(dirs_cam.device)
    span = (t1 - t0)[:, None]
    vnorm = v.norm(dim=-1, keepdim=True)
    if obj.guide > 0:
        x, dx = guided_positions(obj.field, o + t0[:, None] * v, span * v, ok, u, obj.guide)
        t = t0[:, None] + span * x
        delta_len = span * dx * vnorm
    else:  # even strata: the same arithmetic as a run trained without the guide, bit for bit
        t = t0[:, None] + span * ((torch.arange(n_samples, device=dirs_cam.device) + u) / n_samples)
        delta_len = (span / n_samples * vnorm).expand(R, n_samples)
    pts = o[:, None, :] + t[..., None] * v[:, None, :]
    view = v / vnorm.clamp_min(1e-12)
    return t, delta_len, pts, view, ok


@dataclass
class ShadedSamples:
    """One object's samples on a ray batch, evaluated once (no gradients) and reused by
    :func:`render` in place of its :class:`ObjectRays`: an object whose pose and scale are the
    same in many renders of one view (the anchor in every candidate configuration) is queried once.

    Attributes:
        t: ``(R, S)`` planar depth of each sample; ``+inf`` where the ray misses the object.
        tau: ``(R, S)`` optical thickness.
        col: ``(R, S, 3)`` colour where the object alone leaves transmittance above
            ``skip_occluded`` (0 elsewhere: no composite render can see those samples).
        skip_occluded: the threshold it was shaded with; :func:`render` needs one at least as large.
    """

    t: torch.Tensor
    tau: torch.Tensor
    col: torch.Tensor
    skip_occluded: float
    #: :meth:`alone`'s renders by (background, skip_occluded): filled on first use.
    _alone: dict = field(default_factory=dict, repr=False, compare=False)

    def take(self, rows: torch.Tensor) -> "ShadedSamples":
        """The samples of the rays ``rows`` (indices into the batch)."""
        return ShadedSamples(self.t[rows], self.tau[rows], self.col[rows], self.skip_occluded)

    def alone(self, dirs_cam: torch.Tensor, background: torch.Tensor, skip_occluded: float) -> RenderOutput:
        """:func:`render` of this object alone on its whole ray batch, computed once and kept.

        Every composite of the view reuses it on the rays that hit this object alone
        (:func:`render_by_hits`): each ray's result depends on that ray's samples only, so the
        rows taken from it equal a render of those rows.
        """
        key = (tuple(background.tolist()), float(skip_occluded))
        if key not in self._alone:
            self._alone[key] = render([self], dirs_cam, self.t.shape[1], None, background, skip_occluded)
        return self._alone[key]


def object_hits(obj: ObjectRays | ShadedSamples, dirs_cam: torch.Tensor) -> torch.Tensor:
    """``(R,)`` bool: the rays on which the object has samples (posed there, its box hit)."""
    if isinstance(obj, ShadedSamples):
        return torch.isfinite(obj.t[:, 0])  # a missed ray's samples all lie at +inf
    return _box_interval(obj, dirs_cam)[4]


def _optical_thickness(obj: ObjectRays, samples: tuple, keep: torch.Tensor) -> torch.Tensor:
    """Optical thickness ``(R, S)`` of one object's samples (0 where ``keep (R, S)`` is False)."""
    sig = torch.zeros(keep.shape, device=keep.device)
    if keep.any():
        sig[keep] = obj.field.density(samples[2][keep])
    return sig * samples[1]


def _exclusive_transmittance(tau: torch.Tensor) -> torch.Tensor:
    """Transmittance ``(R, S)`` in front of each of ``tau (R, S)``'s ordered samples."""
    csum = torch.cumsum(tau.clamp(0.0, MAX_OPTICAL), 1)
    return torch.exp(-torch.cat([torch.zeros_like(csum[:, :1]), csum[:, :-1]], 1))


@torch.no_grad()
def shade(obj: ObjectRays, dirs_cam: torch.Tensor, n_samples: int, skip_occluded: float = 0.0) -> ShadedSamples:
    """Evaluate one object's deterministic (midpoint) samples on ``dirs_cam (R, 3)`` for reuse."""
    smp = _object_samples(obj, dirs_cam, n_samples, None)
    t, ok = smp[0], smp[4]
    R, S = t.shape
    m = ok[:, None].expand(R, S)
    tau = _optical_thickness(obj, smp, m)
    if skip_occluded > 0:  # colour only where the object alone does not hide the sample
        # Half the threshold: a composite's transmittance, summed in another order, may round
        # above the object's own at the threshold; a few more colours cost nothing.
        m = m & (_exclusive_transmittance(tau) > 0.5 * skip_occluded)
    col = torch.zeros(R, S, 3, device=t.device)
    if m.any():
        col[m] = obj.field.color(smp[2][m], smp[3][:, None, :].expand(R, S, 3)[m])
    return ShadedSamples(torch.where(ok[:, None], t, torch.full_like(t, float("inf"))), tau, col, skip_occluded)


def _visible(objects: Sequence, samples: list, keep: list[torch.Tensor], order: torch.Tensor, skip_occluded: float
             ) -> list[torch.Tensor]:
    """``keep`` narrowed to samples whose composite transmittance exceeds ``skip_occluded``
    (a gradient-free density pass over all objects, in depth order ``order (R, K*S)``)."""
    with torch.no_grad():
        tau = torch.cat([obj.tau if smp is None else _optical_thickness(obj, smp, m)
                         for obj, smp, m in zip(objects, samples, keep)], 1)
        visible_sorted = _exclusive_transmittance(torch.gather(tau, 1, order)) > skip_occluded
        visible = torch.empty_like(visible_sorted).scatter_(1, order, visible_sorted)
    S = keep[0].shape[1]
    return [m & visible[:, k * S : (k + 1) * S] for k, m in enumerate(keep)]


def _shade_kept(obj: ObjectRays | ShadedSamples, samples: tuple | None, keep: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Optical thickness ``(R, S)`` and colour ``(R, S, 3)`` of one object's kept samples (with
    gradients; 0 elsewhere). A kept sample of shaded samples is visible with the object alone,
    so its colour is cached."""
    if samples is None:
        return torch.where(keep, obj.tau, torch.zeros_like(obj.tau)), torch.where(keep[..., None], obj.col, torch.zeros_like(obj.col))
    R, S = keep.shape
    sig = torch.zeros(R, S, device=keep.device)
    col = torch.zeros(R, S, 3, device=keep.device)
    if keep.any():
        view = samples[3][:, None, :].expand(R, S, 3)[keep]
        sg, cl = obj.field.density_and_color(samples[2][keep], view)
        sig = sig.masked_scatter(keep, sg)
        col = col.masked_scatter(keep[..., None].expand(R, S, 3), cl)
    return sig * samples[1], col


def distortion(w: torch.Tensor, t: torch.Tensor, strata: torch.Tensor | None = None) -> torch.Tensor:
    """How spread out a ray's weights are, ``(R,)``, for weights ``w (R, S)`` of depth-sorted samples
    ``t (R, S)`` (``+inf`` where there is no sample) that split the ray's sampled interval into
    strata, each ``strata (R, S)`` of it (summing to 1; None: evenly, ``1/S`` each).

    Mip-NeRF 360's distortion loss, ``sum_ij w_i w_j |s_i - s_j| + sum_i w_i^2 strata_i / 3``, with
    ``s`` the position in the ray's sampled interval (0 to 1, so the value does not depend on the
    object's unit or size): a fog spread over the interval scores up to ~1/3, one opaque sample
    1/(3S) of even strata. The double sum is two cumulative sums, O(S) per ray.
    """
    finite = torch.isfinite(t)
    lo = torch.where(finite, t, torch.full_like(t, float("inf"))).amin(1, keepdim=True)
    hi = torch.where(finite, t, torch.full_like(t, -float("inf"))).amax(1, keepdim=True)
    span = torch.where(hi > lo, hi - lo, torch.ones_like(hi))  # guarded: a missed ray has no span
    s = torch.where(finite, (t - torch.where(finite, lo, torch.zeros_like(lo))) / span, torch.ones_like(t))
    w_before = torch.cumsum(w, 1) - w
    ws_before = torch.cumsum(w * s, 1) - w * s
    between = 2.0 * (w * (s * w_before - ws_before)).sum(1)
    if strata is None:
        return between + w.square().sum(1) / (3.0 * t.shape[1])
    return between + (w.square() * strata).sum(1) / 3.0


def _composite(taus: list[torch.Tensor], cols: list[torch.Tensor], t_all: torch.Tensor, order: torch.Tensor,
               bg: torch.Tensor, with_distortion: bool = False, strata: torch.Tensor | None = None) -> RenderOutput:
    """Merge K objects' samples (per object ``(R, S)`` optical thickness and ``(R, S, 3)`` colour,
    planar depths ``t_all (R, K*S)``) in depth order ``order`` into one :class:`RenderOutput`;
    ``strata (R, K*S)``: each sample's share of its ray's interval, for :func:`distortion`."""
    R, K, S = order.shape[0], len(taus), taus[0].shape[1]
    tau = torch.gather(torch.cat(taus, 1), 1, order)
    col = torch.gather(torch.cat(cols, 1), 1, order[..., None].expand(R, K * S, 3))
    t_raw = torch.gather(t_all, 1, order)
    t_sorted = torch.where(torch.isfinite(t_raw), t_raw, torch.zeros_like(t_raw))

    w, log_w = transmittance_weights(tau)
    acc = w.sum(1)
    rgb = (w[..., None] * col).sum(1) + (1.0 - acc)[:, None] * bg
    depth = (w * t_sorted).sum(1)
    # Back to per-object order, so each object's share is a logsumexp over its own S samples
    # (K x S values per ray in all, not K x (K x S) with the others masked out).
    log_w_obj = torch.empty_like(log_w).scatter(1, order, log_w).view(R, K, S)
    log_share = log_w_obj.logsumexp(2)
    # eps floor: rays that hit nothing get a uniform, finite segmentation instead of NaN.
    log_share = torch.logaddexp(log_share, torch.full_like(log_share, torch.log(torch.tensor(SEG_EPS)).item()))
    log_seg = log_share - log_share.logsumexp(1, keepdim=True)
    dist = None
    if with_distortion:
        dist = distortion(w, t_raw, None if strata is None else torch.gather(strata, 1, order) / K)
    return RenderOutput(rgb=rgb, depth=depth, acc=acc, log_seg=log_seg, distortion=dist)


def render(
    objects: Sequence[ObjectRays | ShadedSamples],
    dirs_cam: torch.Tensor,
    n_samples: int,
    generator: torch.Generator | None = None,
    background: torch.Tensor | None = None,
    skip_occluded: float = 0.0,
    with_distortion: bool = False,
) -> RenderOutput:
    """Render a ray batch of K objects composited (a single object = rendering it alone).

    The configuration (scales) is folded into each object's ``cam_to_obj`` similarity; ``t``
    and the returned depth are in the ray camera's unit (scene units for a configuration,
    the object's own unit when one object is rendered with its rigid pose). Returns per-ray
    ``(R, ...)`` results (:class:`RenderOutput`) with ``K = len(objects)``.

    Args:
        objects: per object its field, camera-to-object similarity, presence and depth range,
            or its :func:`shade`-d samples (same ``n_samples``, deterministic rendering only).
        dirs_cam: ``(R, 3)`` camera-frame directions with unit z.
        n_samples: stratified samples per object inside its box interval.
        generator: jitter source (None = interval midpoints, deterministic evaluation).
        background: ``(3,)`` colour behind everything (default black).
        skip_occluded: when > 0, a gradient-free density pass first finds samples whose
            transmittance is below this value; only the others are evaluated with gradients
            and colour (their omission changes ``acc`` by less than ``skip_occluded``).
        with_distortion: also return each ray's :func:`distortion` (meant for one object alone).
    """
    R, K, S = dirs_cam.shape[0], len(objects), n_samples
    dev = dirs_cam.device
    bg = background if background is not None else torch.zeros(3, device=dev)
    if K == 0:  # nothing to composite (e.g. every object absent from a frame): the background
        zero = torch.zeros(R, device=dev)
        return RenderOutput(rgb=bg.expand(R, 3).clone(), depth=zero, acc=zero.clone(), log_seg=torch.zeros(R, 0, device=dev))
    for obj in objects:
        if isinstance(obj, ShadedSamples) and (generator is not None or obj.t.shape != (R, S) or obj.skip_occluded > skip_occluded):
            raise ValueError("shaded samples need deterministic rendering with their ray batch, sample count and "
                             f"a skip_occluded >= theirs ({obj.skip_occluded}), got {skip_occluded}")
    # Cached objects (ShadedSamples) bring their samples, optical thickness and colour along.
    samples = [None if isinstance(obj, ShadedSamples) else _object_samples(obj, dirs_cam, S, generator) for obj in objects]
    t_obj = [obj.t if smp is None else torch.where(smp[4][:, None], smp[0], torch.full_like(smp[0], float("inf")))
             for obj, smp in zip(objects, samples)]
    t_all = torch.cat(t_obj, 1)
    order = torch.argsort(t_all, dim=1)
    keep = [torch.isfinite(t) for t in t_obj]
    if skip_occluded > 0:
        keep = _visible(objects, samples, keep, order, skip_occluded)
    shaded = [_shade_kept(obj, smp, m) for obj, smp, m in zip(objects, samples, keep)]
    strata = None  # each sample's share of its object's interval, where samples are not even
    if with_distortion and any(isinstance(obj, ObjectRays) and obj.guide > 0 for obj in objects):
        strata = torch.cat([torch.full((R, S), 1.0 / S, device=dev) if smp is None
                            else smp[1] / smp[1].sum(1, keepdim=True).clamp_min(1e-30) for smp in samples], 1)
    return _composite([x[0] for x in shaded], [x[1] for x in shaded], t_all, order, bg, with_distortion, strata)


@torch.no_grad()
def render_by_hits(
    objects: Sequence[ObjectRays | ShadedSamples],
    dirs_cam: torch.Tensor,
    n_samples: int,
    background: torch.Tensor | None = None,
    skip_occluded: float = 0.0,
    reuse_alone: bool = True,
) -> RenderOutput:
    """:func:`render` (deterministic, no gradients) with each ray composited from the objects it
    hits only: rays are grouped by the set of objects whose box they cross, and each group is
    rendered with that set. An object a ray misses adds only samples at ``+inf`` with no density,
    which sort behind the others and add zeros to every sum, so the colour, opacity and depth are
    those of :func:`render` to float rounding (sums over fewer terms; colour differs most where a
    sample's transmittance rounds across ``skip_occluded``; bit for bit for one object alone), at
    a cost that follows the
    samples that can contribute: a small object alone in a view covers a few per cent of the rays,
    and most rays of a composite hit the anchor alone.

    ``log_seg (R, K)`` is each object's log share of the weights among the objects the ray hits
    and ``-inf`` for the others (:func:`render` floors every share at ``SEG_EPS`` instead); its
    argmax is :func:`render`'s wherever some object holds a share above ``SEG_EPS``. A ray that
    hits nothing gets the background, opacity and depth 0. Rays that hit a single
    :class:`ShadedSamples` object (the anchor alone, most rays of a candidate configuration) take
    its :meth:`ShadedSamples.alone` render, made once for every configuration rendered with it
    (``reuse_alone=False`` renders them again each time: the baseline that benchmarks compare with).
    """
    R, K = dirs_cam.shape[0], len(objects)
    dev = dirs_cam.device
    bg = background if background is not None else torch.zeros(3, device=dev)
    rgb = bg.expand(R, 3).clone()
    depth = torch.zeros(R, device=dev)
    acc = torch.zeros(R, device=dev)
    log_seg = torch.full((R, K), -float("inf"), device=dev)
    if K == 0 or R == 0:
        return RenderOutput(rgb=rgb, depth=depth, acc=acc, log_seg=log_seg)
    hits = torch.stack([object_hits(obj, dirs_cam) for obj in objects], 1)  # (R, K)
    if K < 63:  # each ray's set of objects as one integer: unique over rows is much slower
        sets, group = torch.unique((hits.long() << torch.arange(K, device=dev)).sum(1), return_inverse=True)
        members = [[k for k in range(K) if c >> k & 1] for c in sets.tolist()]
    else:
        sets, group = torch.unique(hits, dim=0, return_inverse=True)
        members = [row.nonzero().flatten().tolist() for row in sets]
    for g, ks in enumerate(members):
        if not ks:  # hits nothing: the background
            continue
        rows = (group == g).nonzero().flatten()
        if reuse_alone and len(ks) == 1 and isinstance(objects[ks[0]], ShadedSamples) and objects[ks[0]].t.shape == (R, n_samples):
            whole = objects[ks[0]].alone(dirs_cam, bg, skip_occluded)
            out = RenderOutput(rgb=whole.rgb[rows], depth=whole.depth[rows], acc=whole.acc[rows], log_seg=whole.log_seg[rows])
        else:
            out = render([objects[k].take(rows) for k in ks], dirs_cam[rows], n_samples, None, bg, skip_occluded)
        rgb[rows], depth[rows], acc[rows] = out.rgb, out.depth, out.acc
        log_seg[rows[:, None], torch.tensor(ks, device=dev)[None, :]] = out.log_seg
    return RenderOutput(rgb=rgb, depth=depth, acc=acc, log_seg=log_seg)

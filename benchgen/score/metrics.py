"""Evaluation metrics for novel views: PSNR, SSIM, LPIPS, SSIMAE, PQ / mIoU, best-of-N (co-visibility
masks: :mod:`benchgen.score.covisibility`).

Conventions (docs/metrics.md has the definitions):

* Images are float RGB in [0, 1], shape ``(..., H, W, 3)``, numpy or torch (any device). Leading
  dimensions are a batch; image metrics return one value per image. Results come back as torch
  tensors when an input is a tensor, else as numpy arrays (a Python float for a single image).
* ``mask`` is boolean ``(..., H, W)``, **True where a pixel is evaluated** (e.g. co-visible).
  Masked metrics average over those pixels only; an empty mask gives NaN.
* Depth is planar, ``+inf`` where nothing is hit; instance ids are integers with ``255`` = none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Union

import numpy as np
import torch

from scenecore.dataset import NO_OBJECT
from benchgen.score.lpips import get_model

Array = Union[np.ndarray, torch.Tensor]

#: SSIM in the NeRF convention: Gaussian window sigma 1.5 truncated at 3.5 sigma (11 taps),
#: population covariances, K1 = 0.01, K2 = 0.03, data range 1 (skimage's settings in docs/metrics.md).
SSIM_SIGMA = 1.5
SSIM_RADIUS = int(3.5 * SSIM_SIGMA + 0.5)  # scipy.ndimage's radius rule -> 5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _tensor(x: Array, device: torch.device | None = None) -> torch.Tensor:
    """Float tensor view of an array; numpy float64 stays float64 (exact comparisons with skimage)."""
    t = torch.as_tensor(x, device=device)
    if not (t.is_floating_point() or t.dtype == torch.bool):
        raise TypeError(f"expected a float image/depth or a bool mask, got {t.dtype}")
    return t


def _device(*xs: Array | None) -> torch.device | None:
    return next((x.device for x in xs if isinstance(x, torch.Tensor)), None)


def _result(value: torch.Tensor, *inputs: Array | None) -> Array | float:
    """Return a tensor if any input was one, else numpy (a float for a 0-d result)."""
    if any(isinstance(x, torch.Tensor) for x in inputs):
        return value
    out = value.detach().cpu().numpy()
    return float(out) if out.ndim == 0 else out


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean over the last two dims, restricted to ``mask`` (NaN when the mask is empty)."""
    if mask is None:
        return values.mean((-2, -1))
    m = mask.to(values.dtype)
    return (values * m).sum((-2, -1)) / m.sum((-2, -1))


def _images(pred: Array, gt: Array, mask: Array | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Tensors on one device with a common dtype; batch dims broadcast (e.g. one render vs G truths)."""
    device = _device(pred, gt, mask)
    p, g = _tensor(pred, device), _tensor(gt, device)
    if p.ndim < 3 or p.shape[-1] != 3 or p.shape[-3:] != g.shape[-3:]:
        raise ValueError(f"expected (..., H, W, 3) images of one size, got {tuple(p.shape)} and {tuple(g.shape)}")
    dtype = torch.promote_types(p.dtype, g.dtype)
    p, g = torch.broadcast_tensors(p.to(dtype), g.to(dtype))
    m = None if mask is None else _tensor(mask, device).bool()
    if m is not None and torch.broadcast_shapes(m.shape, p.shape[:-1]) != p.shape[:-1]:
        raise ValueError(f"mask of shape {tuple(m.shape)} does not broadcast to images {tuple(p.shape[:-1])}")
    return p, g, m


# --------------------------------------------------------------------------------------------- PSNR


#: MSE floor of every PSNR: identical images score ``PSNR_MAX`` = 120 dB, not ``+inf``, so that
#: means over views and ground truths stay finite (8-bit quantisation is far above the floor).
MSE_FLOOR = 1e-12
PSNR_MAX = -10.0 * math.log10(MSE_FLOOR)


def psnr_from_mse(mse: Array | float) -> Array | float:
    """PSNR in dB for data range 1 from an MSE (float, numpy array or tensor, any shape).

    ``-10 log10(max(MSE, MSE_FLOOR))``: at most ``PSNR_MAX``; a NaN MSE (nothing to compare)
    stays NaN. The one PSNR of the toolkit: training, evaluation and scoring all call it.
    """
    if isinstance(mse, torch.Tensor):
        return -10.0 * torch.log10(mse.clamp_min(MSE_FLOOR))
    if isinstance(mse, np.ndarray):
        return -10.0 * np.log10(np.maximum(mse, MSE_FLOOR))
    mse = float(mse)
    return mse if math.isnan(mse) else -10.0 * math.log10(max(mse, MSE_FLOOR))


def psnr(pred: Array, gt: Array, mask: Array | None = None) -> Array | float:
    """PSNR in dB for data range 1 (:func:`psnr_from_mse`), MSE over channels and (masked) pixels.

    Identical images give ``PSNR_MAX``; an empty mask gives NaN.
    """
    p, g, m = _images(pred, gt, mask)
    mse = _masked_mean((p - g).square().mean(-1), m)
    return _result(psnr_from_mse(mse), pred, gt, mask)


def squared_error_by_id(pred: Array, gt: Array, ids: Array, num_ids: int, mask: Array | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the error is: squared error summed per ground-truth object.

    ``pred``, ``gt`` ``(..., H, W, 3)`` in [0, 1]; ``ids`` ``(..., H, W)`` the ground truth's object
    ids; ``mask`` as for :func:`psnr`. Returns float64 ``sse (num_ids + 1,)``, the sum over (masked)
    pixels of the channel-mean squared error, and ``pixels (num_ids + 1,)``, their count: slot k
    for the pixels whose id is k in ``0..num_ids-1``, the last slot for every other id (no object,
    255). ``sse.sum() / pixels.sum()`` is :func:`psnr`'s MSE over all the pixels at once, and
    ``psnr_from_mse(sse[k] / pixels[k])`` object k's PSNR on its own pixels.
    """
    p, g, m = _images(pred, gt, mask)
    k = ids.to(p.device).long() if isinstance(ids, torch.Tensor) else torch.from_numpy(np.array(ids, dtype=np.int64)).to(p.device)
    if k.shape != p.shape[:-1]:
        raise ValueError(f"ids of shape {tuple(k.shape)} do not match images {tuple(p.shape[:-1])}")
    slot = torch.where((k >= 0) & (k < num_ids), k, torch.full_like(k, num_ids)).reshape(-1)
    err = (p - g).square().mean(-1).reshape(-1).double()
    keep = torch.ones_like(slot, dtype=torch.bool) if m is None else m.expand(p.shape[:-1]).reshape(-1)
    sse = torch.bincount(slot[keep], weights=err[keep], minlength=num_ids + 1)
    pixels = torch.bincount(slot[keep], minlength=num_ids + 1).double()
    return sse.cpu().numpy(), pixels.cpu().numpy()


# --------------------------------------------------------------------------------------------- SSIM


def _gaussian_taps(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """scipy.ndimage.gaussian_filter1d's normalised taps for sigma 1.5, truncate 3.5."""
    x = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * x.square() / SSIM_SIGMA**2)
    return (w / w.sum()).to(dtype=dtype, device=device)


def _band(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(n, n - 2r)`` matrix whose column j holds the Gaussian taps on rows ``j .. j + 2r``."""
    taps = _gaussian_taps(dtype, device)
    out = torch.zeros(n, n - 2 * SSIM_RADIUS, dtype=dtype, device=device)
    cols = torch.arange(n - 2 * SSIM_RADIUS, device=device)
    for k, w in enumerate(taps):
        out[cols + k, cols] = w
    return out


def ssim_map(pred: Array, gt: Array) -> torch.Tensor:
    """Channel-averaged SSIM map ``(..., H - 10, W - 10)`` on the window-interior pixels.

    skimage filters with reflected borders and then crops the window radius (5 px) before
    averaging; on the cropped region no filter tap reaches the border, so a *valid* separable
    convolution reproduces skimage exactly and needs no padding mode.
    """
    p, g, _ = _images(pred, gt, None)
    *batch, H, W, C = p.shape
    if min(H, W) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"SSIM needs images of at least {2 * SSIM_RADIUS + 1} px a side, got {H}x{W}")
    # (B, 5, C, H, W): x, y, x^2, y^2, xy written in place (no concatenated copy).
    stack = torch.empty(math.prod(batch), 5, C, H, W, dtype=p.dtype, device=p.device)
    x, y = stack[:, 0], stack[:, 1]
    x.copy_(p.reshape(-1, H, W, C).permute(0, 3, 1, 2))
    y.copy_(g.reshape(-1, H, W, C).permute(0, 3, 1, 2))
    torch.mul(x, x, out=stack[:, 2])
    torch.mul(y, y, out=stack[:, 3])
    torch.mul(x, y, out=stack[:, 4])
    # Separable filtering as matmuls with banded matrices (exact: the zero entries add nothing):
    # rows by one plain 2-D matmul, columns by the transposed band from the left, batched over
    # images (no transposed copy); on CPU several times faster than a depthwise conv2d.
    h, w = H - 2 * SSIM_RADIUS, W - 2 * SSIM_RADIUS
    n = (stack.shape[0], 5 * C)
    f = (stack.reshape(-1, W) @ _band(W, stack.dtype, stack.device)).reshape(-1, H, w)
    f = torch.matmul(_band(H, f.dtype, f.device).T.contiguous(), f).reshape(*n, h, w)
    ux, uy, uxx, uyy, uxy = f.split(C, dim=1)
    # The formula with each product formed once and the filtered moments overwritten in place:
    # the same operations on every value in the same order (2 ux uy = 2 (ux uy) exactly).
    mx2, my2, mxy = ux * ux, uy * uy, ux * uy
    vx, vy, vxy = uxx.sub_(mx2), uyy.sub_(my2), uxy.sub_(mxy)
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    # (2 ux uy + c1)(2 vxy + c2) / ((ux^2 + uy^2 + c1)(vx + vy + c2))
    s = mxy.mul_(2).add_(c1).mul_(vxy.mul_(2).add_(c2)).div_(mx2.add_(my2).add_(c1).mul_(vx.add_(vy).add_(c2)))
    return s.mean(1).reshape(*batch, h, w)


def ssim(pred: Array, gt: Array, mask: Array | None = None) -> Array | float:
    """SSIM in the NeRF convention, equal to ``skimage.metrics.structural_similarity(pred, gt,
    data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.

    With ``mask`` the SSIM map is averaged over masked pixels of the window interior (the
    5-px border that skimage crops stays excluded), so an all-True mask gives the unmasked value.
    """
    p, g, m = _images(pred, gt, mask)
    s = ssim_map(p, g)
    if m is not None:
        r = SSIM_RADIUS
        m = m[..., r:-r, r:-r]
    return _result(_masked_mean(s, m), pred, gt, mask)


# -------------------------------------------------------------------------------------------- LPIPS


def from_rgb8(rgb: np.ndarray) -> torch.Tensor:
    """8-bit colour ``(..., 3)`` as float32 in [0, 1] (``rgb / 255``): a ground truth as SSIM and
    LPIPS compare it."""
    return torch.from_numpy(np.asarray(rgb) / np.float32(255.0))


def _lpips_input(images: torch.Tensor) -> torch.Tensor:
    """``(..., H, W, 3)`` in [0, 1] as the network's ``(B, 3, H, W)`` in [-1, 1], float32."""
    H, W = images.shape[-3:-1]
    return images.float().reshape(-1, H, W, 3).permute(0, 3, 1, 2) * 2 - 1


@torch.no_grad()
def lpips_features(images: Array, batch_size: int = 64) -> list[list[torch.Tensor]]:
    """LPIPS's normalised features of ``images (..., H, W, 3)`` in [0, 1], per batch of
    ``batch_size`` images as :func:`lpips` takes them: pass them as its ``pred_features`` or
    ``gt_features`` when one image set is compared with many (a candidate with every ground
    truth it matches, a ground truth with several candidate sets)."""
    x = _lpips_input(_tensor(images))
    model = get_model(x.device)
    return [model.normalised_features(x[i : i + batch_size]) for i in range(0, x.shape[0], batch_size)]


@torch.no_grad()
def lpips(pred: Array, gt: Array, mask: Array | None = None, batch_size: int = 64,
          pred_features: list[list[torch.Tensor]] | None = None, gt_features: list[list[torch.Tensor]] | None = None,
          ) -> Array | float:
    """LPIPS v0.1, AlexNet, images in [0, 1] (scaled to [-1, 1] as ``lpips(..., normalize=True)``).

    Without ``mask``: the official value (per-layer spatial means, summed). With ``mask``: the
    distance map of ``lpips.LPIPS(spatial=True)`` (layer maps upsampled bilinearly to the image
    size and summed) averaged over masked pixels. The two differ slightly for an all-True mask,
    because bilinear upsampling does not preserve a map's mean at the borders.
    Computed in float32 on the inputs' device, ``batch_size`` images at a time.
    ``pred_features`` / ``gt_features``: :func:`lpips_features` of ``pred`` / ``gt`` (same
    ``batch_size``, after broadcasting), used instead of running the network on them again.
    """
    p, g, m = _images(pred, gt, mask)
    batch = p.shape[:-3]
    H, W = p.shape[-3:-1]
    x0, x1 = _lpips_input(p), _lpips_input(g)
    if m is not None:
        m = m.expand(*batch, H, W).reshape(-1, H, W)
    model = get_model(p.device)
    out = []
    for j, i in enumerate(range(0, x0.shape[0], batch_size)):
        a = pred_features[j] if pred_features is not None else x0[i : i + batch_size]
        b = gt_features[j] if gt_features is not None else x1[i : i + batch_size]
        out.append(model(a, b) if m is None else _masked_mean(model.spatial(a, b, (H, W)), m[i : i + batch_size]))
    return _result(torch.cat(out).reshape(batch), pred, gt, mask)


# ------------------------------------------------------------------------------------------- SSIMAE


def _valid_medians(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """numpy's median of each row's valid entries ``(B, 1)``: the mean of the two middle order
    statistics (+inf for a row with none). On the CPU each row's two are selected in linear time
    (``np.partition``) rather than by sorting the row whole; elsewhere rows are sorted. The same values."""
    if x.device.type != "cpu":
        n = valid.sum(-1, keepdim=True)
        # Invalid entries sort last as +inf; the two middle order statistics are then gathered.
        srt = torch.where(valid, x, torch.full_like(x, math.inf)).sort(-1).values
        lo = srt.gather(-1, ((n - 1) // 2).clamp(min=0))
        hi = srt.gather(-1, (n // 2).clamp(max=x.shape[-1] - 1))
        return 0.5 * (lo + hi)
    xs, vs = x.detach().numpy(), valid.numpy()
    med = np.full((len(xs), 1), np.inf, dtype=xs.dtype)
    for r in range(len(xs)):
        v = xs[r][vs[r]]
        if v.size:
            k = [(v.size - 1) // 2, v.size // 2]
            lo, hi = np.partition(v, k)[k]
            med[r, 0] = 0.5 * (lo + hi)
    return torch.from_numpy(med)


def _median_mad_normalise(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``(x - median) / mean|x - median|`` over valid entries of each row of ``(B, N)``.

    The median is numpy's (mean of the two middle values for an even count). A constant row has
    zero deviation; it is divided by 1 instead, so it normalises to all zeros (finite).
    """
    n = valid.sum(-1, keepdim=True)
    med = _valid_medians(x, valid)
    dev = torch.where(valid, (x - med).abs(), torch.zeros_like(x)).sum(-1, keepdim=True) / n
    dev = torch.where(dev > 0, dev, torch.ones_like(dev))
    return torch.where(valid, (x - med) / dev, torch.zeros_like(x))


def ssimae(pred_depth: Array, gt_depth: Array, mask: Array | None = None) -> Array | float:
    """Scale- and shift-invariant depth MAE (Ranftl et al.; the OSN paper's SSIMAE).

    Each of prediction and ground truth is normalised per image to zero median and unit mean
    absolute deviation over the valid pixels (``mask`` and both depths finite), then the mean
    absolute difference over those pixels is returned. Invariant to ``a * d + b`` with ``a > 0``
    applied to either map. Depth maps are ``(..., H, W)``; no valid pixel gives NaN.
    """
    device = _device(pred_depth, gt_depth, mask)
    p, g = _tensor(pred_depth, device), _tensor(gt_depth, device)
    if p.shape != g.shape or p.ndim < 2:
        raise ValueError(f"expected two (..., H, W) depth maps of one shape, got {tuple(p.shape)} and {tuple(g.shape)}")
    dtype = torch.promote_types(p.dtype, g.dtype)
    p, g = p.to(dtype), g.to(dtype)
    valid = torch.isfinite(p) & torch.isfinite(g)
    if mask is not None:
        valid = valid & _tensor(mask, device).bool()
    batch = p.shape[:-2]
    p, g, valid = (t.reshape(-1, p.shape[-2] * p.shape[-1]) for t in (p, g, valid.expand(p.shape)))
    err = (_median_mad_normalise(p, valid) - _median_mad_normalise(g, valid)).abs()
    out = torch.where(valid, err, torch.zeros_like(err)).sum(-1) / valid.sum(-1)
    return _result(out.reshape(batch), pred_depth, gt_depth, mask)


# ------------------------------------------------------------------------------------- segmentation


@dataclass(frozen=True)
class SegmentationScores:
    """Panoptic quality (PQ = SQ x RQ per class, averaged over classes) and mean IoU of one view."""

    pq: float
    sq: float
    rq: float
    miou: float
    num_classes: int  # classes present in either map over the evaluated pixels


def segmentation_scores(
    pred_ids: Array, gt_ids: Array, mask: Array | None = None, ignore_id: int = NO_OBJECT
) -> SegmentationScores:
    """PQ and mIoU of instance-id maps ``(H, W)`` (ids ``0..K-1``, ``ignore_id`` = none).

    Every object id is its own class with at most one segment per map, so standard PQ reduces to:
    a class is a true positive iff its predicted and ground-truth segments overlap with IoU > 0.5
    (then PQ_c = SQ_c = IoU_c, RQ_c = 1), otherwise PQ_c = SQ_c = RQ_c = 0. Classes are those
    present in either map; PQ, SQ, RQ and mIoU (mean IoU_c) average over them. Pixels outside
    ``mask`` or with ground truth ``ignore_id`` are not evaluated; a prediction of ``ignore_id``
    on an object pixel counts as missing that object. No class present gives NaN everywhere.
    """
    gt = np.asarray(gt_ids.cpu() if isinstance(gt_ids, torch.Tensor) else gt_ids).astype(np.int64)
    pr = np.asarray(pred_ids.cpu() if isinstance(pred_ids, torch.Tensor) else pred_ids).astype(np.int64)
    if gt.shape != pr.shape or gt.ndim != 2:
        raise ValueError(f"expected two (H, W) id maps of one shape, got {pr.shape} and {gt.shape}")
    keep = gt != ignore_id
    if mask is not None:
        keep &= np.asarray(mask.cpu() if isinstance(mask, torch.Tensor) else mask, dtype=bool)
    gt, pr = gt[keep], pr[keep]
    hit = pr != ignore_id
    if (gt < 0).any() or (pr[hit] < 0).any():
        raise ValueError("instance ids must be non-negative")
    size = int(max(gt.max(initial=-1), pr[hit].max(initial=-1))) + 1
    area_gt = np.bincount(gt, minlength=size)
    area_pr = np.bincount(pr[hit], minlength=size)
    inter = np.bincount(gt[gt == pr], minlength=size)
    present = (area_gt + area_pr) > 0
    if not present.any():
        nan = float("nan")
        return SegmentationScores(nan, nan, nan, nan, 0)
    iou = inter[present] / (area_gt + area_pr - inter)[present]
    tp = iou > 0.5
    pq = float(np.where(tp, iou, 0.0).mean())
    return SegmentationScores(pq=pq, sq=pq, rq=float(tp.mean()), miou=float(iou.mean()), num_classes=int(present.sum()))


# ---------------------------------------------------------------------------------------- best-of-N


@dataclass(frozen=True)
class BestOfN:
    """Per ground truth g: the chosen sample ``indices[g]`` and its mean score ``scores[g]``.

    ``mean_scores`` ``(N, G)`` holds every sample's mean over views; the best score using only the
    first n samples is ``np.maximum.accumulate(mean_scores, axis=0)[n - 1]`` (for higher-is-better).
    """

    indices: np.ndarray
    scores: np.ndarray
    mean_scores: np.ndarray


def best_of_n(
    scores: Array | Callable[[int], Array], num_samples: int | None = None, higher_is_better: bool = True
) -> BestOfN:
    """Match each ground-truth configuration to the sample with the best mean score over its views.

    Args:
        scores: an ``(N, G, V)`` array (e.g. PSNR of sample n against view v of ground truth g), or
            a callable ``scores(n) -> (G, V)`` evaluated for ``n = 0..num_samples-1`` so that each
            sample is rendered once and never all held in memory.
        num_samples: N, required with a callable.
        higher_is_better: True for PSNR/SSIM, False for LPIPS or errors.

    Views scoring NaN (e.g. an empty co-visibility mask) are left out of a mean; a sample whose
    views are all NaN is never chosen over one with a score. Ties go to the lowest sample index.
    """
    if callable(scores):
        if num_samples is None or num_samples < 1:
            raise ValueError("best_of_n with a callable needs num_samples >= 1")
        rows = [np.asarray(torch.as_tensor(scores(n)).cpu(), dtype=np.float64) for n in range(num_samples)]
        if any(r.ndim != 2 or r.shape != rows[0].shape for r in rows):
            raise ValueError(f"scores(n) must return (G, V) arrays of one shape, got {[r.shape for r in rows[:3]]}...")
        table = np.stack(rows)
    else:
        table = np.asarray(torch.as_tensor(scores).cpu(), dtype=np.float64)
        if table.ndim != 3:
            raise ValueError(f"scores must be (N samples, G ground truths, V views), got shape {table.shape}")
    finite_views = ~np.isnan(table)
    # nanmean without the all-NaN warning: sum of non-NaN / their count.
    mean = np.where(finite_views, table, 0.0).sum(-1) / finite_views.sum(-1).clip(min=1)
    mean[~finite_views.any(-1)] = np.nan
    ranked = np.where(np.isnan(mean), -np.inf, mean if higher_is_better else -mean)
    idx = np.argmax(ranked, axis=0)
    return BestOfN(indices=idx, scores=mean[idx, np.arange(mean.shape[1])], mean_scores=mean)

"""The layered best-of-N search: approximate PSNR of N samples against G ground truths, fast.

An object's look in a view depends only on its own scale, so each object is rendered alone at Q
quantised scales per view (a *layer*), a sample is approximated by depth-sorted over-compositing
of its objects' nearest layers, and all N x G PSNRs of a view come from three matrix products.
``benchmarks/bench_bestofn.py`` measures this against the naive search.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from scenecore import dataset as D
from benchgen.score import metrics as M
from benchgen.score.truth import Truth
from osn.model.parallel import map_views
from osn.model.run import TrainedRun
from osn.sample.configurations import Samples


def scale_levels(sbar: np.ndarray, levels: int) -> list[np.ndarray]:
    """Per object position of ``sbar (N, K)``: at most ``levels`` scales at evenly spaced quantiles
    of the samples' log-scales, from their smallest to their largest (ascending, distinct).

    Quantiles rather than an even log grid because the samples crowd one end of their range (a
    box sampled evenly in scale holds more of them at large scales): the levels go where the
    samples are, and a sample's layer is that much nearer its own scale (docs/metrics.md)."""
    out = []
    for k in range(sbar.shape[1]):
        lg = np.log(sbar[:, k].astype(np.float64))
        if levels <= 1 or lg.max() - lg.min() <= 1e-9:
            out.append(np.array([float(sbar[:, k].min())]))
            continue
        out.append(np.exp(np.unique(np.quantile(lg, np.linspace(0.0, 1.0, levels)))))
    return out


def nearest_level(values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Index of the grid level nearest to each value in log space."""
    lg = np.log(grid)
    return np.abs(np.log(values)[:, None] - lg[None]).argmin(1)


@dataclass
class Layer:
    """One object rendered alone at one scale in one view (premultiplied colour)."""

    color: torch.Tensor  # (P, 3) premultiplied
    alpha: torch.Tensor  # (P,)
    depth: torch.Tensor  # (P,) planar depth, +inf where empty


def render_layers(run: TrainedRun, frame: D.Frame, grids: list[np.ndarray], base_sbar: np.ndarray) -> list[list[Layer]]:
    """``layers[k][q]``: object position k rendered alone at scale ``grids[k][q]`` in ``frame``."""
    bg = np.asarray(run.config.get("background", (0.0, 0.0, 0.0)))
    out: list[list[Layer]] = []
    for k, grid in enumerate(grids):
        per = []
        for s in grid:
            sbar = base_sbar.copy()
            sbar[k] = s
            r = run.render_view(frame.camera_to_world, frame.time_index, sbar, objects=[k])
            a = r["acc"].reshape(-1)
            col = r["rgb"].reshape(-1, 3) - (1.0 - a)[:, None] * bg
            dep = r["depth"].reshape(-1)  # +inf where the layer is empty
            per.append(Layer(torch.from_numpy(col).float(), torch.from_numpy(a).float(), torch.from_numpy(dep).float()))
        out.append(per)
    return out


def stack_layers(layers: list[list[Layer]]) -> list[Layer]:
    """Per object its Q layers as one :class:`Layer` of ``(Q, P, ...)`` tensors (what
    :func:`composite_layers` indexes; made once per view instead of once per chunk of samples)."""
    return [Layer(torch.stack([q.color for q in per]), torch.stack([q.alpha for q in per]), torch.stack([q.depth for q in per]))
            for per in layers]


def composite_layers(layers: list[list[Layer]] | list[Layer], level_idx: np.ndarray, background: np.ndarray) -> torch.Tensor:
    """Approximate images ``(n, P, 3)`` of n samples: their objects' layers over-composited by depth.

    ``layers``: per object its layers (``layers[k][q]``), or :func:`stack_layers` of them."""
    stacked = layers if layers and isinstance(layers[0], Layer) else stack_layers(layers)
    idx = torch.as_tensor(np.asarray(level_idx, dtype=np.int64))
    n, K = idx.shape
    col = torch.stack([stacked[k].color[idx[:, k]] for k in range(K)], 1)  # (n, K, P, 3)
    alpha = torch.stack([stacked[k].alpha[idx[:, k]] for k in range(K)], 1)
    depth = torch.stack([stacked[k].depth[idx[:, k]] for k in range(K)], 1)
    order = torch.argsort(depth, dim=1)
    alpha = torch.gather(alpha, 1, order)
    col = torch.gather(col, 1, order[..., None].expand_as(col))
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], 1), 1)
    img = (trans[..., None] * col).sum(1)
    rest = (trans[:, -1] * (1.0 - alpha[:, -1]))[..., None]
    return img + rest * torch.as_tensor(background, dtype=img.dtype)


def masked_targets(gt: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """What :func:`masked_mse_matrix` needs of G targets ``(G, P, 3)`` and masks ``(G, P)``, which
    do not change between chunks of images of one view: per target the mask per channel
    ``(G, P*3)``, the masked target ``(G, P*3)``, its squared sum ``(G,)`` and mask size ``(G,)``."""
    m3 = mask.double().repeat_interleave(3, dim=1)  # (G, P*3)
    y = gt.reshape(gt.shape[0], -1).double()
    return m3, m3 * y, (m3 * y * y).sum(1), m3.sum(1)


def masked_mse_matrix(images: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor,
                      targets: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
    """MSE ``(n, G)`` of n images ``(n, P, 3)`` against G targets ``(G, P, 3)`` on masks ``(G, P)``.

    Three matrix products instead of an ``n x G x P`` tensor: sum m (x - y)^2 = x^2.m - 2 x.(m y) + m.y^2.
    ``targets``: :func:`masked_targets` of ``gt`` and ``mask``, made once for many image chunks.
    """
    x = images.reshape(images.shape[0], -1).double()
    m3, my, my2, size = masked_targets(gt, mask) if targets is None else targets
    sse = (x * x) @ m3.T - 2.0 * x @ my.T + my2[None]
    out = sse.clamp_min(0.0) / size.clamp_min(1.0)[None]
    return torch.where(size[None] > 0, out, torch.full_like(out, float("nan")))


def layered_psnr(
    run: TrainedRun, samples: Samples, truth: Truth, levels: int, chunk: int = 64, echo: Callable[[str], None] | None = None
) -> np.ndarray:
    """Approximate PSNR ``(N, G, V)`` of every sample against every ground-truth view (co-visible pixels);
    views side by side on CPU threads (:func:`osn.model.parallel.map_views`)."""
    N, G, V = len(samples.sbar), truth.num_configurations, truth.num_views
    grids = scale_levels(samples.sbar, levels)
    idx = np.stack([nearest_level(samples.sbar[:, k], grids[k]) for k in range(samples.sbar.shape[1])], 1)
    bg = np.asarray(run.config.get("background", (0.0, 0.0, 0.0)))
    base = np.array([g[0] for g in grids])
    out = np.full((N, G, V), np.nan)

    def view(v: int) -> None:  # fills out[:, :, v], a slice no other view writes
        layers = stack_layers(render_layers(run, truth.frames[v], grids, base))
        y = torch.from_numpy(truth.masked_rgb[v].reshape(G, -1, 3)).double() / 255.0  # view-major: no copy
        targets = masked_targets(y, torch.from_numpy(truth.mask[v]))
        for i in range(0, N, chunk):
            imgs = composite_layers(layers, idx[i : i + chunk], bg)
            out[i : i + chunk, :, v] = M.psnr_from_mse(masked_mse_matrix(imgs, y, None, targets).numpy())

    map_views(view, list(range(V)), run.device, "layered search" if echo is not None else None)
    return out

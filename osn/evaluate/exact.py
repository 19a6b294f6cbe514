"""Exact renders of one configuration on the evaluated views, and its image metrics against ground truth."""

from __future__ import annotations

import numpy as np
import torch

from benchgen.score import metrics as M
from osn.evaluate.ground_truth import GroundTruth
from osn.model.run import TrainedRun


def render_sample(run: TrainedRun, gt: GroundTruth, sbar: np.ndarray) -> dict[str, np.ndarray]:
    """Exact composite renders of one configuration on every evaluated view: rgb/depth/ids/acc ``(V, ...)``."""
    views = [run.render_view(f.camera_to_world, f.time_index, sbar) for f in gt.frames]
    return {k: np.stack([r[k] for r in views]) for k in ("rgb", "depth", "ids", "acc")}


def exact_psnr(render: dict[str, np.ndarray], gt: GroundTruth) -> np.ndarray:
    """PSNR ``(G, V)`` of one exactly rendered sample against every ground truth."""
    G, V = gt.rgb.shape[:2]
    out = np.empty((G, V))
    pred = torch.from_numpy(render["rgb"]).double()
    for g in range(G):
        out[g] = np.asarray(M.psnr(pred, torch.from_numpy(gt.rgb[g]).double() / 255.0, torch.from_numpy(gt.mask[g])))
    return out


def full_metrics(render: dict[str, np.ndarray], gt: GroundTruth, g: int, with_lpips: bool) -> dict[str, float]:
    """All image metrics of a rendered sample against ground truth g (means over its views)."""
    pred = torch.from_numpy(render["rgb"]).float()
    ref = torch.from_numpy(gt.rgb[g]).float() / 255.0
    mask = torch.from_numpy(gt.mask[g])
    out = {
        "psnr": float(np.nanmean(np.asarray(M.psnr(pred, ref, mask)))),
        "ssim": float(np.nanmean(np.asarray(M.ssim(pred, ref, mask)))),
        "ssimae": float(np.nanmean(np.asarray(M.ssimae(torch.from_numpy(render["depth"]).float(),
                                                        torch.from_numpy(gt.depth[g]).float(), mask)))),
    }
    if with_lpips:
        out["lpips"] = float(np.nanmean(np.asarray(M.lpips(pred, ref, mask))))
    pq, miou = [], []
    for v in range(len(gt.frames)):
        s = M.segmentation_scores(render["ids"][v], gt.ids[g, v], gt.mask[g, v])
        pq.append(s.pq)
        miou.append(s.miou)
    out["pq"] = float(np.nanmean(pq)) * 100.0
    out["miou"] = float(np.nanmean(miou)) * 100.0
    return out


def mean_std(rows: list[dict[str, float]]) -> dict[str, list[float]]:
    """Per metric of ``rows`` (one per ground truth): ``[mean, std]`` ignoring NaN."""
    keys = rows[0].keys() if rows else []
    return {k: [float(np.nanmean([r[k] for r in rows])), float(np.nanstd([r[k] for r in rows]))] for k in keys}

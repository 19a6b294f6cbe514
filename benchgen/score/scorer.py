"""Score any method's candidates against every ground-truth configuration of a dataset.

1. :func:`truth.load_truth`: evaluated views and co-visibility masks of the G configurations.
2. :func:`bestofn.psnr_matrix`: every candidate streamed once, exact masked PSNR against all G
   truths; each ground truth is matched to the candidate with the best mean PSNR.
3. :func:`match_metrics`: PSNR, SSIM, LPIPS (and SSIMAE, PQ, mIoU when every candidate has depth
   / ids) of the matched candidates only, mean and std over the G ground truths.
4. :func:`error_by_object`: where the matched candidates' squared error lies, by the ground
   truth's objects (any method: it reads the ground truth's ids, not the candidate's).

Candidates come from a :class:`predictions.CandidateSource`: a prediction directory
(:class:`predictions.PredictionDir`) or arrays in memory (:class:`predictions.MemorySource`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from benchgen.score import bestofn
from benchgen.score import metrics as M
from benchgen.score.predictions import Candidate, CandidateSource
from benchgen.score.truth import Truth

#: Reported metrics in table order: key, header, format, higher is better.
METRICS = (("psnr", "PSNR ↑", "{:.2f}"), ("ssim", "SSIM ↑", "{:.3f}"), ("lpips", "LPIPS ↓", "{:.3f}"),
           ("ssimae", "SSIMAE ↓", "{:.3f}"), ("pq", "PQ ↑", "{:.1f}"), ("miou", "mIoU ↑", "{:.1f}"))


@dataclass
class ScoreResult:
    """Everything a report needs. ``matrix`` ``(N, G)``: mean PSNR of candidate n against truth g."""

    names: list[str]
    matrix: np.ndarray
    per_ground_truth: list[dict[str, Any]]
    summary: dict[str, dict[str, float]]
    curves: dict[str, Any]
    timings: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)
    by_object: dict[str, Any] = field(default_factory=dict)


def _to_unit(rgb: np.ndarray) -> torch.Tensor:
    """Colour ``(..., 3)`` uint8 / uint16 / float as a float64 tensor in [0, 1]."""
    return torch.from_numpy(bestofn.colour_units(rgb) / bestofn.UNIT)


def _nanmean(x: Any) -> float:
    x = np.asarray(x, dtype=np.float64)
    return float(x[~np.isnan(x)].mean()) if (~np.isnan(x)).any() else float("nan")


def match_metrics(
    cand: Candidate, rgb: np.ndarray, depth: np.ndarray, ids: np.ndarray, mask: np.ndarray, with_lpips: bool,
    lpips_features: tuple[list, list] | None = None, num_objects: int = 0, pred: torch.Tensor | None = None,
) -> dict[str, Any]:
    """Means over views of a candidate against one ground truth (without PSNR, which the pass has).

    ``rgb (V, H, W, 3)`` uint8, ``depth``/``ids``/``mask`` ``(V, H, W)``: the ground truth and its
    co-visibility masks. SSIM and LPIPS in float32 (as ``osn evaluate``); SSIMAE only when the
    candidate has depth, PQ / mIoU (in percent) only when it has ids. ``lpips_features``: the
    candidate's and the ground truth's :func:`metrics.lpips_features`, when already computed.
    With ``num_objects``, also ``object_sse`` / ``object_pixels`` (lists of ``num_objects + 1``):
    :func:`metrics.squared_error_by_id` by the ground truth's ids. ``pred``: the candidate's colour
    as float64 in [0, 1], when already converted.
    """
    pred = (_to_unit(cand.rgb) if pred is None else pred).float()
    ref, m = M.from_rgb8(rgb), torch.from_numpy(mask)
    out: dict[str, Any] = {"ssim": _nanmean(M.ssim(pred, ref, m))}
    if num_objects:  # float32 as SSIM's inputs: no float64 copy of the ground truth (large test sets)
        sse, px = M.squared_error_by_id(pred, ref, ids, num_objects, m)
        out["object_sse"], out["object_pixels"] = sse.tolist(), px.astype(np.int64).tolist()
    if with_lpips:
        pf, gf = lpips_features if lpips_features is not None else (None, None)
        out["lpips"] = _nanmean(M.lpips(pred, ref, m, pred_features=pf, gt_features=gf))
    if cand.depth is not None:
        out["ssimae"] = _nanmean(M.ssimae(torch.from_numpy(np.asarray(cand.depth, np.float64)), torch.from_numpy(depth.astype(np.float64)), m))
    if cand.ids is not None:
        seg = [M.segmentation_scores(cand.ids[v], ids[v], mask[v]) for v in range(len(mask))]
        out["pq"] = 100.0 * _nanmean([s.pq for s in seg])
        out["miou"] = 100.0 * _nanmean([s.miou for s in seg])
    return out


def error_by_object(rows: list[dict[str, Any]], names: list[str]) -> dict[str, Any]:
    """Squared error of the matched candidates by ground-truth object, pooled over ground truths.

    ``rows``: :func:`match_metrics` rows with ``object_sse`` / ``object_pixels``; ``names``: the
    objects' names by id. Per object (and ``no object`` when such pixels were evaluated): its
    share of the evaluated pixels, its share of the squared error, and the PSNR on its pixels
    (pooled: total error over total pixels, so it weighs ground truths by their pixels). The
    shares say which object a better method should improve; a share of error above the share of
    pixels marks an object rendered worse than the rest.
    """
    sse = np.sum([r["object_sse"] for r in rows], axis=0)
    px = np.sum([r["object_pixels"] for r in rows], axis=0).astype(np.float64)
    labels = list(names) + ["no object"]
    keep = [k for k in range(len(labels)) if px[k] > 0]
    total_sse, total_px = float(sse.sum()), float(px.sum())
    return {
        "objects": [labels[k] for k in keep],
        "pixel_share": [float(px[k] / total_px) for k in keep],
        "error_share": [float(sse[k] / total_sse) if total_sse > 0 else float("nan") for k in keep],
        "psnr": [float(M.psnr_from_mse(sse[k] / px[k])) for k in keep],
        "psnr_all": float(M.psnr_from_mse(total_sse / total_px)) if total_px else float("nan"),
    }


def summarise(rows: list[dict[str, Any]], keys: list[str]) -> dict[str, dict[str, float]]:
    """Mean and (population) std over ground truths of each metric, NaN rows left out."""
    out = {}
    for k in keys:
        x = np.array([r[k] for r in rows], dtype=np.float64)
        x = x[~np.isnan(x)]
        out[k] = {"mean": float(x.mean()) if x.size else float("nan"), "std": float(x.std()) if x.size else float("nan")}
    return out


def metric_keys(source: CandidateSource, with_lpips: bool) -> list[str]:
    """The metrics reported for these candidates (depth and ids only when every candidate has them)."""
    keys = ["psnr", "ssim"] + ["lpips"] * with_lpips + ["ssimae"] * source.has_depth
    return keys + ["pq", "miou"] * source.has_ids


def score(truth: Truth, source: CandidateSource, with_lpips: bool = True, workers: int = 1, progress: bool = False) -> ScoreResult:
    """Best-of-N scoring of ``source``'s candidates against every configuration of ``truth``.

    Every candidate is checked while it is scored (a malformed one raises
    :class:`predictions.PredictionError` before anything is returned); the full metrics are
    computed for the matched candidates only, each loaded once more.
    """
    from tqdm import tqdm

    if with_lpips:
        M.get_model()  # fail on missing LPIPS weights before the long pass, not after it
    timings = {}
    t0 = time.perf_counter()
    matrix = bestofn.psnr_matrix(truth, source, workers, progress)
    best = bestofn.match(matrix)
    timings["candidate_pass_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    num_objects = truth.scene.num_objects
    rows: list[dict[str, Any]] = []
    with tqdm(total=truth.num_configurations, desc="matched metrics", unit="gt", disable=not progress, dynamic_ncols=True) as bar:
        for n in np.unique(best.indices):  # each matched candidate is loaded once
            cand = source.load(int(n))
            pred = _to_unit(cand.rgb)
            # LPIPS's network runs once per image set: the candidate's here, each ground truth's
            # kept by `truth` across candidate sets (the distances are the same, feature for feature).
            pred_features = M.lpips_features(pred.float()) if with_lpips else None
            for g in np.flatnonzero(best.indices == n):
                rgb, depth, ids = truth.views(int(g))
                row = {"configuration": int(g), "match": source.names[n], "match_index": int(n), "psnr": float(best.scores[g])}
                feats = (pred_features, truth.lpips_features(int(g))) if with_lpips else None
                rows.append({**row, **match_metrics(cand, rgb, depth, ids, truth.masks(int(g)), with_lpips, feats,
                                                    num_objects, pred)})
                bar.update()
    rows.sort(key=lambda r: r["configuration"])
    timings["metrics_s"] = time.perf_counter() - t0
    keys = metric_keys(source, with_lpips)
    info = {
        "num_candidates": len(source.names), "num_ground_truths": truth.num_configurations,
        "num_views": truth.num_views, "views": [f.name for f in truth.frames],
        "covisible_fraction": float(truth.mask.mean()), "metrics": keys, "workers": workers,
        "distinct_matches": int(len(np.unique(best.indices))),
    }
    by_object = error_by_object(rows, [o.name for o in sorted(truth.scene.objects, key=lambda o: o.id)])
    return ScoreResult(list(source.names), matrix, rows, summarise(rows, keys), bestofn.curves(matrix), timings, info, by_object)

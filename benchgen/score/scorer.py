"""Score any method's candidates against every ground-truth configuration of a dataset.

1. :func:`truth.load_truth`: evaluated views and co-visibility masks of the G configurations.
2. :func:`bestofn.psnr_matrix`: every candidate streamed once, exact masked PSNR against all G
   truths; each ground truth is matched to the candidate with the best mean PSNR.
3. :func:`match_metrics`: PSNR, SSIM, LPIPS (and SSIMAE, PQ, mIoU when every candidate has depth
   / ids) of the matched candidates only, mean and std over the G ground truths.
4. :func:`error_by_object`: where the matched candidates' squared error lies, by the ground
   truth's objects (any method: it reads the ground truth's ids, not the candidate's).
5. :mod:`fidelity`: when the candidates hold renders of the training video, which of them explain
   it, and best of N over those alone (the guarded figure); :mod:`coverage`: the share of ground
   truths matched and of candidates matching, over PSNR levels.

Candidates come from a :class:`predictions.CandidateSource`: a prediction directory
(:class:`predictions.PredictionDir`) or arrays in memory (:class:`predictions.MemorySource`).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from benchgen.score import bestofn
from benchgen.score import coverage as COV
from benchgen.score import fidelity as F
from benchgen.score import metrics as M
from benchgen.score.parallel import ordered_map
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
    #: Files written beside ``metrics.json`` (name -> bytes): the per-file digests of :mod:`provenance`.
    files: dict[str, bytes] = field(default_factory=dict)
    #: :func:`fidelity.check`'s record, with the guarded matches' ``summary`` and ``per_ground_truth``.
    fidelity: dict[str, Any] = field(default_factory=dict)
    #: :func:`coverage.curves` of the matrix (over the faithful candidates too when fidelity was checked).
    coverage: dict[str, Any] = field(default_factory=dict)


def _to_unit(rgb: np.ndarray) -> torch.Tensor:
    """Colour ``(..., 3)`` uint8 / uint16 / float as a float64 tensor in [0, 1]."""
    return torch.from_numpy(bestofn.colour_units(rgb) / bestofn.UNIT)


def _per_view(x: Any) -> list[float]:
    """A metric's values over views ``(V,)`` (tensor or array) as a list of floats."""
    return np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64).reshape(-1).tolist()


def match_view_psnr(rgb: np.ndarray, truth: Truth, g: int) -> list[float]:
    """PSNR on each evaluated view of a candidate's colour ``rgb (V, H, W, 3)`` against ground
    truth g: the values whose mean the candidate pass computed (for integer colours the same exact
    squared errors, :mod:`bestofn`); NaN where a view's mask is empty."""
    sse = np.empty(truth.num_views)
    for v in range(truth.num_views):
        m = truth.mask[v, g]
        d = (bestofn.colour_units(rgb[v]).reshape(-1, 3) - bestofn.colour_units(truth.masked_rgb[v, g]).reshape(-1, 3))[m]
        sse[v] = np.einsum("pc,pc->", d, d)
    count = truth.mask[:, g].sum(-1, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mse = sse / (bestofn.UNIT**2 * 3 * count)
    return M.psnr_from_mse(torch.from_numpy(mse)).numpy().tolist()


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
    as float64 in [0, 1], when already converted. ``per_view``: each metric's value on every view
    (NaN where a view's mask is empty), whose means the other keys are.
    """
    pred = (_to_unit(cand.rgb) if pred is None else pred).float()
    ref, m = M.from_rgb8(rgb), torch.from_numpy(mask)
    per_view: dict[str, list[float]] = {"ssim": _per_view(M.ssim(pred, ref, m))}
    out: dict[str, Any] = {"ssim": _nanmean(per_view["ssim"])}
    if num_objects:  # float32 as SSIM's inputs: no float64 copy of the ground truth (large test sets)
        sse, px = M.squared_error_by_id(pred, ref, ids, num_objects, m)
        out["object_sse"], out["object_pixels"] = sse.tolist(), px.astype(np.int64).tolist()
    if with_lpips:
        pf, gf = lpips_features if lpips_features is not None else (None, None)
        per_view["lpips"] = _per_view(M.lpips(pred, ref, m, pred_features=pf, gt_features=gf))
    if cand.depth is not None:
        per_view["ssimae"] = _per_view(M.ssimae(torch.from_numpy(np.asarray(cand.depth, np.float64)),
                                                torch.from_numpy(depth.astype(np.float64)), m))
    if cand.ids is not None:
        seg = [M.segmentation_scores(cand.ids[v], ids[v], mask[v]) for v in range(len(mask))]
        per_view["pq"], per_view["miou"] = [100.0 * s.pq for s in seg], [100.0 * s.miou for s in seg]
        out["pq"], out["miou"] = 100.0 * _nanmean([s.pq for s in seg]), 100.0 * _nanmean([s.miou for s in seg])
    out.update({k: _nanmean(v) for k, v in per_view.items() if k not in out})
    return {**out, "per_view": per_view}


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

    Every candidate is checked while it is scored: its colour whole, its depth and ids files up to
    their headers (``load_rgb``, where the source has it); the full metrics are computed for the
    matched candidates only, each loaded once more and checked whole. A malformed candidate raises
    :class:`predictions.PredictionError` before anything is returned. With renders of the training
    video, also the fidelity check and best of N over the faithful candidates (:func:`guarded`).
    ``workers`` > 1: the candidates are read, and the matched ones' metrics computed, in that many
    processes (the same result).
    """
    if with_lpips:
        M.get_model()  # fail on missing LPIPS weights before the long pass, not after it
    timings = {}
    t0 = time.perf_counter()
    matrix = bestofn.psnr_matrix(truth, source, workers, progress)
    best = bestofn.match(matrix)
    timings["candidate_pass_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rows = matched_rows(truth, source, best, with_lpips, progress, workers=workers)
    timings["metrics_s"] = time.perf_counter() - t0
    keys = metric_keys(source, with_lpips)
    t0 = time.perf_counter()
    fidelity = guarded(truth, source, matrix, rows, keys, with_lpips, workers, progress)
    timings["fidelity_s"] = time.perf_counter() - t0
    info = {
        "num_candidates": len(source.names), "num_ground_truths": truth.num_configurations,
        "num_views": truth.num_views, "views": [f.name for f in truth.frames],
        "covisible_fraction": float(truth.mask.mean()), "metrics": keys, "workers": workers,
        "distinct_matches": int(len(np.unique(best.indices))),
        "covisibility_masks": "computed" if truth.masks_note else "stored", "covisibility_note": truth.masks_note,
    }
    by_object = error_by_object(rows, [o.name for o in sorted(truth.scene.objects, key=lambda o: o.id)])
    ok = np.asarray(fidelity["faithful"], bool) if fidelity["checked"] else None
    return ScoreResult(list(source.names), matrix, rows, summarise(rows, keys), bestofn.curves(matrix), timings, info, by_object,
                       fidelity=fidelity, coverage=COV.curves(matrix, ok))


def guarded(truth: Truth, source: CandidateSource, matrix: np.ndarray, rows: list[dict[str, Any]], keys: list[str],
            with_lpips: bool, workers: int = 1, progress: bool = False) -> dict[str, Any]:
    """:func:`fidelity.check` of ``source`` and, when some candidate is faithful, best of N over the
    faithful ones: ``summary`` and ``per_ground_truth`` (the full metrics of those matches; a match
    that is also the unguarded one reuses its row of ``rows``)."""
    fid = F.check(truth.root, truth.scene, source, workers, progress)
    if not fid["checked"] or not fid["num_faithful"]:
        return {**fid, "summary": None, "per_ground_truth": []} if fid["checked"] else fid
    best = F.guarded_match(matrix, np.asarray(fid["faithful"], bool))
    same = {r["configuration"]: r for r in rows if best.indices[r["configuration"]] == r["match_index"]}
    todo = [g for g in range(len(best.indices)) if g not in same]
    new = matched_rows(truth, source, best, with_lpips, progress, todo, workers) if todo else []
    grows = sorted([*same.values(), *new], key=lambda r: r["configuration"])
    return {**fid, "summary": summarise(grows, keys), "per_ground_truth": F.trim_rows(grows),
            "distinct_matches": int(len(np.unique(best.indices)))}


#: Compute the matched candidates' metrics in the ``--workers`` processes (torch on one thread in
#: each); False: all in this process (``benchmarks/bench_score_protocol.py`` times both). The same rows.
METRICS_IN_WORKERS = True

# Set before forking workers (:func:`parallel.ordered_map`), so that they inherit it unpickled.
_JOB: dict[str, Any] = {}


def matched_rows(truth: Truth, source: CandidateSource, best: M.BestOfN, with_lpips: bool, progress: bool = False,
                 configurations: list[int] | None = None, workers: int = 1) -> list[dict[str, Any]]:
    """Full metrics of each ground truth's match ``best.indices[g]`` (PSNR ``best.scores[g]``), for
    ``configurations`` (default: all), sorted by configuration; each matched candidate loaded once
    (and checked whole: :meth:`predictions.PredictionDir.load`), each ground truth's views read once.
    ``workers`` > 1 computes them in that many processes, one matched candidate per task."""
    from tqdm import tqdm

    gs = np.arange(len(best.indices)) if configurations is None else np.asarray(configurations, dtype=np.int64)
    tasks = [(int(n), [int(g) for g in gs[best.indices[gs] == n]]) for n in np.unique(best.indices[gs])]
    parallel = workers > 1 and METRICS_IN_WORKERS and getattr(source, "fork_safe", True)
    _JOB.update(truth=truth, source=source, best=best, with_lpips=with_lpips, parent=os.getpid())
    rows: list[dict[str, Any]] = []
    try:
        with tqdm(total=len(gs), desc="matched metrics", unit="gt", disable=not progress, dynamic_ncols=True) as bar:
            for new in ordered_map(_candidate_rows, tasks, workers if parallel else 1):
                rows += new
                bar.update(len(new))
    finally:
        _JOB.clear()
    rows.sort(key=lambda r: r["configuration"])
    return rows


def _candidate_rows(n: int, gs: list[int]) -> list[dict[str, Any]]:
    """:func:`matched_rows`' rows of candidate n, matched to ground truths ``gs``. In a worker
    process torch runs on one thread (the workers share the cores; torch in a forked process must
    not start a thread pool)."""
    if os.getpid() != _JOB["parent"]:
        torch.set_num_threads(1)
    truth, source, best, with_lpips = _JOB["truth"], _JOB["source"], _JOB["best"], _JOB["with_lpips"]
    cand = source.load(n)
    pred = _to_unit(cand.rgb)
    # LPIPS's network runs once per image set: the candidate's here, each ground truth's kept by
    # `truth` across candidate sets when it runs in this process (the distances are the same,
    # feature for feature).
    pred_features = M.lpips_features(pred.float()) if with_lpips else None
    rows = []
    for g in gs:
        rgb, depth, ids = truth.views(g)
        row = {"configuration": g, "match": source.names[n], "match_index": n, "psnr": float(best.scores[g])}
        feats = (pred_features, truth.lpips_features(g, rgb)) if with_lpips else None
        full = match_metrics(cand, rgb, depth, ids, truth.masks(g), with_lpips, feats, truth.scene.num_objects, pred)
        full["per_view"] = {"psnr": match_view_psnr(cand.rgb, truth, g), **full["per_view"]}
        rows.append({**row, **full})
    return rows

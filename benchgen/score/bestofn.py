"""Exact best-of-N matching by streaming: each candidate is read once and scored against all G truths.

The PSNR of candidate n against view v of ground truth g needs the masked squared error
``sum_p m (x - y)^2 = sum_p m x^2 - 2 sum_p x (m y) + sum_p m y^2``: for a chunk of B candidates
and one view, two matrix products ``(B, P) @ (P, G)`` and ``(B, 3P) @ (3P, G)`` give all B x G
errors at once. Colours are integers (16-bit units; an 8-bit ground truth is ``257 y``), so in
float64 every product and sum is an exact integer while it stays below 2^53, i.e. for images up to
~700k pixels: the errors are exact, whatever the BLAS, the chunking or the number of workers.
Float candidates (in-memory renders) are scaled to the same units and are accurate to float64.

Memory holds the ground truth, one chunk of candidates per worker and the ``(N, G)`` mean-PSNR
matrix; it does not grow with N beyond that matrix.
"""

from __future__ import annotations

import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Iterator, Sequence

import numpy as np

from benchgen.score import metrics as M
from benchgen.score.predictions import CandidateSource
from benchgen.score.truth import Truth

#: Colour unit of the exact error: full-scale 16-bit. 8-bit values v are ``257 v`` (65535 / 255).
UNIT = 65535.0
_FROM_8BIT = 257.0
#: Candidate colour (bytes, stored as loaded) per chunk: bounds a worker's memory.
CHUNK_BYTES = 256 * 2**20
MAX_CHUNK = 64


def colour_units(rgb: np.ndarray) -> np.ndarray:
    """``rgb`` ``(..., 3)`` (uint8, uint16 or float in [0, 1]) as float64 in 16-bit units."""
    if rgb.dtype == np.uint8:
        return rgb.astype(np.float64) * _FROM_8BIT
    if rgb.dtype == np.uint16:
        return rgb.astype(np.float64)
    return rgb.astype(np.float64) * UNIT


def chunk_size(num_candidates: int, truth: Truth) -> int:
    """Candidates per chunk: within ``CHUNK_BYTES`` and at most N / 8 (so several workers share
    even a small N). Depends on N and the image size only, never on the number of workers."""
    per_candidate = truth.num_views * truth.scene.height * truth.scene.width * 3
    return max(1, min(MAX_CHUNK, CHUNK_BYTES // per_candidate, math.ceil(num_candidates / 8)))


def view_psnr(rgbs: Sequence[np.ndarray], truth: Truth) -> np.ndarray:
    """PSNR ``(B, G, V)`` of B candidates, each ``(V, H, W, 3)`` of any colour dtype, against every truth view.

    NaN where a view's mask is empty (nothing to compare), as :func:`metrics.psnr`.
    """
    B, V, G = len(rgbs), truth.num_views, truth.num_configurations
    sse = np.empty((B, G, V))
    count = np.empty((G, V))
    for v in range(V):
        x = np.stack([colour_units(c[v]).reshape(-1) for c in rgbs])  # (B, 3P), 16-bit units
        m = truth.mask[v].astype(np.float64)  # (G, P)
        y = truth.masked_rgb[v].astype(np.float64)  # (G, 3P), 8-bit units, zero where masked out
        x2 = (x * x).reshape(B, -1, 3).sum(-1)  # (B, P)
        y2 = (y * y).sum(1)  # (G,)
        sse[:, :, v] = x2 @ m.T - (2 * _FROM_8BIT) * (x @ y.T) + _FROM_8BIT**2 * y2
        count[:, v] = m.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mse = np.maximum(sse, 0.0) / (UNIT**2 * 3 * count)  # 0 / 0 = NaN for an empty mask
    return M.psnr_from_mse(mse)


# Set in the parent before forking workers, so that they inherit it instead of unpickling it.
_JOB: dict[str, Any] = {}


def _score_chunk(start: int, stop: int) -> np.ndarray:
    """PSNR ``(B, G, V)`` of candidates ``start..stop-1`` (each read, checked and dropped)."""
    source: CandidateSource = _JOB["source"]
    return view_psnr([source.load(n).rgb for n in range(start, stop)], _JOB["truth"])


def _chunks(n: int, size: int) -> list[tuple[int, int]]:
    return [(i, min(i + size, n)) for i in range(0, n, size)]


def _run_chunks(chunks: list[tuple[int, int]], workers: int) -> Iterator[np.ndarray]:
    """Results of :func:`_score_chunk` in chunk order (a worker's error is raised in that order)."""
    if workers <= 1:
        yield from (_score_chunk(a, b) for a, b in chunks)
        return
    # Workers run numpy only (torch's OpenMP pool is not fork-safe; numpy's BLAS is).
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
        futures = [pool.submit(_score_chunk, a, b) for a, b in chunks]
        try:
            for f in futures:
                yield f.result()
        finally:
            for f in futures:
                f.cancel()


def psnr_matrix(truth: Truth, source: CandidateSource, workers: int = 1, progress: bool = False) -> np.ndarray:
    """Mean PSNR ``(N, G)`` over the evaluated views of every candidate against every truth.

    Candidates are streamed in chunks (:func:`chunk_size`), each read once; ``workers`` > 1 reads
    and scores chunks in that many processes with an identical result. A view with an empty mask
    is left out of a mean (:func:`metrics.best_of_n`'s convention).
    """
    from tqdm import tqdm

    N = len(source.names)
    out = np.empty((N, truth.num_configurations))
    chunks = _chunks(N, chunk_size(N, truth))
    _JOB.update(truth=truth, source=source)
    try:
        with tqdm(total=N, desc="candidates", unit="cand", disable=not progress, dynamic_ncols=True) as bar:
            for (a, b), table in zip(chunks, _run_chunks(chunks, workers)):
                out[a:b] = M.best_of_n(table).mean_scores
                bar.update(b - a)
    finally:
        _JOB.clear()
    return out


def match(matrix: np.ndarray) -> M.BestOfN:
    """Per ground truth the candidate with the best mean PSNR of ``matrix (N, G)`` (ties: lowest index)."""
    return M.best_of_n(matrix[:, :, None])


def curves(matrix: np.ndarray, max_points: int = 200) -> dict[str, Any]:
    """Best PSNR against N and against the number of ground truths, from the exact ``(N, G)`` matrix.

    ``best_psnr_vs_n``: mean over ground truths of the best of the first n candidates (directory
    order), at up to ``max_points`` log-spaced n including N. ``psnr_vs_num_ground_truths``: mean
    over candidates of each one's best match among the first m ground truths (the paper's
    appendix: how well samples are explained as more ground truths are known).
    ``sorted_best_psnr``: every ground truth's best PSNR, ascending.
    """
    N, G = matrix.shape
    filled = np.where(np.isnan(matrix), -np.inf, matrix)
    best = np.maximum.accumulate(filled, axis=0)  # (N, G): best of the first n + 1
    ns = np.unique(np.geomspace(1, N, min(N, max_points)).round().astype(int))
    by_gt = np.maximum.accumulate(filled, axis=1)  # (N, G): each candidate's best of the first m + 1
    return {
        "best_psnr_vs_n": {"n": ns.tolist(), "psnr": [_finite_mean(best[n - 1]) for n in ns]},
        "psnr_vs_num_ground_truths": {"num_gt": list(range(1, G + 1)), "psnr": [_finite_mean(by_gt[:, m]) for m in range(G)]},
        "sorted_best_psnr": np.sort(np.where(np.isfinite(best[-1]), best[-1], np.nan)).tolist(),
    }


def _finite_mean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")

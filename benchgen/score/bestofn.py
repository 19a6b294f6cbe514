"""Exact best-of-N matching by streaming: each candidate is read once and scored against all G truths.

The PSNR of candidate n against view v of ground truth g needs the masked squared error
``sum_p m (x - y)^2 = sum_p m x^2 - 2 sum_p x (m y) + sum_p m y^2``: for a chunk of B candidates
and one view, two matrix products ``(B, P) @ (P, G)`` and ``(B, 3P) @ (3P, G)`` give all B x G
errors at once. Colours are integers (16-bit units; an 8-bit ground truth is ``257 y``), so in
float64 every product and sum is an exact integer while it stays below 2^53, i.e. for images up to
~700k pixels: the errors are exact, whatever the BLAS, the chunking or the number of workers.
Float candidates (in-memory renders) are scaled to the same units and are accurate to float64.

Each worker reads, checks and scores whole chunks (reading is the slow part: decoding each view's
colour; depth and ids are checked up to their headers, and decoded only for matched candidates)
and returns only the chunk's ``(B, G)`` means: the colours never cross a process boundary, and no
process waits on another's share. Memory holds the ground truth (shared by the forked workers),
one chunk per worker and the ``(N, G)`` mean-PSNR matrix; it does not grow with N beyond that matrix.
"""

from __future__ import annotations

import math
import os
from typing import Any, Sequence

import numpy as np
import torch

from benchgen.score import metrics as M
from benchgen.score.parallel import ordered_map
from benchgen.score.predictions import CandidateSource
from benchgen.score.truth import Truth

#: Colour unit of the exact error: full-scale 16-bit. 8-bit values v are ``257 v`` (65535 / 255).
UNIT = 65535.0
_FROM_8BIT = 257.0
#: Candidate colour (bytes, as 8-bit) per chunk: bounds the memory each worker holds. Larger
#: chunks spread each view's conversion of the ground truth to float over more candidates.
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


def truth_energy(truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    """Per view and ground truth: ``sum_p m y^2`` (8-bit units) and the mask's pixel count, ``(V, G)`` each."""
    y2 = np.stack([np.einsum("gp,gp->g", y, y, dtype=np.float64) for y in truth.masked_rgb])
    return y2, truth.mask.sum(-1, dtype=np.float64)


def view_psnr(rgbs: Sequence[np.ndarray], truth: Truth, energy: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """PSNR ``(B, G, V)`` of B candidates, each ``(V, H, W, 3)`` of any colour dtype, against every truth view.

    ``energy``: :func:`truth_energy` (computed when not given). NaN where a view's mask is empty
    (nothing to compare), as :func:`metrics.psnr`.
    """
    y2, count = truth_energy(truth) if energy is None else energy
    B, V = len(rgbs), truth.num_views
    sse = torch.empty(B, truth.num_configurations, V, dtype=torch.float64)
    eight_bit = EXACT_FLOAT32 and all(c.dtype == np.uint8 for c in rgbs)
    for v in range(V):
        if eight_bit:
            sse[:, :, v] = _sse_8bit(np.stack([c[v].reshape(-1) for c in rgbs]), truth.masked_rgb[v], truth.mask[v], y2[v])
            continue
        x = torch.from_numpy(np.stack([colour_units(c[v]).reshape(-1) for c in rgbs]))  # (B, 3P), 16-bit units
        m = torch.from_numpy(truth.mask[v]).double()  # (G, P)
        y = torch.from_numpy(truth.masked_rgb[v]).double()  # (G, 3P), 8-bit units, zero where masked out
        sq = x.square().reshape(B, -1, 3)
        x2 = sq[..., 0] + sq[..., 1] + sq[..., 2]  # (B, P); faster than a strided sum(-1)
        sse[:, :, v] = x2 @ m.T - (2 * _FROM_8BIT) * (x @ y.T) + _FROM_8BIT**2 * torch.from_numpy(y2[v])
    mse = sse.clamp_min(0.0) / torch.from_numpy(UNIT**2 * 3 * count.T)  # 0 / 0 = NaN for an empty mask
    return M.psnr_from_mse(mse).numpy()


#: Score 8-bit candidates with :func:`_sse_8bit` (exact float32 blocks, several times faster than
#: float64 products); False: every candidate in float64 (``benchmarks/bench_score_protocol.py``
#: times both). Both give the same errors, bit for bit.
EXACT_FLOAT32 = True
#: Products summed per float32 block: 8-bit x 8-bit products are at most 255^2, and 256 of them
#: stay below 2^24, below which float32 holds every integer.
_PRODUCT_BLOCK = 256
#: Pixels summed per float32 block of the masked squares' halves (each at most 511 per pixel).
_SQUARE_BLOCK = 1 << 15
_SQUARE_SPLIT = 9  # a pixel's x^2 summed over channels (< 2^18) = 2^9 high + low, each < 2^9


def _exact_float32_products(a: torch.Tensor, b: torch.Tensor, block: int) -> torch.Tensor:
    """``a (B, L) @ b (G, L).T`` in float64, from float32 products summed over blocks of ``block``
    columns in float32 and across blocks in float64. Exact when the inputs are non-negative
    integers whose products summed over any ``block`` columns stay below 2^24: every partial sum a
    float32 BLAS forms, in whatever order, is then an integer float32 holds exactly."""
    B, L = a.shape
    n = L // block * block
    out = torch.zeros(B, b.shape[0], dtype=torch.float64)
    if n:
        nb = n // block
        out += torch.bmm(a[:, :n].reshape(B, nb, block).transpose(0, 1),
                         b[:, :n].reshape(-1, nb, block).permute(1, 2, 0)).sum(0, dtype=torch.float64)
    if n < L:
        out += (a[:, n:] @ b[:, n:].T).double()
    return out


def _sse_8bit(x8: np.ndarray, y8: np.ndarray, mask: np.ndarray, y2: np.ndarray) -> torch.Tensor:
    """Masked squared errors ``(B, G)`` in 16-bit units of 8-bit candidates ``x8 (B, 3P)`` against
    one view of every truth: ``y8 (G, 3P)`` uint8 zero where masked out, ``mask (G, P)``, ``y2 (G,)``
    its :func:`truth_energy` (8-bit units).

    An 8-bit value v is 257 v in 16-bit units, so the error is
    ``257^2 (sum m x^2 - 2 sum x y + sum m y^2)`` in 8-bit integers: the cross term from float32
    products in blocks of :data:`_PRODUCT_BLOCK`, the masked squares (a pixel's sum over channels,
    below 2^18) split into two halves below 2^9, each summed in float32 over blocks of
    :data:`_SQUARE_BLOCK` pixels. Every sum is an exact integer, so the result equals the float64
    formula of :func:`view_psnr` exactly.
    """
    B = x8.shape[0]
    x = torch.from_numpy(x8)
    cross = _exact_float32_products(x.float(), torch.from_numpy(y8).float(), _PRODUCT_BLOCK)
    xi = x.int().reshape(B, -1, 3)
    sq = (xi * xi).sum(-1, dtype=torch.int32)  # (B, P)
    halves = torch.cat([sq >> _SQUARE_SPLIT, sq & ((1 << _SQUARE_SPLIT) - 1)]).float()
    h = _exact_float32_products(halves, torch.from_numpy(mask).float(), _SQUARE_BLOCK)
    masked_sq = h[:B] * (1 << _SQUARE_SPLIT) + h[B:]
    return _FROM_8BIT**2 * (masked_sq - 2 * cross + torch.from_numpy(y2))


# Set before forking workers (:func:`parallel.ordered_map`), so that they inherit it unpickled.
_JOB: dict[str, Any] = {}


#: The pass decodes only the candidates' colour, checking their depth and ids files up to their
#: headers (``load_rgb``, where the source has it); False: every file decoded and checked whole
#: (``benchmarks/bench_score_protocol.py`` times both). The PSNR matrix is the same.
COLOUR_ONLY = True


def _read_chunk(start: int, stop: int) -> list[np.ndarray]:
    """Colours of candidates ``start..stop-1``, read and checked (``load_rgb``: depth and ids up to
    their headers; a source without it: each candidate whole, depth and ids dropped).

    Runs in worker processes."""
    source: CandidateSource = _JOB["source"]
    load_rgb = getattr(source, "load_rgb", None) if COLOUR_ONLY else None
    return [load_rgb(n) if load_rgb else source.load(n).rgb for n in range(start, stop)]


#: Score each chunk in the worker that read it (:func:`_score_chunk`); False: workers return the
#: chunk's colours and this process scores them while they read the next ones, as before
#: (``benchmarks/bench_score_protocol.py`` times both). The matrix is the same, bit for bit.
SCORE_IN_WORKERS = True


def _score_chunk(start: int, stop: int) -> np.ndarray:
    """Mean PSNR ``(stop - start, G)`` of candidates ``start..stop-1``, read, checked and scored in
    this process (torch on one thread in a worker: the workers share the cores)."""
    if os.getpid() != _JOB["parent"]:
        torch.set_num_threads(1)
    return M.best_of_n(view_psnr(_read_chunk(start, stop), _JOB["truth"], _JOB["energy"])).mean_scores


def psnr_matrix(truth: Truth, source: CandidateSource, workers: int = 1, progress: bool = False) -> np.ndarray:
    """Mean PSNR ``(N, G)`` over the evaluated views of every candidate against every truth.

    Candidates are streamed in chunks (:func:`chunk_size`), each read once; ``workers`` > 1 reads
    them in that many processes, with an identical result. A view with an empty mask is left out
    of a mean (:func:`metrics.best_of_n`'s convention).
    """
    from tqdm import tqdm

    if workers > 1 and not getattr(source, "fork_safe", True):
        raise ValueError("these candidates cannot be loaded in forked processes: score them with workers=1")
    N, size = len(source.names), chunk_size(len(source.names), truth)
    out = np.empty((N, truth.num_configurations))
    chunks = [(i, min(i + size, N)) for i in range(0, N, size)]
    energy = truth_energy(truth)
    in_workers = SCORE_IN_WORKERS and workers > 1
    _JOB.update(source=source, truth=truth, energy=energy, parent=os.getpid())
    threads = torch.get_num_threads()
    try:
        if not in_workers:
            torch.set_num_threads(pass_threads(workers))
        with tqdm(total=N, desc="candidates", unit="cand", disable=not progress, dynamic_ncols=True) as bar:
            for (a, b), done in zip(chunks, ordered_map(_score_chunk if in_workers else _read_chunk, chunks, workers)):
                out[a:b] = done if in_workers else M.best_of_n(view_psnr(done, truth, energy)).mean_scores
                bar.update(b - a)
    finally:
        _JOB.clear()
        torch.set_num_threads(threads)
    return out


#: Give the pass's products only the cores the reading workers leave (:func:`pass_threads`);
#: False: torch's own thread count, as before (``benchmarks/bench_score_protocol.py`` times both).
THREADS_BESIDE_WORKERS = True


def pass_threads(workers: int) -> int:
    """Torch threads for the products while ``workers`` processes read candidates: the cores they
    leave, at least one: on 2 cores with 2 workers, torch's two threads beside two busy readers
    wait on each other, and the pass took several times as long as with one thread."""
    threads = torch.get_num_threads()
    if workers <= 1 or not THREADS_BESIDE_WORKERS:
        return threads
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(threads, cores - workers))


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

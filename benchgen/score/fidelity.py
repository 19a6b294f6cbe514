"""Fidelity: does a candidate explain the training video? The guard that spraying cannot pass.

Every ground-truth configuration of a dataset reproduces the training video exactly (that is
what makes it a solution: objects scale about each training camera's centre, and the valid
region is where no depth order seen by a training ray changes). A method's valid solutions share
that property: rendered from the training cameras they all show the same video, as well as the
method's fields can render it. A configuration outside the valid region changes which object a
training ray sees first, so its render of some training frame differs from the video. Best of N
alone cannot tell the two apart: configurations sprayed over the whole scale box raise it (each
ground truth picks whichever spray member happens to resemble it on the test views).

A candidate may therefore hold its render of every training frame, ``CAND/train/rgb/NAME.png``
(docs/predictions.md). :func:`check` scores those renders against the training video and applies
the rule of :func:`faithful` (docs/metrics.md, "Fidelity"):

* per training frame t, the reference ``r_t`` is the best PSNR any candidate reaches on that frame
  (the method's own rendering of the video: ground truths would reach ``PSNR_MAX``);
* a candidate is *faithful* when on every training frame it lies within :data:`TOLERANCE_DB` of
  ``r_t`` and above the PSNR of the frame's flat mean colour (a render that explains nothing).

The guarded best of N matches each ground truth among the faithful candidates only
(:func:`guarded_match`). The training renders are read once, in ``workers`` processes, like
the test views (:mod:`benchgen.score.bestofn`); nothing here depends on the number of workers.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from scenecore import dataset as D
from benchgen.score import metrics as M
from benchgen.score.bestofn import UNIT, colour_units
from benchgen.score.parallel import ordered_map
from benchgen.score.predictions import CandidateSource

#: dB a faithful candidate may lie below the best candidate on any training frame: 12% more
#: squared error on that frame. Chosen from the shortfalls measured on the demo
#: (benchmarks/bench_fidelity.py; docs/metrics.md, "Fidelity"): a few times what OSN's samples
#: inside the valid region spread, below what configurations clearly outside it fall short.
TOLERANCE_DB = 0.5
#: Candidates whose training renders are read per task (one task per worker call).
CHUNK = 16

NOT_CHECKED = ("fidelity was not checked: no candidate holds train/rgb/NAME.png (its render of the training "
               "video), so best of N is unguarded and spraying configurations raises it")


def training_frames(scene: D.Scene) -> list[D.Frame]:
    """The training video's frames in time order (the order of :func:`scenecore.dataset.read_training_video`)."""
    return sorted(scene.train_frames, key=lambda f: f.time_index)


def frame_psnr(rgb: np.ndarray, video: np.ndarray) -> np.ndarray:
    """PSNR ``(T,)`` of a candidate's training renders ``rgb (T, H, W, 3)`` (uint8, uint16 or float
    in [0, 1]) against the training video ``video (T, H, W, 3)`` uint8, every pixel. Exact for
    integer colours (16-bit units, as the test-view pass)."""
    d = colour_units(rgb).reshape(len(video), -1) - colour_units(video).reshape(len(video), -1)
    mse = np.einsum("tp,tp->t", d, d) / (d.shape[1] * UNIT**2)
    return M.psnr_from_mse(mse)


def flat_psnr(video: np.ndarray) -> np.ndarray:
    """PSNR ``(T,)`` of each training frame's flat mean colour against the frame: a render that
    explains nothing of the frame's content."""
    flat = np.broadcast_to(video.reshape(len(video), -1, 3).mean(1)[:, None, None, :] / 255.0, video.shape)
    return frame_psnr(np.ascontiguousarray(flat), video)


# Set before forking workers (:func:`parallel.ordered_map`), so that they inherit it unpickled.
_JOB: dict[str, Any] = {}


def _chunk_psnr(start: int, stop: int) -> np.ndarray:
    """Training PSNRs ``(stop - start, T)`` of candidates ``start..stop-1`` (numpy only: runs in workers)."""
    source, video = _JOB["source"], _JOB["video"]
    return np.stack([frame_psnr(source.load_train(n), video) for n in range(start, stop)])


def train_psnr_matrix(source: CandidateSource, video: np.ndarray, workers: int = 1, progress: bool = False) -> np.ndarray:
    """PSNR ``(N, T)`` of every candidate's training renders against the training video."""
    from tqdm import tqdm

    if workers > 1 and not getattr(source, "fork_safe", True):
        workers = 1  # renders made in this process (torch) cannot be loaded in forked ones
    N = len(source.names)
    chunks = [(a, min(a + CHUNK, N)) for a in range(0, N, CHUNK)]
    out = np.empty((N, len(video)))
    _JOB.update(source=source, video=video)
    try:
        with tqdm(total=N, desc="training renders", unit="cand", disable=not progress, dynamic_ncols=True) as bar:
            for (a, b), p in zip(chunks, ordered_map(_chunk_psnr, chunks, workers)):
                out[a:b] = p
                bar.update(b - a)
    finally:
        _JOB.clear()
    return out


def faithful(train_psnr: np.ndarray, flat: np.ndarray, tolerance_db: float = TOLERANCE_DB) -> dict[str, np.ndarray]:
    """The rule: ``train_psnr (N, T)``, ``flat (T,)`` -> ``reference (T,)`` (best candidate per
    frame), ``shortfall (N,)`` (dB below the reference on the candidate's worst frame) and
    ``faithful (N,)`` (shortfall within ``tolerance_db`` and every frame above its flat colour)."""
    reference = train_psnr.max(0)
    shortfall = (reference[None] - train_psnr).max(1)
    ok = (shortfall <= tolerance_db) & (train_psnr > flat[None]).all(1)
    return {"reference": reference, "shortfall": shortfall, "faithful": ok}


def guarded_match(matrix: np.ndarray, ok: np.ndarray) -> M.BestOfN:
    """Per ground truth the faithful candidate (``ok (N,)``) with the best mean PSNR of
    ``matrix (N, G)`` (ties: lowest index); the indices are rows of ``matrix``."""
    rows = np.flatnonzero(ok)
    best = M.best_of_n(matrix[rows][:, :, None])
    return M.BestOfN(rows[best.indices], best.scores, best.mean_scores)


def check(root: str, scene: D.Scene, source: CandidateSource, workers: int = 1, progress: bool = False,
          tolerance_db: float = TOLERANCE_DB) -> dict[str, Any]:
    """Fidelity of ``source``'s candidates against the training video of the dataset at ``root``.

    Returns ``{"checked": False, "note": ...}`` when the candidates hold no training renders,
    else the record ``metrics.json`` holds under ``fidelity`` (docs/predictions.md) and
    ``faithful`` (bool ``(N,)``) for :func:`guarded_match`.
    """
    if not getattr(source, "has_train", False):
        return {"checked": False, "note": NOT_CHECKED}
    frames = training_frames(scene)
    video = D.read_training_video(root, scene)[0]
    p = train_psnr_matrix(source, video, workers, progress)
    flat = flat_psnr(video)
    rule = faithful(p, flat, tolerance_db)
    ok = rule["faithful"]
    return {
        "checked": True, "tolerance_db": tolerance_db, "train_frames": [f.name for f in frames],
        "reference_psnr": rule["reference"].tolist(), "flat_psnr": flat.tolist(),
        "train_psnr": p.mean(1).tolist(), "shortfall_db": rule["shortfall"].tolist(), "faithful": ok.tolist(),
        "num_faithful": int(ok.sum()), "faithful_share": float(ok.mean()),
    }


def summary_cells(record: dict[str, Any]) -> list[str]:
    """``faithful k / N (share)`` and the median training PSNR, for a report line."""
    n = len(record["faithful"])
    return [f"{record['num_faithful']} / {n} ({100 * record['faithful_share']:.1f}%)",
            f"{float(np.median(record['train_psnr'])):.2f}"]


def report_lines(fidelity: dict[str, Any], guarded_table: str | None, structure_table: str) -> list[str]:
    """The report's leading section: the figures that tell a method from a spray."""
    lines = ["## Method or spray?", ""]
    if not fidelity.get("checked"):
        return lines + [f"Note: {fidelity['note']}. The structure metrics of the matches below still tell a method "
                        "from a spray (a sprayed configuration that wins on colour misplaces objects):", "",
                        structure_table, ""]
    faithful_cell, median = summary_cells(fidelity)
    lines += [
        f"Fidelity: {faithful_cell} candidates are faithful: on every one of the {len(fidelity['train_frames'])} "
        f"training frames their render lies within {fidelity['tolerance_db']:g} dB of the best candidate's render of "
        "that frame (and above the frame's flat mean colour); median training PSNR of the candidates "
        f"{median} dB. Guarded best of N matches each ground truth among the faithful candidates only "
        "(docs/metrics.md, \"Fidelity\").", "",
    ]
    if guarded_table is None:
        return lines + ["No candidate is faithful: the guarded best of N does not exist.", ""]
    return lines + [guarded_table, ""]


def trim_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Guarded matches as ``metrics.json`` holds them: the per-view values stay with the unguarded rows."""
    return [{k: v for k, v in r.items() if k != "per_view"} for r in rows]

"""Coverage and precision beside best of N, from the exact ``(N, G)`` PSNR matrix.

A candidate *matches* ground truth g at level x when its mean PSNR over g's evaluated views
(the matrix entry) is at least x dB. Over a grid of levels (:data:`LEVELS`, the same for every
scoring, so that two methods' curves share their x axis):

* **coverage** (x): the share of ground truths that some candidate matches at x, i.e. whose
  best-of-N PSNR is at least x (what best of N averages, as a distribution);
* **precision** (x): the share of candidates that match some ground truth at x. A learned valid
  set spends its candidates near ground truths; configurations sprayed over the scale box do not.

With fidelity checked (:mod:`benchgen.score.fidelity`) the same two curves are given over the
faithful candidates: a ground truth is covered only by a faithful candidate, and precision counts
the candidates that are faithful *and* match (over all N, so unfaithful candidates lower it).
Ground truths whose views are all masked out (a NaN column) are left out of coverage.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

#: PSNR levels (dB) of the curves: fixed, so that curves of different scorings line up.
LEVELS = np.round(np.arange(0.0, 60.0 + 1e-9, 0.25), 2)


def curves(matrix: np.ndarray, faithful: np.ndarray | None = None, levels: np.ndarray = LEVELS) -> dict[str, Any]:
    """``levels`` and, per level, ``ground_truths`` (coverage) and ``candidates`` (precision);
    with ``faithful (N,)`` bool also ``ground_truths_faithful`` and ``candidates_faithful``."""
    filled = np.where(np.isnan(matrix), -np.inf, matrix)
    gts = ~np.isnan(matrix).all(0)  # ground truths with something to compare
    best_gt = filled[:, gts].max(0)  # (G',)
    best_cand = filled[:, gts].max(1) if gts.any() else np.full(len(matrix), -np.inf)  # (N,)
    lv = np.asarray(levels, dtype=np.float64)[:, None]
    out: dict[str, Any] = {
        "levels": [float(x) for x in levels],
        "ground_truths": (best_gt[None] >= lv).mean(1).tolist() if gts.any() else [float("nan")] * len(levels),
        "candidates": (best_cand[None] >= lv).mean(1).tolist(),
    }
    if faithful is not None:
        ok = np.asarray(faithful, bool)
        best_gt_ok = filled[ok][:, gts].max(0) if ok.any() else np.full(int(gts.sum()), -np.inf)
        out["ground_truths_faithful"] = (best_gt_ok[None] >= lv).mean(1).tolist() if gts.any() else out["ground_truths"]
        out["candidates_faithful"] = ((best_cand[None] >= lv) & ok[None]).mean(1).tolist()
    return out


def at(cov: dict[str, Any], level: float, key: str) -> float:
    """The curve ``key`` at the grid level nearest ``level``."""
    i = int(np.argmin(np.abs(np.asarray(cov["levels"]) - level)))
    return float(cov[key][i])


def report_levels(best_mean: float) -> list[float]:
    """Five grid levels, 1 dB apart, around a mean best-of-N PSNR (the report's table)."""
    if not np.isfinite(best_mean):
        return []
    c = float(np.clip(np.floor(best_mean), 2.0, LEVELS[-1] - 2.0))
    return [c - 2, c - 1, c, c + 1, c + 2]


def table(cov: dict[str, Any], levels: list[float]) -> str:
    """Markdown: coverage and precision (and their faithful variants) at ``levels``."""
    keys = [("ground_truths", "coverage"), ("candidates", "precision")]
    if "ground_truths_faithful" in cov:
        keys += [("ground_truths_faithful", "coverage, faithful"), ("candidates_faithful", "precision, faithful")]
    lines = ["| PSNR level (dB) | " + " | ".join(h for _, h in keys) + " |", "|---|" + "---|" * len(keys)]
    for x in levels:
        lines.append(f"| ≥ {x:g} | " + " | ".join(f"{100 * at(cov, x, k):.0f}%" for k, _ in keys) + " |")
    return "\n".join(lines)


def plot(cov: dict[str, Any], path: Path, save: Any) -> None:
    """``coverage.png``: coverage and precision against the level, over the levels where they change.
    ``save(fig, path)`` writes the figure (the report's atomic PNG writer)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(cov["levels"])
    curves_ = [(k, label, style) for k, label, style in (
        ("ground_truths", "coverage: ground truths matched", "-"), ("candidates", "precision: candidates matching", "-"),
        ("ground_truths_faithful", "coverage, faithful candidates", "--"),
        ("candidates_faithful", "precision, faithful candidates", "--")) if k in cov]
    ys = np.array([np.asarray(cov[k], dtype=np.float64) for k, _, _ in curves_])
    moving = np.flatnonzero((ys != ys[:, :1]).any(0))  # levels where some curve has left its first value
    lo = x[max(int(moving[0]) - 4, 0)] if moving.size else x[0]
    hi = x[min(int(np.flatnonzero(np.nanmax(ys, 0) > 0)[-1]) + 4, len(x) - 1)] if (np.nanmax(ys, 0) > 0).any() else x[-1]
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for (k, label, style), y in zip(curves_, ys):
        ax.plot(x, y, style, label=label)
    ax.set(xlim=(lo, max(hi, lo + 1)), ylim=(-0.02, 1.02), xlabel="PSNR level x (dB)", ylabel="share",
           title="coverage and precision at level x")
    ax.legend(fontsize=7)
    save(fig, path)
    plt.close(fig)

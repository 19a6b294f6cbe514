"""The output of ``benchgen score``: ``metrics.json``, ``report.md``, PNG plots, ``psnr_matrix.npy``.

They are written only after the whole scoring succeeded, together: into a temporary directory
that then replaces the report directory whole (``scenecore.atomic.own_dir``), so a kill never
leaves a new matrix beside an old report. A marker file (:data:`MARKER`) tells a report
directory of ours, which is replaced, from a directory of the user's, which is refused.
"""

from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from scenecore import dataset as D
from scenecore.atomic import check_own_dir, own_dir, unmarked_report
from benchgen.score import coverage as COV
from benchgen.score import fidelity as F
from benchgen.score import provenance as P
from benchgen.score.digests import DATASET_LISTING, PREDICTIONS_LISTING
from benchgen.score.scorer import METRICS, ScoreResult

FORMAT = "benchgen-score"
VERSION = 1

#: The file that marks a report directory written by ``benchgen score`` (replaced by the next one).
MARKER = ".benchgen-score"
_WHAT = "a benchgen score report"
_FILES = ("report.md", "metrics.json", "psnr_matrix.npy", "best_of_n.png", "per_ground_truth.png", "coverage.png",
          PREDICTIONS_LISTING, DATASET_LISTING)


def _unmarked(out: Path) -> bool:
    """A report directory of ours written before the marker existed."""
    return unmarked_report(out, _FILES, "metrics.json", lambda m: isinstance(m, dict) and m.get("format") == FORMAT)


def check_out_dir(out: str | Path) -> None:
    """Refuse (``FileExistsError``, one line) an ``--out`` holding files ``benchgen score`` did not
    write, before any scoring: :func:`write_report` checks again when it writes."""
    check_own_dir(out, MARKER, _WHAT, _unmarked)


def _json_safe(x: Any) -> Any:
    """NaN and infinities become null (JSON has neither); numpy scalars become Python numbers."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def metrics_json(res: ScoreResult, method: dict[str, Any], command: str, dataset: str, predictions: str) -> dict[str, Any]:
    """The content of ``metrics.json`` (docs/predictions.md lists the fields)."""
    return _json_safe({
        "format": FORMAT, "version": VERSION, "command": command, "method": method,
        "dataset": dataset, "predictions": predictions, **res.info,
        "summary": res.summary, "per_ground_truth": res.per_ground_truth, "curves": res.curves,
        "timings": res.timings, "candidates": res.names, "error_by_object": res.by_object,
        "fidelity": res.fidelity, "coverage": res.coverage,
    })


def results_table(summary: dict[str, dict[str, float]], label: str) -> str:
    """One-row markdown table: mean ± std over ground truths of every reported metric."""
    cols = [m for m in METRICS if m[0] in summary]
    cell = [f"{f.format(summary[k]['mean'])} ± {f.format(summary[k]['std'])}" for k, _, f in cols]
    return "\n".join([f"| method | {' | '.join(c[1] for c in cols)} |", "|---|" + "---|" * len(cols), f"| {label} | {' | '.join(cell)} |"])


def by_object_table(by_method: dict[str, dict[str, Any]]) -> str:
    """Markdown table of :func:`scorer.error_by_object` for one or more candidate sets scored on the
    same ground truths: one row per ground-truth object with its share of the evaluated pixels,
    then per set the PSNR on that object's pixels and, in brackets, its share of the squared error."""
    first = next(iter(by_method.values()))
    lines = ["| object | share of pixels | " + " | ".join(f"{name}: PSNR (share of error)" for name in by_method) + " |",
             "|---|---|" + "---|" * len(by_method)]
    for k, obj in enumerate(first["objects"]):
        cells = [f"{b['psnr'][k]:.2f} ({100 * b['error_share'][k]:.1f}%)" for b in by_method.values()]
        lines.append(f"| {obj} | {100 * first['pixel_share'][k]:.1f}% | " + " | ".join(cells) + " |")
    return "\n".join(lines)


BY_OBJECT_NOTE = ("Where the error is, by the ground truth's objects (matched candidates, every ground truth's "
                  "co-visible pixels pooled; `scorer.error_by_object`):")


def _save_fig(fig: Any, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    D.atomic_write_bytes(path, buf.getvalue())


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_best_of_n(curves: dict[str, Any], path: Path) -> None:
    """Two panels from :func:`bestofn.curves`: best PSNR against the number of candidates n, and
    each candidate's best PSNR against the number of ground truths m."""
    plt = _pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.5))
    axs[0].semilogx(curves["best_psnr_vs_n"]["n"], curves["best_psnr_vs_n"]["psnr"], ".-")
    axs[0].set(xlabel="first n candidates (directory order)", ylabel="best PSNR, mean over ground truths (dB)", title="best of n")
    axs[1].plot(curves["psnr_vs_num_ground_truths"]["num_gt"], curves["psnr_vs_num_ground_truths"]["psnr"], ".-")
    axs[1].set(xlabel="first m ground truths", ylabel="each candidate's best PSNR, mean (dB)",
               title="candidates against more ground truths")
    _save_fig(fig, path)
    plt.close(fig)


def plot_per_ground_truth(sorted_best: list[float], num_candidates: int, path: Path) -> None:
    """Every ground truth's best PSNR, sorted: how evenly the candidates cover the ground truths."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(1, len(sorted_best) + 1), sorted_best, ".-")
    ax.set(xlabel="ground truth (sorted)", ylabel=f"PSNR of its best of {num_candidates} (dB)", title="per ground truth")
    _save_fig(fig, path)
    plt.close(fig)


def write_plots(res: ScoreResult, out: Path) -> list[str]:
    """``best_of_n.png`` and ``per_ground_truth.png`` in ``out``; returns the file names."""
    plot_best_of_n(res.curves, out / "best_of_n.png")
    plot_per_ground_truth(res.curves["sorted_best_psnr"], len(res.names), out / "per_ground_truth.png")
    if not res.coverage:
        return ["best_of_n.png", "per_ground_truth.png"]
    COV.plot(res.coverage, out / "coverage.png", _save_fig)
    return ["best_of_n.png", "per_ground_truth.png", "coverage.png"]


#: The structure metrics: a sprayed configuration that wins on colour misplaces objects.
STRUCTURE = ("ssimae", "pq", "miou")


def lead_lines(res: ScoreResult, name: str) -> list[str]:
    """The report's first section: what tells a method from a spray (the guarded best of N, the
    structure metrics, coverage and precision), before the unguarded table."""
    fid = res.fidelity or {"checked": False, "note": F.NOT_CHECKED}
    structure = {k: v for k, v in res.summary.items() if k in STRUCTURE}
    guarded = None
    if fid.get("checked") and fid.get("summary"):
        guarded = results_table(fid["summary"], f"{name}: best of {fid['num_faithful']} faithful")
    lines = F.report_lines(fid, guarded, results_table(structure, f"{name}: best of {len(res.names)}") if structure else
                           "(no depth or ids: SSIMAE, PQ and mIoU need them)")
    if res.coverage:
        levels = COV.report_levels(res.summary.get("psnr", {}).get("mean", float("nan")))
        lines += ["Coverage: the share of ground truths some candidate matches with a mean PSNR at or above the level; "
                  "precision: the share of candidates matching some ground truth at that level (`coverage.png`, "
                  "`metrics.json` `coverage`; docs/metrics.md):", "", COV.table(res.coverage, levels), ""]
    return lines + ["## Best of N over all candidates (unguarded)", ""]


def report_markdown(res: ScoreResult, method: dict[str, Any], command: str, plots: list[str]) -> str:
    """``report.md``: the results table, what was scored, timings, plots and the per-ground-truth matches."""
    i, t = res.info, res.timings
    name = str(method.get("name", "candidates"))
    label = f"{name}: best of {i['num_candidates']}"
    keys = [m for m in METRICS if m[0] in res.summary]
    lines = ["# Benchmark score", "", f"Command: `{command}`", "", *P.banner_lines(i.get("provenance"))]
    if method.get("notes"):
        lines += [f"Method notes: {method['notes']}", ""]
    lines += [
        f"{i['num_candidates']} candidates against {i['num_ground_truths']} ground-truth configurations on "
        f"{i['num_views']} test views each; {100 * i['covisible_fraction']:.1f}% of test pixels are co-visible with "
        "the training video (the rest are masked out). Each ground truth is matched to the candidate with the best "
        f"mean PSNR over its views ({i['distinct_matches']} distinct candidates matched); metrics are mean ± std "
        "over the ground truths.", "",
        *([f"Note: {i['covisibility_note']}.", ""] if i.get("covisibility_note") else []),
        *lead_lines(res, name),
        results_table(res.summary, label), "",
        *([BY_OBJECT_NOTE, "", by_object_table({label: res.by_object}), ""] if res.by_object else []),
        "| time | seconds |", "|---|---|",
        *[f"| {k.removesuffix('_s').replace('_', ' ')} | {v:.1f} |" for k, v in t.items()], "",
        *[f"![{p}]({p})" for p in plots], "",
        "| ground truth | match | " + " | ".join(h for _, h, _ in keys) + " |",
        "|---|---|" + "---|" * len(keys),
    ]
    for r in res.per_ground_truth:
        lines.append(f"| {r['configuration']:03d} | {r['match']} | " + " | ".join(f.format(r[k]) for k, _, f in keys) + " |")
    lines += ["", "`metrics.json` holds every number here (and every view's value in `per_ground_truth[].per_view`); "
              "`psnr_matrix.npy` the mean PSNR of every candidate (rows, in the order of `candidates`) against every "
              "ground truth (columns).", "", *P.report_lines(i.get("provenance"))]
    return "\n".join(lines) + "\n"


def write_report(res: ScoreResult, out_dir: str | Path, method: dict[str, Any], command: str, dataset: str, predictions: str) -> Path:
    """Write every output to ``out_dir`` (created, or a previous report replaced); returns the path
    of ``report.md``. Raises ``FileExistsError`` when ``out_dir`` holds files of another origin.

    Adds ``report_s`` and ``total_s`` (the sum of every stage) to ``res.timings``.
    """
    t0 = time.perf_counter()
    with own_dir(out_dir, MARKER, _WHAT, _unmarked) as out:
        buf = io.BytesIO()
        np.save(buf, res.matrix)
        D.atomic_write_bytes(out / "psnr_matrix.npy", buf.getvalue())
        for name, data in res.files.items():  # the per-file digests (provenance)
            D.atomic_write_bytes(out / name, data)
        plots = write_plots(res, out)
        res.timings["report_s"] = time.perf_counter() - t0
        res.timings["total_s"] = sum(v for k, v in res.timings.items() if k != "total_s")
        D.atomic_write_bytes(out / "report.md", report_markdown(res, method, command, plots).encode())
        D.atomic_write_json(out / "metrics.json", metrics_json(res, method, command, dataset, predictions))
    return Path(out_dir) / "report.md"

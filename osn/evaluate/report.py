"""The evaluation report: ``report.md`` with tables, PNG plots beside it, and ``metrics.json``.

Error is always put next to time: the training curve (PSNR and valid-set IoU against wall
time, from ``metrics.jsonl``) and the search time against N are first-class plots.

The files change together: they are written into a temporary directory that replaces the report
directory whole, and only a directory holding :data:`MARKER` (ours) is replaced.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import io
import numpy as np

from scenecore.atomic import check_own_dir, own_dir, unmarked_report
from scenecore.dataset import atomic_write_bytes, atomic_write_json, read_json
from osn.train.environment import describe
from benchgen.score import provenance as P
from benchgen.score.digests import DATASET_LISTING, PREDICTIONS_LISTING
from benchgen.score.report import BY_OBJECT_NOTE, by_object_table
from benchgen.score.scorer import METRICS
from osn.evaluate.bestofn import TRUE_SCALES, EvalResult
from osn.train import read_metrics


def _unposed_lines(e: dict[str, Any]) -> list[str]:
    """A paragraph on objects the run could not place at some test timestamps (none: no lines)."""
    objs = e.get("unposed_objects") or {}
    if not objs:
        return []
    names = "; ".join(f"{n} at t = {', '.join(map(str, ts))}" for n, ts in objs.items())
    return [
        f"Objects without a pose at a test view's timestamp (they left the training view, or were not registered): "
        f"{names}. The run renders nothing for them there: {100 * e['unposed_object_fraction']:.2f}% of the co-visible "
        "test pixels show such an object and count as errors in every figure below.",
        "",
    ]


def _inputs_line(run_dir: Path) -> str:
    """What the run trained on: the oracle is an ablation, SfM is the method as published."""
    try:
        source = read_json(Path(run_dir) / "inputs" / "inputs.json").get("source", "unknown")
    except (OSError, ValueError, AttributeError):
        source = "unknown"
    if source == "oracle":
        return ("Inputs: **oracle** (per-object poses and sparse depths from the ground truth: an ablation that "
                "separates learning errors from SfM errors, not the method as published).")
    if source == "colmap":
        return "Inputs: per-object SfM (pycolmap), as the method is published."
    return f"Inputs: {source}."


def _consistency_lines(run_dir: Path) -> list[str]:
    """A paragraph on the SfM reconstructions the preprocessing check found inconsistent, and what
    was done with each, and on those likely depth-reversed (``meta.consistency`` and
    ``meta.likely_reversed`` of the run's ``inputs.json``), and one on the frames bridged
    (``meta.bridged_frames``); none: no lines."""
    try:
        rec = read_json(Path(run_dir) / "inputs" / "inputs.json")
        meta = rec.get("meta", {})
        checks, reversed_ = meta.get("consistency") or {}, meta.get("likely_reversed") or {}
        bridged = meta.get("bridged_frames") or {}
        names = {str(o.get("id")): o.get("name", "?") for o in rec.get("objects", []) if isinstance(o, dict)}
    except (OSError, ValueError, AttributeError):
        return []
    flagged = [f"- {c.get('action', '?')}: {c['message']}" for c in checks.values()
               if isinstance(c, dict) and c.get("message")]
    flagged += [f"- likely depth-reversed: {m}" for m in reversed_.values() if isinstance(m, str)]
    out = (["SfM reconstructions that contradict the video (checked without ground truth, docs/preprocess.md):",
            "", *flagged, ""] if flagged else [])
    lines = [f"- object {k} ({names.get(k, '?')}): frames {', '.join(map(str, v))}" for k, v in bridged.items()
             if isinstance(v, list) and v]
    if lines:
        out += ["Frames SfM left an object unposed in, posed from its registered neighbours and the anchor's cameras "
                "(each fits the mask as well as the registered poses fit theirs; docs/preprocess.md):", "", *lines, ""]
    return out


def _environment_lines(run_dir: Path) -> list[str]:
    """What the run trained with (``run.json``; none for runs trained before it was recorded)."""
    try:
        rec = read_json(Path(run_dir) / "run.json")
    except (OSError, ValueError):
        return []
    env = rec.get("environment") if isinstance(rec, dict) else None
    if not env:
        return []
    if str(env.get("device", "")).startswith("cuda"):
        line = (f"Trained with {describe(env)}: CUDA's atomic adds make two such trainings agree only up to rounding, "
                "which training carries on (docs/training.md).")
    else:
        line = (f"Trained with {describe(env)}: a training reproduces to the last digit on the same kind of processor "
                "and torch build, and lands elsewhere within the seed spread on another (docs/training.md).")
    if rec.get("resumed_on"):
        line += " Resumed with " + "; ".join(describe(e) for e in rec["resumed_on"]) + "."
    return [line, ""]


def _true_scales_note(e: dict[str, Any]) -> str:
    """What the "true scales" row is, when the evaluation has it."""
    if "true_scales_own_match" not in e:
        return ""
    return (" The \"true scales\" row reads the ground truth: the same fields rendered at every ground truth's "
            "exact scales (best of those G), what best of N approaches as its samples approach the exact "
            "configurations. The gap between the two is the scale search's; the row's own error is the fields' "
            "(best of N can exceed it in PSNR where a wrong configuration hides a field error: SSIMAE, PQ and mIoU "
            f"show the layout). {100 * e['true_scales_own_match']:.0f}% of ground truths match their own scales"
            + ("." if e.get("true_scales_own_margin_db") is None else
               f", {e['true_scales_own_margin_db']:+.2f} dB above the other ground truths' scales on average."))


def _fmt(ms: list[float], f: str) -> str:
    return f"{f.format(ms[0])} ± {f.format(ms[1])}"


def results_table(table: dict[str, dict[str, list[float]]]) -> str:
    """Markdown table: one row per method, mean ± std over the ground truths."""
    cols = [m for m in METRICS if any(m[0] in row for row in table.values())]
    lines = ["| method | " + " | ".join(c[1] for c in cols) + " |", "|---|" + "---|" * len(cols)]
    for name, row in table.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(row[c[0]], c[2]) if c[0] in row else "" for c in cols) + " |")
    return "\n".join(lines)


def summary_lines(table: dict[str, dict[str, list[float]]], valid_set: dict[str, float], scale_error: list[float]) -> list[str]:
    """The console summary of an evaluation: the results table, valid-set accuracy, scale error."""
    v = valid_set
    line = f"valid-set IoU {v['iou']:.3f} (precision {v['precision']:.3f}, recall {v['recall']:.3f})"
    if "iou_without_dropped" in v:
        line += f"; {v['iou_without_dropped']:.3f} at best without the dropped objects' bounds"
    if scale_error:
        line += f"; relative scale error of matches {float(np.mean(scale_error)):.3f}"
    return [results_table(table), line]


def _region_note(v: dict[str, float]) -> str:
    """``: 0.0139 of the box, 5421 points`` when the accuracy says how it was measured."""
    if "not_measured" in v:
        return f": not measured, {v['not_measured']}"
    if "exact_fraction" not in v:
        return ""
    return f": {v['exact_fraction']:.3g} of the box, learned {v['learned_fraction']:.3g}, {v['exact_points']} region points drawn"


def _save_fig(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def write_plots(res: EvalResult, train_log: list[dict[str, Any]], out: Path) -> list[str]:
    """PNG plots; returns their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    if train_log:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        t = [r["wall_time"] for r in train_log]
        ax.plot(t, [r.get("psnr", np.nan) for r in train_log], "b.-", label="training-view PSNR")
        ax.set_xlabel("training wall time (s)")
        ax.set_ylabel("PSNR (dB)", color="b")
        if any("iou" in r for r in train_log):
            ax2 = ax.twinx()
            ax2.plot(t, [r.get("iou", np.nan) for r in train_log], "r.-", label="valid-set IoU")
            ax2.set_ylabel("valid-set IoU", color="r")
            ax2.set_ylim(0, 1)
        ax.set_title("error against training time")
        _save_fig(fig, out / "training_curve.png")
        plt.close(fig)
        names.append("training_curve.png")
    c = res.curves
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.5))
    fig.subplots_adjust(wspace=0.3)  # the right panel's y label clears the left panel
    axs[0].semilogx(c["best_psnr_vs_n"]["n"], c["best_psnr_vs_n"]["psnr"], "o-", label="best of N")
    for name, style in (("highest score", "--"), (TRUE_SCALES, ":")):  # what N buys, and what it can reach
        if name in res.table:
            axs[0].axhline(res.table[name]["psnr"][0], color="k", lw=1, ls=style, label=name)
    axs[0].legend(fontsize=8)
    axs[0].set_xlabel("number of samples N")
    axs[0].set_ylabel("best PSNR, mean over ground truths (dB)")
    axs[0].set_title("best of N (exact scores of rendered samples)", fontsize=10)
    axs[1].plot(c["overall_psnr_vs_num_gt"]["num_gt"], c["overall_psnr_vs_num_gt"]["psnr"], "o-")
    axs[1].set_xlabel("number of ground truths")
    axs[1].set_ylabel("PSNR of each sample's best match (dB)")
    axs[1].set_title("all samples against more ground truths")
    _save_fig(fig, out / "best_of_n.png")
    plt.close(fig)
    names.append("best_of_n.png")
    if c["search_seconds_per_view_vs_n"]:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ns = [int(k) for k in c["search_seconds_per_view_vs_n"]]
        ax.loglog(ns, list(c["search_seconds_per_view_vs_n"].values()), "o-")
        ax.set_xlabel("N samples")
        ax.set_ylabel("search time per test view (s)")
        ax.set_title("evaluation time against N")
        _save_fig(fig, out / "search_time.png")
        plt.close(fig)
        names.append("search_time.png")
    p = c.get("validity_profile")
    if p:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        x = np.array(p["actual_scale"])
        ax.plot(x, p["score"], "b-", label="learned validity score")
        ex = np.array(p["exact"], dtype=float)
        ax.fill_between(x, 0, ex, color="g", alpha=0.2, label="exact valid interval")
        ax.axhline(0.5, color="k", lw=0.5, ls="--")
        ax.set_xlabel(f"scale of {p['object']} (others at ground truth 0)")
        ax.set_ylabel("validity")
        ax.legend(loc="best")
        _save_fig(fig, out / "validity_profile.png")
        plt.close(fig)
        names.append("validity_profile.png")
    return names


def _reached(train_log: list[dict[str, Any]]) -> str:
    """Training PSNR and valid-set IoU of the last metrics record (what the time bought)."""
    last = train_log[-1] if train_log else {}
    psnr = f"{last['psnr']:.2f} dB" if "psnr" in last else "n/a"
    iou = f"{last['iou']:.3f}" if "iou" in last else "n/a"
    return f"{psnr} / {iou}"


#: Pairs whose missed or excess share of the region is below this are left out of the report's table.
LIMIT_SHARE = 0.005


def limits_lines(limits: list[dict[str, Any]], rows: int = 8) -> list[str]:
    """The report's table of the region's pair bounds the learned set gets most wrong
    (:func:`osn.evaluate.valid_set.valid_set_accuracy`'s ``limits``), largest share first."""
    shown = sorted((e for e in limits if max(e["missed"], e["excess"]) >= LIMIT_SHARE), key=lambda e: -(e["missed"] + e["excess"]))
    if not shown:
        return []
    lines = [
        "Where the learned valid set departs from the exact region, per pair bound `s_i / s_j < B_ij`: the share of the "
        "region it misses nearest that bound (too tight there) and its volume beyond that bound in units of the region's "
        "(too loose); missed shares add up to 1 - recall. Label rays: the final label pool's rays that could set the "
        "bound (0: nothing in training bounds the pair; a minority: left out by `pair_minority`).",
        "",
        "| bound | B_ij | missed | beyond | label rays |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {e['pair']} | {e['bound']:.4f} | {e['missed']:.3f} | {e['excess']:.3f} | {_pool_cell(e)} |" for e in shown[:rows]]
    if len(shown) > rows:
        lines.append(f"| ({len(shown) - rows} more in metrics.json) | | | | |")
    return lines + [""]


def _pool_cell(e: dict[str, Any]) -> str:
    """A limits entry's label rays: ``12``, ``3 (a minority, left out)``, or ``-`` without the record."""
    if "pool_rays" not in e:
        return "-"
    return f"{e['pool_rays']} (a minority, left out)" if e["pool_minority"] else str(e["pool_rays"])


#: The file that marks a report directory written by ``osn evaluate`` (replaced by the next one).
MARKER = ".osn-report"
_WHAT = "an osn evaluation report"
_FILES = ("report.md", "metrics.json", "training_curve.png", "best_of_n.png", "search_time.png", "validity_profile.png",
          PREDICTIONS_LISTING, DATASET_LISTING)


def _unmarked(out: Path) -> bool:
    """A report directory of ours written before the marker existed."""
    return unmarked_report(out, _FILES, "metrics.json",
                           lambda m: isinstance(m, dict) and str(m.get("command", "")).startswith("osn "))


def check_out_dir(out: str | Path) -> None:
    """Refuse (``FileExistsError``, one line) a report directory holding files ``osn`` did not
    write, before the evaluation: :func:`write_report` checks again when it writes."""
    check_own_dir(out, MARKER, _WHAT, _unmarked)


def write_report(res: EvalResult, out_dir: str | Path, run_dir: Path, command: str) -> Path:
    """Write ``report.md``, ``metrics.json`` and the plots to ``out_dir`` (created, or a previous
    report replaced); returns the report path. Raises ``FileExistsError`` when ``out_dir`` holds
    files of another origin."""
    with own_dir(out_dir, MARKER, _WHAT, _unmarked) as out:
        _write_report_files(res, out, run_dir, command)
    return Path(out_dir) / "report.md"


def _write_report_files(res: EvalResult, out: Path, run_dir: Path, command: str) -> None:
    """Every file of the report into ``out`` (the temporary directory of :func:`write_report`)."""
    train_log = read_metrics(run_dir / "metrics.jsonl")  # lines cut by a kill are skipped
    plots = write_plots(res, train_log, out)
    train_s = train_log[-1]["wall_time"] if train_log else float("nan")
    for name, data in res.files.items():  # the per-file digests (benchgen.score.provenance)
        atomic_write_bytes(out / name, data)
    record = {k: v for k, v in asdict(res).items() if k != "files"}
    atomic_write_json(out / "metrics.json", {**record, "train_seconds": train_s, "command": command})
    v, e = res.valid_set, res.extra
    se = res.scale_error
    lines = [
        "# OSN evaluation report",
        "",
        f"Command: `{command}`",
        "",
        *P.banner_lines(e.get("provenance")),
        _inputs_line(run_dir),
        "",
        *_consistency_lines(run_dir),
        *_environment_lines(run_dir),
        f"{e['num_samples']} sampled configurations against {e['num_gt']} ground-truth configurations on "
        f"{e['num_views']} test views each; {100 * e['covisible_fraction']:.1f}% of test pixels are co-visible "
        "with the training video (the rest are masked out). Each ground truth is matched to the sample with the "
        "best mean PSNR over its views (best of N); the baselines commit to one solution of the same model."
        + _true_scales_note(e),
        "",
        *_unposed_lines(e),
        results_table(res.table),
        "",
        *([BY_OBJECT_NOTE, "", by_object_table(e["error_by_object"]), ""] if e.get("error_by_object") else []),
        "| figure | value |",
        "|---|---|",
        f"| valid-set IoU / precision / recall (exact region{_region_note(v)}) | {v['iou']:.3f} / {v['precision']:.3f} / {v['recall']:.3f} |",
        *([f"| valid-set IoU of the exact region without the bounds of the objects preprocessing dropped "
           f"(the best these inputs allow) | {v['iou_without_dropped']:.3f} |"] if "iou_without_dropped" in v else []),
        f"| relative scale error of matched samples | {np.mean(se):.3f} ± {np.std(se):.3f} |" if se else "| relative scale error | n/a (no ground-truth units) |",
        f"| training time, and training PSNR / valid-set IoU reached by then | {train_s:.0f} s: {_reached(train_log)} |",
        f"| evaluation time (ground truth, layered pre-selection, exact scoring of the pre-selected, baselines) | "
        f"{res.timings['ground_truth_s']:.0f} s, {res.timings['layered_search_s']:.0f} s, "
        f"{res.timings['exact_scoring_s']:.0f} s, {res.timings['baselines_s']:.0f} s"
        + (f", true scales {res.timings['true_scales_s']:.0f} s |" if "true_scales_s" in res.timings else " |"),
        f"| ground truths outside the sampled scale box (Eq. 1; reachable only from its edge) | "
        f"{e['gt_outside_scale_box']} of {e['num_gt']} (at most {e['gt_outside_scale_box_max']:.3f} of a range beyond it) |",
        *([f"| samples drawn by hit-and-run inside the learned set (uniform draws found too few) | "
           f"{e['samples_by_hit_and_run']} of {e['num_samples']} |"] if e.get("samples_by_hit_and_run") else []),
        *([f"| samples below the validity threshold (no valid vector found: the best-scoring ones) | "
           f"{e['sample_fallbacks']} of {e['num_samples']} |"] if e.get("sample_fallbacks") else []),
        f"| samples rendered and scored exactly (pre-selected by the layered estimate) | {e['candidates_rendered_exactly']} of {e['num_samples']} |",
        f"| layered estimate alone picks the same match | {100 * e['approx_match_agrees']:.0f}% of ground truths |",
        "",
    ]
    lines += limits_lines(v.get("limits", []))
    lines += [f"![{p}]({p})" for p in plots]
    lines += ["", "`metrics.json` holds every number here, per ground truth (each view's in `per_gt[].per_view`), "
              "with the timings.", "", *P.report_lines(e.get("provenance"))]
    atomic_write_bytes(out / "report.md", ("\n".join(lines) + "\n").encode())

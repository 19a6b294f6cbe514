"""``benchgen score PRED --data DATASET``: the benchmark's scorer for any method's renders."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from scenecore.cli import UserError, subcommand
from scenecore.lock import output_lock

DESCRIPTION = (
    "Score a method's candidate solutions (docs/predictions.md: PRED/CAND/rgb/NAME.png per test view, optional "
    "depth/NAME.exr and ids/NAME.png) against every ground-truth configuration of DATASET: each ground truth is "
    "matched to the candidate with the best mean PSNR over its co-visible test pixels (exact, over all candidates), "
    "then PSNR, SSIM, LPIPS (SSIMAE when every candidate has depth, PQ and mIoU when every candidate has ids) of the "
    "matches are reported as mean and std over the ground truths. Writes report.md, metrics.json, psnr_matrix.npy "
    "and PNG plots. Candidates that hold train/rgb/NAME.png (their renders of the training video) are checked for "
    "fidelity, and best of N is also reported over the faithful ones, which spraying configurations cannot raise; "
    "coverage and precision are reported over PSNR levels. "
    "Every prediction file is checked before anything is written; a bad one is named on one line "
    "with exit code 2. A dataset whose verification.json is missing or failed is refused (exit 2) unless "
    "--unverified. metrics.json records the SHA-256 of every prediction and ground-truth file read (listed in "
    "predictions.sha256 and dataset.sha256 beside it), the protocol and the scorer's version; "
    "'benchgen score --check DIR/metrics.json' recomputes them: exit 0 when everything matches, 1 with one line per "
    "difference, 2 on bad input."
)


def add_score_command(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``score`` on ``benchgen``'s sub-parsers."""
    p = subcommand(sub, "score", _cmd_score, "score any method's renders: best of N against every ground truth", DESCRIPTION)
    p.add_argument("predictions", metavar="PRED", nargs="?", default=None,
                   help="prediction directory: one sub-directory per candidate (docs/predictions.md); with --check, "
                   "where the scored predictions are now (default: the directory metrics.json records)")
    p.add_argument("--data", metavar="DATASET", help="dataset directory written by 'benchgen generate' (required to score; "
                   "with --check, where the scored dataset is now, default: the directory metrics.json records)")
    p.add_argument("--unverified", action="store_true",
                   help="score a dataset whose verification.json is missing or failed (refused otherwise); the report "
                   "and metrics.json say so")
    p.add_argument("--check", metavar="METRICS", default=None,
                   help="re-verify a score instead: recompute the digests metrics.json records from the prediction "
                   "and dataset files and name every difference (exit 0: all match, 1: something differs)")
    p.add_argument("--out", default=None, metavar="DIR", help="output directory; when not given, PRED-score beside PRED. A previous report there is "
                   "replaced; a directory holding other files is refused")
    p.add_argument("--max-views", type=int, default=0, metavar="K",
                   help="score at most K test views, evenly spread as in 'osn evaluate' (0 = all; candidates need only these)")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS (it needs the weights installed by 'make setup')")
    p.add_argument("--workers", type=int, default=1, metavar="N", help="processes reading and checking candidates (and the ground truth) while this one scores them; same result for any N")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _command(args: argparse.Namespace, out: Path) -> str:
    parts = ["benchgen", "score", args.predictions, "--data", args.data, "--out", str(out)]
    parts += ["--max-views", str(args.max_views)] * bool(args.max_views) + ["--no-lpips"] * args.no_lpips
    parts += ["--unverified"] * args.unverified
    return shlex.join(parts + ["--workers", str(args.workers)])


def _cmd_score(args: argparse.Namespace) -> int:
    if args.workers < 1 or args.max_views < 0:
        raise UserError(f"--workers must be >= 1 and --max-views >= 0, got {args.workers} and {args.max_views}")
    if args.check is not None:
        return _check(args)
    if args.predictions is None or args.data is None:
        raise UserError("give PRED and --data DATASET to score (or --check METRICS to re-verify a score)")
    data, pred = Path(args.data), Path(args.predictions)
    if not data.is_dir():
        raise UserError(f"{data}: not a directory (expected a dataset written by 'benchgen generate')")
    out = Path(args.out) if args.out else pred.resolve().parent / f"{pred.resolve().name}-score"
    with output_lock(out):  # one writer per report
        return _score_locked(args, data, pred, out)


def _score_locked(args: argparse.Namespace, data: Path, pred: Path, out: Path) -> int:
    from scenecore import dataset as D
    from benchgen.score import provenance as P
    from benchgen.score.predictions import PredictionDir
    from benchgen.score.report import check_out_dir, results_table, write_report
    from benchgen.score.scorer import metric_keys, score
    from benchgen.score.truth import evaluated_views, load_truth

    check_out_dir(out)  # before the scoring, not after it
    scene = D.load_scene(data)
    verified = P.verification(data, scene, args.unverified)  # refuses an unverified dataset
    views = [f.name for f in evaluated_views(scene, args.max_views)]
    # The structure of every candidate is checked before the ground truth is read (it is cheap).
    source = PredictionDir(pred, scene, views)
    t0 = time.perf_counter()
    prov = P.collect(data, scene, views, args.max_views, metric_keys(source, not args.no_lpips), verified, pred,
                     workers=args.workers)
    t_digests = time.perf_counter() - t0
    t0 = time.perf_counter()
    truth = load_truth(data, args.max_views, args.workers, progress=not args.quiet)
    t_truth = time.perf_counter() - t0
    res = score(truth, source, with_lpips=not args.no_lpips, workers=args.workers, progress=not args.quiet)
    res.timings = {"digests_s": t_digests, "ground_truth_s": t_truth, **res.timings}
    res.info["provenance"], res.files = prov.record, prov.files
    report = write_report(res, out, source.method, _command(args, out), str(data), str(pred))
    label = f"{source.method.get('name', 'candidates')}: best of {len(source)}"
    print(fidelity_summary(res.fidelity, source.method.get("name", "candidates")))
    print(results_table(res.summary, label + (" (unguarded)" if res.fidelity.get("checked") else "")))
    if truth.masks_note:
        print(f"note: {truth.masks_note}")
    print(f"{len(source)} candidates x {truth.num_configurations} ground truths x {truth.num_views} views in "
          f"{res.timings['total_s']:.1f} s; report: {report}")
    return 0


def fidelity_summary(fidelity: dict, name: str) -> str:
    """What the command prints first: the guarded best of N, or that fidelity was not checked."""
    from benchgen.score.report import results_table

    if not fidelity.get("checked"):
        return f"note: {fidelity['note']}"
    head = f"faithful candidates: {fidelity['num_faithful']} / {len(fidelity['faithful'])}"
    if not fidelity.get("summary"):
        return head + " (no guarded best of N)"
    return head + "\n" + results_table(fidelity["summary"], f"{name}: best of {fidelity['num_faithful']} faithful")


def _check(args: argparse.Namespace) -> int:
    """``--check METRICS``: one line per difference and exit 1, or one line and exit 0."""
    from benchgen.score.check import check

    if args.out is not None or args.unverified or args.max_views or args.no_lpips:
        raise UserError("--check takes only METRICS, PRED, --data and --workers (it scores nothing)")
    lines, notes = check(args.check, args.predictions, args.data, args.workers)
    for line in notes + lines:
        print(line)
    if lines:
        print(f"{args.check}: {len(lines)} difference(s) from the scored files", file=sys.stderr)
        return 1
    print(f"{args.check}: every recorded digest matches the files")
    return 0

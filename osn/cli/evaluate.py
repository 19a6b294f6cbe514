"""``osn sample`` and ``osn evaluate``: command-line front ends of :mod:`osn.sample` and :mod:`osn.evaluate`."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import time
from pathlib import Path

from scenecore.cli import UserError, subcommand
from scenecore import dataset as D
from scenecore.lock import output_lock
from benchgen.score import provenance
from osn.evaluate.bestofn import EvalConfig, evaluate
from osn.evaluate.report import check_out_dir, summary_lines, write_report
from osn.model.run import load_run
from osn.sample.configurations import Samples, sample_configurations


def _cmd_sample(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    run = load_run(args.run)
    s = sample_configurations(run, args.n, args.threshold, args.seed)
    out = Path(args.out) if args.out else Path(args.run) / "samples.npz"
    s.save(out)
    note = f" ({s.chained} by hit-and-run inside the set: uniform draws found too few)" if s.chained else ""
    note += f" ({s.fell_back} below the threshold: no valid vector was found)" if s.fell_back else ""
    print(f"{len(s.sbar)} configurations (score > {args.threshold}){note} written to {out} "
          f"in {time.perf_counter() - t0:.1f} s; scores {s.score.min():.3f}..{s.score.max():.3f}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path(args.run) / "report"
    with contextlib.ExitStack() as held:  # one writer per report and per candidates directory
        for d in (out, args.candidates):
            if d is not None:
                held.enter_context(output_lock(d))
        return _evaluate_locked(args, out)


def _evaluate_locked(args: argparse.Namespace, out: Path) -> int:
    check_out_dir(out)  # before the evaluation, not after it
    # An unverified dataset is refused before the run is loaded (evaluate() records the verdict).
    provenance.verification(args.data, D.load_scene(args.data), args.unverified)
    cfg = EvalConfig(max_views=args.max_views, levels=args.levels, topk=args.topk, lpips=not args.no_lpips, seed=args.seed,
                     true_scales=not args.no_true_scales)
    run = load_run(args.run)
    samples_path = Path(args.samples) if args.samples else Path(args.run) / "samples.npz"
    samples = Samples.load(samples_path)
    if samples.sbar.shape[1] != run.inputs.num_objects:
        raise UserError(f"{samples_path}: samples have {samples.sbar.shape[1]} objects, the run has {run.inputs.num_objects}")
    t0 = time.perf_counter()
    res = evaluate(run, args.data, samples, cfg, candidates_dir=args.candidates, unverified=args.unverified)
    res.timings["total_s"] = time.perf_counter() - t0
    report = write_report(res, out, Path(args.run), "osn " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    print("\n".join(summary_lines(res.table, res.valid_set, res.scale_error)))
    print(f"report: {report}")
    return 0


def add_eval_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``osn sample`` and ``osn evaluate``."""
    p = subcommand(sub, "sample", _cmd_sample, "draw valid scale configurations from a trained scale network",
                   description="Draw N scale vectors uniformly from the learned valid set (validity score above the "
                   "threshold): uniform draws over the scale box, and where they find too few (a set a millionth "
                   "of the box) hit-and-run inside the set from those found. Uses no ground truth. Writes "
                   "normalised scales, de-normalised scales, scores and how many were drawn each way to "
                   "RUN/samples.npz.")
    p.add_argument("run", help="run directory of `osn train`")
    p.add_argument("-n", type=int, default=1000, help="number of configurations")
    p.add_argument("--threshold", type=float, default=0.5, help="minimum validity score")
    p.add_argument("--seed", type=int, default=0, help="sampling seed")
    p.add_argument("--out", help="output file (default RUN/samples.npz)")

    p = subcommand(sub, "evaluate", _cmd_evaluate, "best-of-N evaluation against every ground-truth configuration",
                   description="Match each ground-truth configuration of DATASET to the best of the sampled "
                   "configurations (mean PSNR over its test views), report PSNR/SSIM/LPIPS/SSIMAE/PQ/mIoU (mean +- std "
                   "over ground truths) next to single-solution baselines, the valid-set accuracy against the exact "
                   "region, curves and timings. Writes report.md, metrics.json (with the SHA-256 of every dataset file read "
                   "and of the --candidates written, listed in dataset.sha256 and predictions.sha256; 'benchgen score "
                   "--check' re-verifies them) and PNG plots. A dataset whose verification.json is missing or failed is "
                   "refused unless --unverified.")
    p.add_argument("run", help="run directory of `osn train`")
    p.add_argument("--data", required=True, metavar="DATASET", help="the benchgen dataset the run was trained on")
    p.add_argument("--samples", metavar="FILE", help="samples file (default RUN/samples.npz from `osn sample`)")
    p.add_argument("--out", help="report directory (default RUN/report); a previous report there is replaced, "
                   "a directory holding other files is refused")
    p.add_argument("--max-views", type=int, default=30, help="evaluate at most this many test views, evenly spread (0 = all)")
    p.add_argument("--levels", type=int, default=EvalConfig.levels,
                   help="quantised scales per object in the layered search, at quantiles of the samples' scales "
                        "(more: a closer pre-selection, a slower search)")
    p.add_argument("--topk", type=int, default=EvalConfig.topk, help="candidates per ground truth rendered exactly before matching")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    p.add_argument("--no-true-scales", action="store_true",
                   help="skip the 'true scales' reference row: the run's fields rendered at every ground truth's exact "
                   "scales (what best of N approaches with these fields; costs G more rendered candidates)")
    p.add_argument("--seed", type=int, default=0, help="seed of Monte-Carlo valid-set points (more than 3 objects)")
    p.add_argument("--unverified", action="store_true",
                   help="score a dataset whose verification.json is missing or failed (refused otherwise); the report "
                   "and metrics.json say so")
    p.add_argument("--candidates", metavar="DIR",
                   help="also write the rendered candidates as prediction directories for `benchgen score` "
                   "(DIR/preselected, DIR/highest-score, DIR/centre-of-ranges, DIR/true-scales; docs/predictions.md), "
                   "each candidate with its render of the training video (CAND/train/rgb/, for the fidelity check)")

"""Pre-selected best of N (`osn evaluate`) against exact scoring of all N samples, side by side.

Both go through the benchmark's scorer (`benchgen.score.scorer.score`) on exact renders:
- pre-selected: the layered estimate of all N x G PSNRs picks the ``topk`` samples of every ground
  truth (plus the highest-scoring one); only those are rendered and scored (what `osn evaluate` does);
- all N: every sample rendered and scored.
Reported: both wall times, the PSNR the pre-selected match loses against the best of all N (exact),
and how often the match is the same sample.

    python benchmarks/bench_bestofn.py RUN DATASET [-n 1000] [--views 3] [--levels 64] [--topk 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from benchutil import print_command

from benchgen.score.scorer import score
from benchgen.score.truth import load_truth
from osn.evaluate.bestofn import EvalConfig, preselect, sample_name
from osn.evaluate.exact import RenderedCandidates
from osn.evaluate.layered import layered_psnr
from osn.model.run import load_run
from osn.sample.configurations import sample_configurations


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("dataset")
    p.add_argument("-n", type=int, default=1000, help="samples N")
    p.add_argument("--views", type=int, default=3, help="test views evaluated (0 = all)")
    p.add_argument("--levels", type=int, default=EvalConfig.levels)
    p.add_argument("--topk", type=int, default=EvalConfig.topk)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print_command()

    run = load_run(args.run)
    samples = sample_configurations(run, args.n, seed=args.seed)
    truth = load_truth(args.dataset, args.views)
    G, V, N = truth.num_configurations, truth.num_views, len(samples.sbar)

    t0 = time.perf_counter()
    approx = np.nanmean(layered_psnr(run, samples, truth, args.levels), axis=2)  # (N, G)
    cand = preselect(approx, samples.score, args.topk)
    pre = score(truth, RenderedCandidates(run, truth, {sample_name(int(n)): samples.sbar[n] for n in cand}), with_lpips=False)
    t_pre = time.perf_counter() - t0
    pre_pick = cand[[r["match_index"] for r in pre.per_ground_truth]]

    t0 = time.perf_counter()
    full = score(truth, RenderedCandidates(run, truth, {sample_name(n): samples.sbar[n] for n in range(N)}), with_lpips=False,
                 progress=True)
    t_all = time.perf_counter() - t0
    all_pick = np.array([r["match_index"] for r in full.per_ground_truth])

    loss = full.matrix[all_pick, np.arange(G)] - full.matrix[pre_pick, np.arange(G)]
    print(f"N={N} samples, G={G} ground truths, V={V} views, {run.inputs.width}x{run.inputs.height}, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"all N scored exactly:   {t_all:8.1f} s  ({N} samples rendered)")
    print(f"pre-selected (osn evaluate): {t_pre:8.1f} s  ({len(cand)} samples rendered)")
    print(f"speed-up: {t_all / t_pre:.1f}x")
    print(f"best-of-N PSNR: all N {full.summary['psnr']['mean']:.3f} dB, pre-selected {pre.summary['psnr']['mean']:.3f} dB; "
          f"lost per ground truth: mean {loss.mean():.4f} dB, max {loss.max():.4f} dB "
          f"(same sample for {np.mean(all_pick == pre_pick) * 100:.0f}% of ground truths)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

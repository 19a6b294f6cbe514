"""Best-of-N search: the layered search of `osn evaluate` against the naive search, side by side.

Naive: render every sample exactly on every evaluated view and take, per ground truth, the sample
with the best mean PSNR. Layered (osn.evaluate): per-object layers at quantised scales, N x G
PSNRs by matrix products, exact re-ranking of the top-k candidates. Reported: both wall times,
the speed-up, and the PSNR the layered choice loses against the naive choice (exact renders).

    python benchmarks/bench_bestofn.py RUN DATASET [-n 1000] [--views 3] [--levels 24] [--topk 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from benchutil import print_command


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("dataset")
    p.add_argument("-n", type=int, default=1000, help="samples N")
    p.add_argument("--views", type=int, default=3, help="test views evaluated")
    p.add_argument("--levels", type=int, default=24)
    p.add_argument("--topk", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print_command()

    from osn.evaluate.exact import exact_psnr, render_sample
    from osn.evaluate.ground_truth import load_ground_truth
    from osn.evaluate.layered import layered_psnr
    from osn.sample.configurations import sample_configurations
    from osn.model.run import load_run

    run = load_run(args.run)
    samples = sample_configurations(run, args.n, seed=args.seed)
    gt = load_ground_truth(args.dataset, args.views)
    G, V = gt.rgb.shape[:2]
    N = len(samples.sbar)

    t0 = time.perf_counter()
    approx = np.nanmean(layered_psnr(run, samples, gt, args.levels), axis=2)  # (N, G)
    cand = np.unique(np.argsort(-approx, axis=0)[: args.topk].reshape(-1))
    exact_c = {n: np.nanmean(exact_psnr(render_sample(run, gt, samples.sbar[n]), gt), axis=1) for n in cand}
    layered_pick = np.array([max(cand, key=lambda n: exact_c[n][g]) for g in range(G)])
    t_layered = time.perf_counter() - t0

    t0 = time.perf_counter()
    exact_all = np.stack([np.nanmean(exact_psnr(render_sample(run, gt, samples.sbar[n]), gt), axis=1) for n in range(N)])
    naive_pick = exact_all.argmax(0)
    t_naive = time.perf_counter() - t0

    naive_psnr = exact_all[naive_pick, np.arange(G)]
    layered_psnr_exact = exact_all[layered_pick, np.arange(G)]
    loss = naive_psnr - layered_psnr_exact
    print(f"N={N} samples, G={G} ground truths, V={V} views, {run.inputs.width}x{run.inputs.height}, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"naive search:   {t_naive:8.1f} s  ({N * V} exact renders)")
    print(f"layered search: {t_layered:8.1f} s  ({len(cand)} samples rendered exactly)")
    print(f"speed-up: {t_naive / t_layered:.1f}x")
    print(f"PSNR lost by the layered choice: mean {loss.mean():.4f} dB, max {loss.max():.4f} dB "
          f"(same sample for {np.mean(naive_pick == layered_pick) * 100:.0f}% of ground truths)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Evaluation's renders with views side by side on CPU threads (`osn.model.parallel.map_views`,
what evaluation uses) against one view at a time on torch's intra-op threads.

Two workloads of `osn evaluate`, each run under both modes in turn, twice (A B A B), so machine
noise hits both alike:
- candidates: `osn.evaluate.exact.render_candidates` (whole configurations, exact scoring);
- layered search: `osn.evaluate.layered.layered_psnr` of 200 samples (one object at a time).
Printed: seconds of each (both repeats summed), their ratio, the threads used, and the largest
difference of the renders (colour, depth) and of the layered PSNRs.

    python benchmarks/bench_render_threads.py RUN DATASET [--views 10] [--configs 10]
"""

from __future__ import annotations

import time

import numpy as np
import torch
from benchutil import render_bench_inputs

import osn.model.parallel as parallel
from osn.evaluate.exact import render_candidates
from osn.evaluate.layered import layered_psnr
from osn.sample.configurations import sample_configurations

THREADED = parallel.render_workers


def main() -> None:
    run, truth, sbar = render_bench_inputs(__doc__)
    samples = sample_configurations(run, 200, 0.5, 0)
    modes = {"one view at a time": lambda device, n: 1, "views on threads": THREADED}
    works = {"candidates": lambda: render_candidates(run, truth.frames, list(sbar)),
             "layered search": lambda: layered_psnr(run, samples, truth, 24)}
    seconds = {(w, m): 0.0 for w in works for m in modes}
    out: dict = {}
    for _ in range(2):
        for w, work in works.items():
            for m, workers in modes.items():
                parallel.render_workers = workers
                t0 = time.perf_counter()
                out[(w, m)] = work()
                seconds[(w, m)] += time.perf_counter() - t0
    parallel.render_workers = THREADED
    (ref, new) = modes
    dc = max(float(np.max(np.abs(a.rgb - b.rgb))) for a, b in zip(out[("candidates", ref)], out[("candidates", new)]))
    dd = max(float(np.max(np.abs(np.nan_to_num(a.depth - b.depth, nan=0.0)))) for a, b in zip(out[("candidates", ref)], out[("candidates", new)]))
    dp = float(np.nanmax(np.abs(out[("layered search", ref)] - out[("layered search", new)])))
    print(f"{len(truth.frames)} views, {len(sbar)} candidates, 200 samples for the layered search; "
          f"torch threads {torch.get_num_threads()}, render workers {THREADED(run.device, len(truth.frames))} on {run.device}")
    print(f"| workload | {ref} | {new} | ratio | largest difference |")
    print("|---|---|---|---|---|")
    for w in works:
        a, b = seconds[(w, ref)], seconds[(w, new)]
        d = f"colour {dc:.1e}, depth {dd:.1e}" if w == "candidates" else f"PSNR {dp:.1e} dB"
        print(f"| {w} | {a:.2f} s | {b:.2f} s | {a / b:.2f}x | {d} |")


if __name__ == "__main__":
    main()

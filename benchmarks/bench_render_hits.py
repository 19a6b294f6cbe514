"""Evaluation's renders with each ray composited from the objects it hits, against every object on
every ray, side by side in one process.

`TrainedRun.render_view` renders through `osn.model.volume.render_by_hits` (rays grouped by the
set of object boxes they cross); the reference composites every posed object on every ray
(`osn.model.volume.render`, as before 2026-11-26). Two workloads of `osn evaluate`, alternated
per view so machine noise hits both alike:
- candidates: whole configurations on test views, the anchor shaded once per view (exact scoring);
- layers: one object alone at a time (the layered search renders Q scales of each object).
Printed: seconds of each, their ratio, and the largest difference of colour, opacity and depth
(depth in scene units, over pixels that both renders hit; a hole in one render only counts as inf).

    python benchmarks/bench_render_hits.py RUN DATASET [--views 10] [--configs 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchutil import print_command

import osn.model.run as run_module
from benchgen.score.truth import load_truth
from osn.model.run import load_run
from osn.model.volume import render, render_by_hits
from osn.sample.configurations import sample_configurations


def every_object(objects, dirs, n_samples, background, skip):
    """The reference: `render` on every ray with every posed object."""
    return render(objects, dirs, n_samples, None, background, skip)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="osn train run directory")
    ap.add_argument("dataset", help="its benchgen dataset (test views)")
    ap.add_argument("--views", type=int, default=10, help="test views, evenly spread")
    ap.add_argument("--configs", type=int, default=10, help="sampled configurations rendered per view")
    args = ap.parse_args()
    print_command()
    run = load_run(args.run)
    truth = load_truth(args.dataset, args.views)
    sbar = sample_configurations(run, args.configs, 0.5, 0).sbar
    free = [k for k in range(run.inputs.num_objects) if k != run.anchor_pos]
    seconds = {(w, m): 0.0 for w in ("candidates", "layers") for m in ("every object", "objects hit")}
    diff = {(w, key): 0.0 for w in ("candidates", "layers") for key in ("rgb", "acc", "depth")}
    for f in truth.frames:
        for work in ("candidates", "layers"):
            out = {}
            for mode, fn in (("every object", every_object), ("objects hit", render_by_hits)):
                run_module.render_by_hits = fn  # what render_view composites with
                t0 = time.perf_counter()
                anchor = run.shade_anchor(f.camera_to_world, f.time_index) if work == "candidates" else None
                out[mode] = [run.render_view(f.camera_to_world, f.time_index, s, anchor=anchor,
                                             objects=None if work == "candidates" else [free[c % len(free)]])
                             for c, s in enumerate(sbar)]
                seconds[(work, mode)] += time.perf_counter() - t0
            for a, b in zip(out["every object"], out["objects hit"]):
                for key in ("rgb", "acc", "depth"):
                    finite = np.isfinite(a[key])
                    if not np.array_equal(finite, np.isfinite(b[key])):  # a hole in one render only
                        diff[(work, key)] = float("inf")
                    elif finite.any():
                        diff[(work, key)] = max(diff[(work, key)], float(np.max(np.abs(a[key][finite] - b[key][finite]))))
    run_module.render_by_hits = render_by_hits
    n = len(truth.frames) * len(sbar)
    print(f"{n} renders per workload ({len(truth.frames)} views x {len(sbar)} configurations)")
    print("| workload | every object on every ray | objects each ray hits | ratio | largest difference: colour / opacity / depth |")
    print("|---|---|---|---|---|")
    for work in ("candidates", "layers"):
        a, b = seconds[(work, "every object")], seconds[(work, "objects hit")]
        d = " / ".join(f"{diff[(work, key)]:.1e}" for key in ("rgb", "acc", "depth"))
        print(f"| {work} | {a:.2f} s | {b:.2f} s | {a / b:.2f}x | {d} |")


if __name__ == "__main__":
    main()

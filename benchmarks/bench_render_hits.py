"""Evaluation's renders with each ray composited from the objects it hits, against every object on
every ray, side by side in one process.

`TrainedRun.render_view` renders through `osn.model.volume.render_by_hits` (rays grouped by the
set of object boxes they cross); the reference composites every posed object on every ray
(`osn.model.volume.render`). Two workloads of `osn evaluate`, alternated
per view so machine noise hits both alike:
- candidates: whole configurations on test views, the anchor shaded once per view (exact scoring);
- layers: one object alone at a time (the layered search renders Q scales of each object).
Printed: seconds of each, their ratio, and the largest difference of colour, opacity and depth
(depth in scene units, over pixels that both renders hit; a hole in one render only counts as inf).

    python benchmarks/bench_render_hits.py RUN DATASET [--views 10] [--configs 10]
"""

from __future__ import annotations

from benchutil import compare_renders, render_bench_inputs

import osn.model.run as run_module
from osn.model.volume import render, render_by_hits


def every_object(objects, dirs, n_samples, background, skip):
    """The reference: `render` on every ray with every posed object."""
    return render(objects, dirs, n_samples, None, background, skip)


def main() -> None:
    run, truth, sbar = render_bench_inputs(__doc__)

    def install(impl) -> None:
        run_module.render_by_hits = impl  # what render_view composites with

    compare_renders(run, truth, sbar, [("every object on every ray", every_object), ("objects each ray hits", render_by_hits)],
                    install)


if __name__ == "__main__":
    main()

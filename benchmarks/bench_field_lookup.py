"""Evaluation's renders with the dense fields looked up through ``grid_sample`` (what evaluation
uses: no autograd) against training's gather, side by side in one process.

Without autograd, `osn.model.fields.DenseGridField` looks its grid up with
`osn.model.fields.trilinear_frozen` (``grid_sample`` on a cached channels-first copy); the
reference is `osn.model.fields.trilinear` (one gather of the 8 corners, what training uses for its
backward). Two workloads of `osn evaluate`, alternated per view so machine noise hits both alike:
- candidates: whole configurations on test views, the anchor shaded once per view (exact scoring);
- layers: one object alone at a time (the layered search).
Printed: seconds of each, their ratio, and the largest difference of colour, opacity and depth.

    python benchmarks/bench_field_lookup.py RUN DATASET [--views 10] [--configs 10]
"""

from __future__ import annotations

from benchutil import compare_renders, render_bench_inputs

from osn.model.fields import DenseGridField, trilinear

FROZEN = DenseGridField._lookup


def gather(field: DenseGridField, channels: slice, xn):
    """The reference: training's gather, also without autograd."""
    return trilinear(field.grid[:, channels], field.resolution, xn)


def main() -> None:
    run, truth, sbar = render_bench_inputs(__doc__)

    def install(impl) -> None:
        DenseGridField._lookup = impl

    compare_renders(run, truth, sbar, [("gather", gather), ("grid_sample", FROZEN)], install)


if __name__ == "__main__":
    main()

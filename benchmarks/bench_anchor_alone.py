"""Exact scoring's composites with the rays that cross the anchor alone taken from one render of
the anchor per view, against rendering those rays again for every configuration, side by side.

`osn.model.volume.render_by_hits` groups a view's rays by the object boxes they cross; most rays of
a candidate configuration cross the anchor (the room) alone, whose samples are shaded once per
view (`TrainedRun.shade_anchor`). By default (``reuse_alone=True``) those rays take rows of one
render of the anchor alone (`ShadedSamples.alone`), made at the first configuration of the view and kept; the
reference (`reuse_alone=False`) composites them again for each configuration. Views alternate
between the two, so machine noise hits both alike; the layers workload renders one object alone
(no shaded anchor), so both modes run the same code there.

    python benchmarks/bench_anchor_alone.py RUN DATASET [--views 10] [--configs 10]
"""

from __future__ import annotations

from functools import partial

from benchutil import compare_renders, render_bench_inputs

import osn.model.run as run_module
from osn.model.volume import render_by_hits


def main() -> None:
    run, truth, sbar = render_bench_inputs(__doc__)

    def install(impl) -> None:
        run_module.render_by_hits = impl  # what render_view composites with

    compare_renders(run, truth, sbar, [("anchor's rays composited per configuration", partial(render_by_hits, reuse_alone=False)),
                                       ("anchor alone rendered once per view", render_by_hits)], install)


if __name__ == "__main__":
    main()

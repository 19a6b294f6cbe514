"""Exact renders of sampled configurations on the evaluated test views, as scoring candidates.

:class:`RenderedCandidates` is a :class:`benchgen.score.predictions.CandidateSource`: the scorer
pulls candidates from it exactly as it reads a prediction directory, and
:meth:`RenderedCandidates.write` writes them as one (docs/predictions.md), so the same renders
can be scored again with ``benchgen score``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.atomic import atomic_write_json
from benchgen.score.predictions import SUFFIX, Candidate, check_candidate
from benchgen.score.truth import Truth
from osn.model.run import TrainedRun


def render_candidate(run: TrainedRun, frames: Sequence[D.Frame], sbar: np.ndarray) -> Candidate:
    """Composite volume renders of configuration ``sbar (K,)`` on ``frames``.

    Returns ``rgb (V, H, W, 3)`` float32 in [0, 1], ``depth (V, H, W)`` planar (``+inf`` where
    nothing is hit), ``ids (V, H, W)`` uint8, as a :class:`~benchgen.score.predictions.Candidate`.
    """
    views = [run.render_view(f.camera_to_world, f.time_index, sbar) for f in frames]
    rgb = np.clip(np.stack([v["rgb"] for v in views]), 0.0, 1.0).astype(np.float32)
    depth = np.stack([v["depth"] for v in views]).astype(np.float32)
    return Candidate(rgb=rgb, depth=depth, ids=np.stack([v["ids"] for v in views]).astype(np.uint8))


class RenderedCandidates:
    """Named configurations (``name -> sbar (K,)``) rendered on the evaluated views on demand.

    A render is kept once made: the scorer loads a matched candidate twice (the PSNR pass, then
    its full metrics), and :meth:`write` saves every render without rendering again. Memory is
    that of the rendered candidates (the pre-selection keeps their number small).
    """

    has_depth = True
    has_ids = True

    def __init__(self, run: TrainedRun, truth: Truth, configurations: dict[str, np.ndarray]) -> None:
        self.run, self.truth = run, truth
        self.names = list(configurations)
        self.sbar = [np.asarray(configurations[n]) for n in self.names]
        self.rendered: dict[int, Candidate] = {}

    def __len__(self) -> int:
        return len(self.names)

    def load(self, index: int) -> Candidate:
        if index not in self.rendered:
            c = render_candidate(self.run, self.truth.frames, self.sbar[index])
            check_candidate(c, self.names[index], self.truth.scene, self.truth.num_views, True, True)
            self.rendered[index] = c
        return self.rendered[index]

    def write(self, out: str | Path, method: dict) -> Path:
        """Write every candidate (rendering those not yet rendered) as the prediction directory
        ``out`` (``CAND/{rgb,depth,ids}/NAME.*`` for the evaluated views, ``method.json``)."""
        out = Path(out)
        for i, name in enumerate(self.names):
            c = self.load(i)
            for kind in SUFFIX:
                (out / name / kind).mkdir(parents=True, exist_ok=True)
            for v, f in enumerate(self.truth.frames):
                path = {kind: out / name / kind / (f.name + suffix) for kind, suffix in SUFFIX.items()}
                D.write_rgb(path["rgb"], np.round(c.rgb[v] * 255.0).astype(np.uint8))  # 8-bit, as the dataset
                D.write_depth(path["depth"], c.depth[v])
                D.write_ids(path["ids"], c.ids[v])
        atomic_write_json(out / "method.json", method)
        return out

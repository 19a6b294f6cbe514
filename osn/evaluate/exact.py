"""Exact renders of sampled configurations on the evaluated test views, as scoring candidates."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from scenecore import dataset as D
from benchgen.score.predictions import Candidate, MemorySource
from benchgen.score.truth import Truth
from osn.model.run import TrainedRun


def render_candidate(run: TrainedRun, frames: Sequence[D.Frame], sbar: np.ndarray) -> Candidate:
    """Composite volume renders of configuration ``sbar (K,)`` on ``frames``.

    Returns a :class:`benchgen.score.predictions.Candidate`: ``rgb (V, H, W, 3)`` float in [0, 1],
    ``depth (V, H, W)`` planar (``+inf`` where nothing is hit), ``ids (V, H, W)`` uint8.
    """
    views = [run.render_view(f.camera_to_world, f.time_index, sbar) for f in frames]
    rgb = np.clip(np.stack([v["rgb"] for v in views]), 0.0, 1.0)
    return Candidate(rgb=rgb, depth=np.stack([v["depth"] for v in views]), ids=np.stack([v["ids"] for v in views]).astype(np.uint8))


def candidate_source(run: TrainedRun, truth: Truth, configurations: dict[str, np.ndarray]) -> MemorySource:
    """The named configurations (``name -> sbar (K,)``) as candidates rendered on demand.

    Each candidate is rendered when the scorer asks for it and cached, so a matched candidate
    is rendered once although the scorer loads it twice (the pass, then the full metrics).
    """
    names = list(configurations)
    cache: dict[int, Candidate] = {}

    def load(i: int) -> Candidate:
        if i not in cache:
            cache[i] = render_candidate(run, truth.frames, configurations[names[i]])
        return cache[i]

    return MemorySource(names, load, truth.scene, truth.num_views, has_depth=True, has_ids=True)

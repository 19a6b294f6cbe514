"""Exact renders of sampled configurations on the evaluated test views, as scoring candidates.

:class:`RenderedCandidates` is a :class:`benchgen.score.predictions.CandidateSource`: the scorer
pulls candidates from it exactly as it reads a prediction directory, and
:meth:`RenderedCandidates.write` writes them as one (docs/predictions.md), so the same renders
can be scored again with ``benchgen score``, together with each candidate's render of the training
video (``CAND/train/rgb/NAME.png``, :func:`render_training`), which ``benchgen score``'s fidelity
check compares with the video.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.atomic import atomic_write_json
from scenecore.paths import join_inside
from benchgen.score.predictions import SUFFIX, TRAIN, Candidate, PredictionError, check_candidate, rgb_problem
from benchgen.score.truth import Truth
from osn.model.parallel import map_views
from osn.model.run import TrainedRun

#: Files :meth:`RenderedCandidates.write` writes at once.
WRITE_THREADS = 4


def render_candidates(
    run: TrainedRun, frames: Sequence[D.Frame], sbars: Sequence[np.ndarray], progress: bool = False
) -> list[Candidate]:
    """Composite volume renders of configurations ``sbars`` (each ``(K,)``) on ``frames``.

    View by view (views side by side on CPU threads, :func:`osn.model.parallel.map_views`), so the
    anchor (at scale 1 in every configuration) is shaded once per view and reused by every
    configuration: the renders are those of :meth:`TrainedRun.render_view`.
    Returns per configuration ``rgb (V, H, W, 3)`` float32 in [0, 1], ``depth (V, H, W)`` planar
    (``+inf`` where nothing is hit), ``ids (V, H, W)`` uint8, as a
    :class:`~benchgen.score.predictions.Candidate`.
    """
    def view(f: D.Frame) -> list[dict]:
        anchor = run.shade_anchor(f.camera_to_world, f.time_index)
        return [run.render_view(f.camera_to_world, f.time_index, sbar, anchor=anchor) for sbar in sbars]

    per_view = map_views(view, frames, run.device, f"rendering {len(sbars)} candidates" if progress and sbars else None)
    views = [[v[c] for v in per_view] for c in range(len(sbars))]
    return [Candidate(rgb=np.clip(np.stack([v["rgb"] for v in vs]), 0.0, 1.0).astype(np.float32),
                      depth=np.stack([v["depth"] for v in vs]).astype(np.float32),
                      ids=np.stack([v["ids"] for v in vs]).astype(np.uint8)) for vs in views]


def render_training(run: TrainedRun, frames: Sequence[D.Frame], sbars: Sequence[np.ndarray], progress: bool = False
                    ) -> list[np.ndarray]:
    """Configurations ``sbars`` rendered from the run's own training cameras at the timestamps of
    the dataset's training ``frames`` (time order): per configuration ``rgb (T, H, W, 3)`` uint8,
    as a PNG holds it. A configuration the run's scale network holds valid reproduces the training
    video as well as the fields can; one outside its valid set changes which object some training
    ray sees first."""
    def view(f: D.Frame) -> list[np.ndarray]:
        anchor = run.shade_anchor(None, f.time_index)
        return [np.round(np.clip(run.render_view(None, f.time_index, sbar, anchor=anchor)["rgb"], 0.0, 1.0) * 255.0).astype(np.uint8)
                for sbar in sbars]

    per_view = map_views(view, frames, run.device, f"rendering {len(sbars)} candidates' training views" if progress and sbars else None)
    return [np.stack([v[c] for v in per_view]) for c in range(len(sbars))]


class RenderedCandidates:
    """Named configurations (``name -> sbar (K,)``) rendered on the evaluated views on demand.

    The first :meth:`load` renders every candidate (view by view, sharing the anchor's samples;
    the scorer loads them all) and keeps them: the scorer loads a matched candidate twice (the
    PSNR pass, then its full metrics), and :meth:`write` saves every render without rendering
    again. Memory is that of the rendered candidates (the pre-selection keeps their number small).
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
        if index not in self.rendered:  # the scorer loads every candidate: render all not yet rendered at once
            todo = [i for i in range(len(self)) if i not in self.rendered]
            for i, c in zip(todo, render_candidates(self.run, self.truth.frames, [self.sbar[i] for i in todo], progress=True)):
                check_candidate(c, self.names[i], self.truth.scene, self.truth.num_views, True, True)
                self.rendered[i] = c
        return self.rendered[index]

    def write(self, out: str | Path, method: dict) -> Path:
        """Write every candidate (rendering those not yet rendered) as the prediction directory
        ``out`` (``CAND/{rgb,depth,ids}/NAME.*`` for the evaluated views, ``CAND/train/rgb/NAME.png``
        for every training frame, ``method.json``)."""
        out = Path(out)
        train = sorted(self.truth.scene.train_frames, key=lambda f: f.time_index)
        # Every path checked before anything is rendered or written: names from files stay inside ``out``.
        paths = {(i, v): {kind: join_inside(out, f"{name}/{kind}/{f.name}{suffix}", "candidate file", PredictionError)
                          for kind, suffix in SUFFIX.items()}
                 for i, name in enumerate(self.names) for v, f in enumerate(self.truth.frames)}
        train_paths = {(i, t): join_inside(out, f"{name}/{TRAIN}/rgb/{f.name}{SUFFIX['rgb']}", "candidate file", PredictionError)
                       for i, name in enumerate(self.names) for t, f in enumerate(train)}
        cands = [self.load(i) for i in range(len(self))]
        train_rgb = render_training(self.run, train, self.sbar, progress=True)
        for name, rgb in zip(self.names, train_rgb):
            for t in range(len(train)):
                if p := rgb_problem(f"{name} train view {t}", rgb[t], self.truth.scene):
                    raise PredictionError(p)

        def write_one(i: int, v: int) -> None:
            c, path = cands[i], paths[i, v]
            D.write_rgb(path["rgb"], np.round(c.rgb[v] * 255.0).astype(np.uint8))  # 8-bit, as the dataset
            D.write_depth(path["depth"], c.depth[v])
            D.write_ids(path["ids"], c.ids[v])

        for folder in {p.parent for path in paths.values() for p in path.values()} | {p.parent for p in train_paths.values()}:
            folder.mkdir(parents=True, exist_ok=True)
        # Threads: each file is encoded (the encoders let other threads run) and fsync-ed (a wait
        # on the disk), so several at once keep both going; the first error is raised.
        jobs = [(i, v) for i in range(len(self)) for v in range(len(self.truth.frames))]
        pool = ThreadPoolExecutor(WRITE_THREADS, thread_name_prefix="write")
        try:
            futures = [pool.submit(write_one, i, v) for i, v in jobs]
            futures += [pool.submit(D.write_rgb, train_paths[i, t], train_rgb[i][t]) for i, t in train_paths]
            for fut in futures:
                fut.result()
        finally:  # on an error, files not yet started are not written
            pool.shutdown(wait=True, cancel_futures=True)
        atomic_write_json(out / "method.json", method)
        return out

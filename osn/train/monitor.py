"""What a metrics line measures: training-view PSNR and, given the exact region, valid-set accuracy.

The monitor is the only training code that sees ground truth, and only what its caller hands it:
the dataset's exact valid region (:class:`scenecore.validity.ValidRegion`) and the inputs'
ground-truth units. It never changes what is trained.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F

from scenecore.validity import ValidRegion, set_accuracy, set_samples

from benchgen.score.metrics import psnr_from_mse as psnr
from osn.evaluate.units import dataset_box, free_normalised, ground_truth_problem
from osn.model.scale_net import full_sbar
from osn.model.volume import SKIP_OCCLUDED, render
from osn.train.trainer import Trainer

log = logging.getLogger(__name__)

#: Fixed training-view pixels of the monitor's PSNR (all usable pixels when fewer).
MONITOR_PIXELS = 4096
#: Points per stratum of the monitor's valid-set precision, recall and IoU (``osn evaluate``
#: reports the same figures from its own, larger count: docs/metrics.md).
MONITOR_POINTS = 20000


class TrainingMonitor:
    """Training-view PSNR on a fixed pixel subset and, with the exact region, valid-set accuracy.

    Attributes:
        flat: ``(N,)`` the scored training pixels (frame * HW + pixel), fixed for the run.
        region: the exact region when valid-set accuracy is measured, else None (a single object,
            no region given, or inputs without ground-truth units).
        points: with ``region``, ``MONITOR_POINTS`` fixed points uniform in the sampling box, as
            many in the exact region's interval box and as many near it (:class:`scenecore.validity.SetSamples`).
        s_mc: their free normalised scales, three ``(M, K-1)`` float64 (uniform, inner, near).
        exact_all: with ``region``, the points of every stratum that lie in the region ``(E, K)``.
    """

    def __init__(self, trainer: Trainer, region: ValidRegion | None) -> None:
        self.tr = trainer
        st = trainer.st
        g = torch.Generator().manual_seed(12345)
        # Pixels of dropped objects (IGNORE_ID) are never trained on, so they are not scored.
        pool = st.usable if st.usable is not None else torch.arange(st.T * st.H * st.W, device=st.device)
        n = min(MONITOR_PIXELS, len(pool))
        self.flat = pool[torch.randperm(len(pool), generator=g)[:n].to(st.device)]
        self.region = None
        # Scales need only the units; test cameras (world_to_anchor) are evaluation's concern.
        problem = ground_truth_problem(st.inputs, test_views=False) if region is not None else None
        if problem:
            log.warning("valid-set accuracy is not measured during training: %s", problem)
        if trainer.net is not None and region is not None and not problem:
            self.region = region
            ranges = st.ranges.cpu().numpy()
            # Stratified points: a region of 1e-6 of the box (8 objects) has none among uniform ones.
            self.points = set_samples(region, dataset_box(st.inputs, ranges, region.num_objects), MONITOR_POINTS, seed=12345)
            self.s_mc = [torch.from_numpy(free_normalised(st.inputs, ranges, x)) for x in self.points.strata]
            # The region's points of every stratum, for the interval error (the points are fixed).
            self.exact_all = np.concatenate([x[np.asarray(region.contains(x), bool)] for x in self.points.strata])
            if not self.points.exact.any():
                log.warning("valid-set accuracy: none of %d points in the exact region's interval box is valid; "
                            "recall and IoU are not measured (NaN)", MONITOR_POINTS)

    @torch.no_grad()
    def best_configuration(self) -> torch.Tensor:
        """The best-scoring ``(K,)`` scale vector of 4096 fixed candidates (``[1]`` for one object)."""
        tr = self.tr
        if tr.net is None:
            return torch.ones(1, dtype=torch.float64, device=tr.device)
        g = torch.Generator().manual_seed(54321)
        s = torch.rand(4096, tr.st.K - 1, generator=g).to(tr.device)
        return full_sbar(s[tr.net(s).argmax()][None], tr.st.ranges, tr.st.anchor)[0]

    @torch.no_grad()
    def __call__(self) -> dict[str, float]:
        """The measurements of one metrics line: ``psnr``; with several objects ``seg_acc`` and
        ``sbar_best``; with the region ``precision``, ``recall``, ``iou`` and ``scale_rel_err``."""
        tr, st, cfg = self.tr, self.tr.st, self.tr.cfg
        frames, p = self.flat // (st.H * st.W), self.flat % (st.H * st.W)
        sbar = self.best_configuration()
        out = render(st.object_rays(tr.fields, frames, sbar), st.dirs[p], cfg.samples, skip_occluded=SKIP_OCCLUDED)
        m: dict[str, float] = {"psnr": psnr(float(F.mse_loss(out.rgb, st.images[frames, p])))}
        if st.K > 1:
            lab = st.labels[frames, p]
            ok = lab >= 0
            m["seg_acc"] = float((out.log_seg[ok].argmax(1) == lab[ok]).float().mean())
            m["sbar_best"] = [float(x) for x in sbar.cpu()]
        if self.region is not None:
            learned = [(tr.net(s.float().to(tr.device)) > 0).cpu().numpy() for s in self.s_mc]
            acc = set_accuracy(self.points, *learned)
            m.update({k: acc[k] for k in ("precision", "recall", "iou")})
            m["scale_rel_err"] = self._interval_error(learned)
        return m

    def _interval_error(self, learned: list[np.ndarray]) -> float:
        """Mean relative error of the learned per-object scale intervals (dataset scales, within
        the sampled box) against the exact region's, both read off the same points (all three
        strata; ``learned``: membership per stratum); 1.0 when either set is empty."""
        strata = self.points.strata
        learned = np.concatenate([x[m] for x, m in zip(strata, learned)])
        exact = self.exact_all
        if not len(learned) or not len(exact):
            return 1.0
        errs = []
        for o in self.tr.st.inputs.objects:
            if o.id == self.region.anchor:
                continue
            a, e = learned[:, o.id], exact[:, o.id]
            errs += [abs(a.min() - e.min()) / e.min(), abs(a.max() - e.max()) / e.max()]
        return float(np.mean(errs))

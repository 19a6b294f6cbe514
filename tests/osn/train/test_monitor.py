"""The training monitor measures the learned valid set against the exact region it is given."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from scenecore import dataset as D
from scenecore.validity import ValidRegion

from osn.preprocess.oracle import oracle_inputs
from osn.train import Trainer, TrainingMonitor
from tests.osn.train.common import small_config


def test_monitor_is_exact_with_an_oracle_network(tiny_dataset: Path, tiny_region: ValidRegion) -> None:
    """A network that is the exact region's indicator (computed from the dataset's region and
    units, not from the monitor's labels) scores IoU 1, and the labels are not trivial."""
    inputs = oracle_inputs(tiny_dataset)
    tr = Trainer(inputs, small_config(), torch.device("cpu"))
    ev = TrainingMonitor(tr, tiny_region)
    assert 0.0 < ev.points.exact.mean() < 1.0  # some Monte-Carlo samples are valid, some are not
    region = tiny_region
    units = np.array([o.unit_to_world for o in inputs.objects])
    ranges = tr.st.ranges.cpu().numpy()
    free = [k for k in range(tr.st.K) if k != tr.st.anchor]
    assert all(region.contains(c.scales) for c in D.load_configurations(tiny_dataset))  # the dataset's promise

    class Oracle(torch.nn.Module):
        def forward(self, s: torch.Tensor) -> torch.Tensor:
            sbar = np.ones((len(s), tr.st.K))
            sbar[:, free] = ranges[free, 0] + s.double().cpu().numpy() * (ranges[free, 1] - ranges[free, 0])
            actual = sbar * units[tr.st.anchor] / units  # s_k = sbar_k u_anchor / u_k
            full = np.ones((len(s), region.num_objects))
            full[:, [o.id for o in inputs.objects]] = actual
            return torch.where(torch.from_numpy(np.asarray(region.contains(full))), 10.0, -10.0)

    tr.net = Oracle()
    m = ev()
    assert m["iou"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0 and m["scale_rel_err"] == 0.0


def test_monitor_without_a_region_measures_only_the_training_views(tiny_dataset: Path) -> None:
    tr = Trainer(oracle_inputs(tiny_dataset), small_config(), torch.device("cpu"))
    ev = TrainingMonitor(tr, None)
    m = ev()
    assert ev.region is None and np.isfinite(m["psnr"]) and "seg_acc" in m
    assert not {"iou", "precision", "recall", "scale_rel_err"} & set(m)

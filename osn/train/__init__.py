"""Training: per-object fields and the object scale network, jointly (paper section 3.3).

Modules, in reading order:

* :mod:`~osn.train.config`: :class:`TrainConfig` (a run's ``config.yaml``), ``label_stride``.
* :mod:`~osn.train.schedule`: :class:`Phase`, :func:`build_schedule` (stage 1, rounds of
  scale + field phases, a final scale phase).
* :mod:`~osn.train.tensors`: :class:`SceneTensors` (the inputs as device tensors), :func:`pick_device`.
* :mod:`~osn.train.labels`: the scale phase's label pool (per-object depths, contested rays,
  depth-order constraints).
* :mod:`~osn.train.trainer`: :class:`Trainer`, one step of stage 1, a field or a scale phase;
  its checkpointable state.
* :mod:`~osn.train.monitor`: :class:`TrainingMonitor`, what a metrics line measures (PSNR and,
  given the exact region, valid-set accuracy): the only training code that sees ground truth.
* :mod:`~osn.train.checkpoint`: checkpoint writing, :class:`TrainingDiverged`, ``metrics.jsonl``.
* :mod:`~osn.train.loop`: :func:`train`, the run directory and the iteration loop.

``osn train --data DATASET`` (:mod:`osn.cli.train`) loads the exact region and oracle inputs from the
dataset and calls :func:`train`.
"""

from osn.train.checkpoint import TrainingDiverged, read_metrics
from osn.train.auto import label_stride
from osn.train.config import TrainConfig
from osn.train.loop import train
from osn.train.monitor import TrainingMonitor
from osn.train.schedule import Phase, build_schedule
from osn.train.tensors import pick_device
from osn.train.trainer import Trainer

__all__ = ["Phase", "TrainConfig", "Trainer", "TrainingDiverged", "TrainingMonitor", "build_schedule", "label_stride",
           "pick_device", "read_metrics", "train"]

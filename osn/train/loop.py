"""Joint optimisation of the per-object fields and the object scale network (paper section 3.3).

Schedule (global iteration counter, resumable at any iteration; :mod:`osn.train.schedule`):

1. Stage 1, ``stage1_iters``: every object alone in its own unit, RGB + sparse-depth losses on
   its masked pixels (Eq. 2).
2. ``rounds`` alternation rounds, each a *scale phase* then a *field phase*, and a final scale
   phase. A scale phase renders every object's depth once on all training pixels (the soft
   Z-buffer's per-object depths, Eq. 17), then trains the scale network on ``H`` sampled scale
   vectors per step labelled by the depth order they imply (Eq. 11-13, 18) with BCE-with-logits.
   A field phase composites all objects scaled by one valid scale vector per step (score above
   :data:`~osn.model.scale_net.FIELD_STEP_THRESHOLD`; the best candidate with a logged warning
   when none is) with RGB, scaled-depth and segmentation losses (weights 1, 1, 0.01; Eq. 8-10).
   The scale phase comes first in a round so field phases never sample from an untrained
   network (in the paper's order the first field phase would); the final scale phase fits the
   network to the final fields.

A single-object scene has no scale phases and no scale network. Objects absent from a frame
are never evaluated on its rays; no depth loss is used when the inputs carry no sparse depth.

Run directory: ``config.yaml``, ``inputs/`` (the per-object inputs used), ``run.json`` (the
dataset path, provenance only; :mod:`osn.train.environment`'s record of what it trained with,
and ``resumed_on`` for resumes on another kind of processor or torch build), ``checkpoint.pt``
(atomic, every ``eval_every`` iterations and at the end; has every RNG state, so
``--resume`` reproduces an uninterrupted run bit for bit on the same kind of CPU; CUDA's atomic adds make runs agree only up to rounding),
``metrics.jsonl`` (one JSON line per evaluation: wall time, iteration, phase, losses, training
PSNR and, when the caller gives the exact region, the valid-set precision / recall / IoU and the
relative scale-interval error), ``label_pool.json`` (at the end: the final scale phase's rays per
object pair, :func:`osn.train.labels.pool_record`).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from scenecore import dataset as D
from scenecore.lock import output_lock
from scenecore.validity import ValidRegion

from benchgen.score.metrics import psnr_from_mse as psnr
from osn.model.run import read_checkpoint
from osn.preprocess.inputs import SceneInputs, load_inputs, save_inputs
from osn.model.scale_net import FIELD_STEP_THRESHOLD, NonFiniteScores
from osn.train.checkpoint import TrainingDiverged, append_metrics, save_checkpoint, truncate_metrics
from osn.train.config import TrainConfig
from osn.train.environment import describe, environment, same_kernels
from osn.train.labels import POOL_FILE, pool_record
from osn.train.monitor import TrainingMonitor
from osn.train.schedule import Phase
from osn.train.tensors import pick_device
from osn.train.trainer import Trainer

log = logging.getLogger(__name__)


def check_run_directory(out: str | Path, resume: bool) -> None:
    """Refuse to resume a run without a checkpoint, or to start a new one over an existing run."""
    ckpt = Path(out) / "checkpoint.pt"
    if resume and not ckpt.exists():
        raise FileNotFoundError(f"{ckpt}: nothing to resume")
    if not resume and ckpt.exists():
        raise FileExistsError(f"{out} already holds a run; pass --resume to continue it or choose another --out")


def _start_run(out: Path, cfg: TrainConfig, inputs: SceneInputs, dataset: str | Path | None, env: dict[str, Any]) -> None:
    """Write what a new run depends on: its inputs, ``config.yaml`` and ``run.json`` (the dataset
    and what it trains on, :func:`osn.train.environment.environment`)."""
    # A run killed before its first checkpoint may have left metric lines; a fresh start
    # rewrites them, so they must not stay in front of the new curve.
    (out / "metrics.jsonl").unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    save_inputs(out / "inputs", inputs)
    D.atomic_write_bytes(out / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False).encode())
    # Provenance for people and for `osn export` (its test cameras); training never reads it back:
    # what it measures against comes from its caller (``region``).
    D.atomic_write_json(out / "run.json", {"dataset": str(dataset) if dataset else None, "environment": env})


def _record_resume(out: Path, env: dict[str, Any]) -> None:
    """A resume on another kind of processor or torch build continues the run with other
    rounding: ``run.json`` lists it under ``resumed_on`` and a warning says so (a run started
    before runs recorded their environment has nothing to compare with)."""
    path = out / "run.json"
    rec = D.read_json(path) if path.exists() else {}
    if not rec.get("environment"):
        return
    resumed = rec.get("resumed_on", [])
    if not any(same_kernels(e, env) for e in [rec["environment"], *resumed]):
        log.warning("%s: started with %s, resumed with %s: the rest of the run rounds differently "
                    "(not the figures an uninterrupted run would give)", out, describe(rec["environment"]), describe(env))
        D.atomic_write_json(path, {**rec, "resumed_on": [*resumed, env]})


def _metrics_record(trainer: Trainer, phase: Phase, monitor: TrainingMonitor) -> dict[str, Any]:
    """One metrics line: the losses averaged since the last line, then the monitor's measurements."""
    acc = trainer.loss_acc
    rec: dict[str, Any] = {"iteration": trainer.iteration, "wall_time": round(trainer.elapsed, 3),
                           "phase": phase.name, "round": phase.round}
    rec.update({key: float(np.mean(v)) for key, v in acc.items()})
    if "rgb" in acc:
        rec["train_batch_psnr"] = psnr(rec["rgb"])
    if phase.name == "scale" and trainer.cache is not None:  # the pool's measured room bias per object
        rec["anchor_bias"] = [round(float(b), 5) for b in trainer.cache["anchor_bias"]]
    rec.update(monitor())
    rec["fallbacks"] = trainer.fallbacks
    acc.clear()
    return rec


def _iterate(trainer: Trainer, monitor: TrainingMonitor, out: Path, stop: int, progress: bool) -> None:
    """Step until global iteration ``stop``, writing metric lines and checkpoints on the way."""
    from tqdm import tqdm

    cfg = trainer.cfg
    metrics_path, ckpt = out / "metrics.jsonl", out / "checkpoint.pt"
    bar = tqdm(total=trainer.total, initial=trainer.iteration, desc="osn train", disable=not progress, dynamic_ncols=True)
    t_start = time.perf_counter() - trainer.elapsed
    while trainer.iteration < stop:
        ph = trainer.phase(trainer.iteration)
        try:
            losses = trainer.step()
        except NonFiniteScores as e:  # the scale network's weights are NaN: same one line as a NaN loss
            raise TrainingDiverged.at(out, trainer.iteration, ph, str(e)) from None
        bad = sorted(k for k, v in losses.items() if not math.isfinite(v))
        if bad:  # stop before a NaN reaches a checkpoint; the last good one stays resumable
            raise TrainingDiverged.at(out, trainer.iteration, ph, f"loss {', '.join(bad)} is {losses[bad[0]]}")
        for key, v in losses.items():
            trainer.loss_acc.setdefault(key, []).append(v)
        it = trainer.iteration
        trainer.elapsed = time.perf_counter() - t_start
        if it % cfg.eval_every == 0 or it == ph.end or it == trainer.total:
            rec = _metrics_record(trainer, ph, monitor)
            append_metrics(metrics_path, rec)
            bar.set_postfix(phase=ph.name, psnr=f"{rec['psnr']:.2f}", iou=f"{rec.get('iou', float('nan')):.3f}")
        if it % cfg.eval_every == 0 or it == stop:
            bad_params = trainer.non_finite_parameters()
            if bad_params:  # an update can blow the weights up while the step's loss was finite
                raise TrainingDiverged.at(out, it, ph, f"non-finite weights in {', '.join(bad_params)}")
            save_checkpoint(ckpt, trainer)
        bar.update(1)
    bar.close()


def train(
    out: str | Path,
    cfg: TrainConfig | None = None,
    *,
    inputs: SceneInputs | None = None,
    region: ValidRegion | None = None,
    dataset: str | Path | None = None,
    resume: bool = False,
    max_iterations: int | None = None,
    progress: bool = True,
) -> Path:
    """Train OSN on per-object ``inputs`` into run directory ``out``; returns ``out``.

    Args:
        out: the run directory (see the module docstring).
        cfg: the training config of a new run (default: the CPU default).
        inputs: the per-object inputs of a new run (required unless ``resume``).
        region: the dataset's exact valid region, or None: only the metric lines use it
            (valid-set precision / recall / IoU); pass it again on ``resume``.
        dataset: the dataset path, recorded in ``run.json`` as provenance only.
        resume: continue from ``out/checkpoint.pt`` with the run's own config and inputs.
        max_iterations: stop after that global iteration (with a checkpoint), as an
            interruption would.
        progress: show a progress bar.
    """
    out = Path(out)
    with output_lock(out):  # one writer per run: metrics, config and checkpoint from one run only
        check_run_directory(out, resume)
        if resume:
            cfg = TrainConfig.from_yaml(out / "config.yaml", run_config=True)
            inputs = load_inputs(out / "inputs")
        else:
            if inputs is None:
                raise ValueError(f"{out}: a new run needs its per-object inputs (oracle or preprocessed)")
            cfg = cfg or TrainConfig()
        device = pick_device(cfg.device)
        env = environment(device)
        if resume:
            _record_resume(out, env)
        else:
            _start_run(out, cfg, inputs, dataset, env)
        trainer = Trainer(inputs, cfg, device)
        if resume:
            # Read onto the CPU: load_state_dict moves weights and optimiser state to the device
            # itself, and the RNG states it restores must stay on the CPU (a CUDA resume crashed).
            trainer.load_state_dict(read_checkpoint(out / "checkpoint.pt", "cpu"))
            truncate_metrics(out / "metrics.jsonl", trainer.iteration)
        monitor = TrainingMonitor(trainer, region)
        stop = min(trainer.total, max_iterations) if max_iterations is not None else trainer.total
        _iterate(trainer, monitor, out, stop, progress)
        if trainer.iteration == trainer.total:
            _write_pool_record(trainer, out, inputs)
    if trainer.fallbacks:
        log.warning("%d field steps used a fallback scale vector (no candidate above %.2f)", trainer.fallbacks, FIELD_STEP_THRESHOLD)
    return out


def _write_pool_record(trainer: Trainer, out: Path, inputs: SceneInputs) -> bool:
    """``out/label_pool.json`` from a finished trainer's final scale phase (its pool rebuilt, as a
    resumed phase rebuilds it: the same fields give the same pool); False without scale phases."""
    final = trainer.schedule[-1] if trainer.schedule else None
    if final is None or final.name != "scale":
        return False
    trainer.ensure_cache(final)
    D.atomic_write_json(out / POOL_FILE, pool_record(trainer.cache, [o.id for o in inputs.objects]))
    return True


def record_final_pool(run_dir: str | Path) -> bool:
    """Write the ``label_pool.json`` of a finished run trained before training wrote it, from its
    checkpoint and inputs; False for a run without scale phases (one object). Raises
    ``ValueError`` naming the run when it has not finished training."""
    out = Path(run_dir)
    with output_lock(out):
        cfg = TrainConfig.from_yaml(out / "config.yaml", run_config=True)
        inputs = load_inputs(out / "inputs")
        trainer = Trainer(inputs, cfg, pick_device(cfg.device))
        trainer.load_state_dict(read_checkpoint(out / "checkpoint.pt", "cpu"))
        if trainer.iteration != trainer.total:
            raise ValueError(f"{out}: training stopped at iteration {trainer.iteration} of {trainer.total}; "
                             "its final label pool does not exist yet")
        return _write_pool_record(trainer, out, inputs)


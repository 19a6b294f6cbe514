"""``osn train [DATASET] --out RUN [--config FILE] [--inputs DIR] [--resume]``.

The dataset is read here, not by training: its exact valid region goes to the training monitor
(the valid-set metrics), and its ground truth gives the oracle inputs when ``--inputs`` is not given.
A user's own video has no dataset: ``osn train --inputs DIR`` trains on ``osn preprocess``'s output
and measures nothing against ground truth.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from scenecore.cli import UserError, subcommand
from scenecore.dataset import load_valid_region, read_json
from scenecore.lock import output_lock
from scenecore.validity import ValidRegion

from osn.preprocess.inputs import SceneInputs, load_inputs
from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, read_metrics, train
from osn.train.loop import check_run_directory


def dataset_region(dataset: str | Path | None) -> ValidRegion | None:
    """The dataset's exact valid region, or None when it has none (no ``valid_region.json``)."""
    if dataset is None or not (Path(dataset) / "valid_region.json").exists():
        return None
    return load_valid_region(dataset)


def _refuse_silent_monitor_loss(out: Path) -> None:
    """A run started against a dataset and resumed without it would stop measuring its valid set
    halfway through ``metrics.jsonl``; ask for the dataset instead."""
    try:
        started = read_json(out / "run.json").get("dataset")
    except (ValueError, AttributeError):
        return  # no provenance to go by (an older or hand-made run)
    if started:
        raise UserError(f"{out}: this run was started against the dataset {started} (run.json) and measures its valid "
                        f"set there; pass it again: osn train {started} --out {out} --resume")


def train_on_dataset(
    dataset: str | Path | None,
    out: str | Path,
    cfg: TrainConfig | None = None,
    *,
    inputs: SceneInputs | None = None,
    resume: bool = False,
    max_iterations: int | None = None,
    progress: bool = True,
) -> Path:
    """What ``osn train DATASET`` runs: :func:`osn.train.train` measured against the dataset's
    exact region, on ``inputs`` or (a new run without them) the dataset's oracle inputs.
    A resumed run keeps its own config and inputs; the region is read again from ``dataset``.
    Without a dataset (a user's video) ``inputs`` are required and no region is measured."""
    if dataset is None and inputs is None and not resume:
        raise UserError(f"{out}: give a benchgen DATASET or --inputs DIR (from `osn preprocess`)")
    with output_lock(out):  # from the run's checks to its end (train() takes it again, nested)
        check_run_directory(out, resume)  # before the oracle inputs cost anything
        if resume and dataset is None:
            _refuse_silent_monitor_loss(Path(out))
        region = dataset_region(dataset)
        if not resume and inputs is None:
            inputs = oracle_inputs(dataset)
        return train(out, cfg, inputs=inputs, region=region, dataset=dataset, resume=resume,
                     max_iterations=max_iterations, progress=progress)


def _cmd_train(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.resume and (args.config or args.inputs):
        # A resumed run keeps the config and inputs it started with (saved in --out).
        raise UserError(f"{args.out}: --resume continues with the run's own config.yaml and inputs; drop --config/--inputs")
    cfg = TrainConfig.from_yaml(args.config) if args.config else None
    inputs = load_inputs(args.inputs) if args.inputs else None
    run = train_on_dataset(args.dataset, args.out, cfg, inputs=inputs, resume=args.resume, max_iterations=args.max_iterations)
    records = read_metrics(Path(run) / "metrics.jsonl")
    if records:
        rec = records[-1]
        summary = {k: rec[k] for k in ("iteration", "wall_time", "psnr", "iou", "precision", "recall", "scale_rel_err") if k in rec}
        print(json.dumps(summary))
    return 0


def add_train_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``osn train [DATASET] --out RUN [--config FILE] [--inputs DIR] [--resume]``."""
    p = subcommand(sub, "train", _cmd_train, "train per-object fields and the object scale network on a dataset or on "
                   "preprocessed inputs")
    p.set_defaults(resume_hint="run the same command with --resume to continue")
    p.add_argument("dataset", nargs="?", default=None,
                   help="benchgen dataset directory (oracle per-object inputs are derived from it; its valid_region.json, "
                   "when present, measures the learned valid set); leave it out for your own video and pass --inputs")
    p.add_argument("--out", required=True, help="run directory (checkpoint, metrics.jsonl, config, inputs)")
    p.add_argument("--config", help="YAML training config; omitted keys take the CPU defaults (configs/osn-cpu.yaml)")
    p.add_argument("--inputs", help="per-object inputs directory from `osn preprocess` (or `osn oracle`); "
                   "default: oracle inputs derived from DATASET's ground truth")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint, with the config and inputs it started with")
    p.add_argument("--max-iterations", type=int, default=None, help="stop after this global iteration (resumable)")

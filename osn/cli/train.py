"""``osn train [--data DATASET] --out RUN [--config FILE] [--inputs DIR] [--resume]``.

The dataset is read here, not by training: its exact valid region goes to the training monitor
(the valid-set metrics), and its ground truth gives the oracle inputs when ``--inputs`` is not given.
A user's own video has no dataset: ``osn train --inputs DIR`` trains on ``osn preprocess``'s output
and measures nothing against ground truth.
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import replace
from pathlib import Path

from scenecore.cli import UserError, deprecated_alias, subcommand
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
                        f"set there; pass it again: osn train --data {started} --out {out} --resume")


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
    """What ``osn train --data DATASET`` runs: :func:`osn.train.train` measured against the dataset's
    exact region, on ``inputs`` or (a new run without them) the dataset's oracle inputs.
    A resumed run keeps its own config and inputs; the region is read again from ``dataset``.
    Without a dataset (a user's video) ``inputs`` are required and no region is measured."""
    if dataset is None and inputs is None and not resume:
        raise UserError(f"{out}: give a benchgen dataset (--data DATASET) or --inputs DIR (from `osn preprocess`)")
    with output_lock(out):  # from the run's checks to its end (train() takes it again, nested)
        check_run_directory(out, resume)  # before the oracle inputs cost anything
        if resume and dataset is None:
            _refuse_silent_monitor_loss(Path(out))
        region = dataset_region(dataset)
        if not resume and inputs is None:
            inputs = oracle_inputs(dataset)
        return train(out, cfg, inputs=inputs, region=region, dataset=dataset, resume=resume,
                     max_iterations=max_iterations, progress=progress)


def training_config(config_file: str | Path | None = None, field_iterations: int | None = None,
                    seed: int | None = None) -> TrainConfig:
    """A new run's training config, as ``osn train`` and ``osn demo`` build it: ``config_file``
    (omitted keys: the CPU defaults), every phase length scaled so that the field iterations
    (stage 1 + every round) total ``field_iterations``, and ``seed`` over the file's."""
    if field_iterations is not None and field_iterations < 1:
        raise UserError(f"--field-iterations must be >= 1, got {field_iterations}")
    cfg = TrainConfig.from_yaml(config_file) if config_file else TrainConfig()
    if field_iterations:
        total = cfg.stage1_iters + cfg.rounds * cfg.field_iters
        f = field_iterations / max(total, 1)
        cfg = replace(
            cfg,
            stage1_iters=max(1, round(cfg.stage1_iters * f)),
            field_iters=max(1, round(cfg.field_iters * f)),
            scale_iters=max(1, round(cfg.scale_iters * f)),
            final_scale_iters=max(1, round(cfg.final_scale_iters * f)),
        )
    return cfg if seed is None else replace(cfg, seed=seed)


def _cmd_train(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    new_run = {"--config": args.config, "--inputs": args.inputs, "--field-iterations": args.field_iterations,
               "--seed": args.seed}
    given = [k for k, v in new_run.items() if v is not None]
    if args.resume and given:
        # A resumed run keeps the config and inputs it started with (saved in --out).
        raise UserError(f"{args.out}: --resume continues with the run's own config.yaml and inputs; drop {'/'.join(given)}")
    cfg = None if args.resume else training_config(args.config, args.field_iterations, args.seed)
    inputs = load_inputs(args.inputs) if args.inputs else None
    run = train_on_dataset(args.data, args.out, cfg, inputs=inputs, resume=args.resume, max_iterations=args.max_iterations)
    records = read_metrics(Path(run) / "metrics.jsonl")
    if records:
        rec = records[-1]
        summary = {k: rec[k] for k in ("iteration", "wall_time", "psnr", "iou", "precision", "recall", "scale_rel_err") if k in rec}
        print(json.dumps(summary))
    return 0


def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config`` and ``--field-iterations``, as ``osn train`` and ``osn demo`` both take them
    (:func:`training_config`)."""
    p.add_argument("--config", help="YAML training config; omitted keys take the CPU defaults (configs/osn-cpu.yaml)")
    p.add_argument("--field-iterations", type=int, default=None,
                   help="scale every phase of the config's schedule so that the field iterations (stage 1 + every "
                   "round) total this many (default: the config's schedule)")


def add_train_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``osn train [--data DATASET] --out RUN [--config FILE] [--inputs DIR] [--resume]``."""
    p = subcommand(sub, "train", _cmd_train, "train per-object fields and the object scale network on a dataset or on "
                   "preprocessed inputs")
    p.set_defaults(resume_hint="run the same command with --resume to continue")
    p.add_argument("--data", metavar="DATASET",
                   help="benchgen dataset directory (oracle per-object inputs are derived from it; its valid_region.json, "
                   "when present, measures the learned valid set); leave it out for your own video and pass --inputs")
    p.add_argument("--out", required=True, help="run directory (checkpoint, metrics.jsonl, config, inputs)")
    add_config_options(p)
    p.add_argument("--inputs", help="per-object inputs directory from `osn preprocess` (or `osn oracle`); "
                   "default: oracle inputs derived from DATASET's ground truth")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint, with the config and inputs it started with")
    p.add_argument("--max-iterations", type=int, default=None, help="stop after this global iteration (resumable)")
    p.add_argument("--seed", type=int, default=None, help="training seed (default: the config's seed)")
    deprecated_alias(p, "dataset", "--data DATASET", nargs="?", metavar="DATASET")

"""Learned valid set against training time: the valid-set options side by side, on several scenes.

    python benchmarks/bench_iou.py DATASET [DATASET ...] --work DIR [--variants before,after]
                                   [--seeds 0,1,2] [--inputs INPUTS] [--quiet] [key=value ...]

Trains ``osn train`` runs on each ``DATASET`` (a benchgen dataset with ``valid_region.json``;
oracle inputs unless ``--inputs`` gives `osn preprocess` ones, for a single dataset) into
``DIR/<dataset>/<variant>``, one after the other, prints every metrics line (iteration, wall time,
phase, round, PSNR, valid-set IoU / precision / recall) unless ``--quiet``, and one summary table
of all runs at the end (final and best IoU, PSNR, wall time). With ``--seeds`` every variant is
trained once per seed (``DIR/<dataset>/<variant>-seed<N>``) and the table adds each variant's
mean and standard deviation over the seeds: one run's IoU moves with the seed alone by more
than most options move it (docs/experiments/). Variants (overrides of
``configs/osn-cpu.yaml``; docs/training.md explains each option):

* ``before``: a constant scale learning rate (``scale_lr_final: 1``), no stage-1 terms in field
  phases (``w_alone: 0``), every object pair kept (``pair_minority: 0``), the final scale phase
  like the others (``final_label_trim: 0.01``, ``final_scale_iters: 300``);
* ``after``: the config's own values (``w_alone: 1``, ``scale_lr_final: 0.1``,
  ``pair_minority: 0.2``, a final scale phase of 2000 steps on labels trimmed by
  ``final_label_trim: 0.002``);
* ``loose-final``: ``after`` with the final scale phase like the others (``final_label_trim:
  0.01``, ``final_scale_iters: 300``);
* ``no-minority``, ``no-alone``: ``after`` without one option.

``key=value`` override every variant's config (e.g. ``rounds=2``). Runs that already finished in
``DIR`` are read, not retrained. Set ``OMP_NUM_THREADS`` (1-2 on the shared CPU machine).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

from osn.cli.train import dataset_region
from osn.model.run import read_checkpoint
from osn.preprocess.inputs import load_inputs
from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, Trainer, TrainingMonitor, build_schedule, train

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import print_command  # noqa: E402

AFTER: dict = {}
LOOSE_FINAL = {"final_label_trim": 0.01, "final_scale_iters": 300}
VARIANTS = {
    "before": {"w_alone": 0.0, "scale_lr_final": 1.0, "pair_minority": 0.0, **LOOSE_FINAL},
    "after": AFTER,
    "loose-final": LOOSE_FINAL,
    "no-minority": {"pair_minority": 0.0},
    "no-alone": {"w_alone": 0.0},
}


def _value(v: str):
    return yaml.safe_load(v)


def run_variant(dataset: str, name: str, base: dict, inputs_dir: str | None, work: Path, quiet: bool,
                seed: int | None = None) -> tuple:
    """Train (or read) one variant on one dataset (with ``seed``: that seed, in its own directory);
    print its curve; return its summary row."""
    region = dataset_region(dataset)
    cfg = TrainConfig.from_dict({**base, **VARIANTS[name], **({} if seed is None else {"seed": seed})})
    label = name if seed is None else f"{name}-seed{seed}"
    out = work / Path(dataset).name / label
    metrics = out / "metrics.jsonl"
    inputs = load_inputs(inputs_dir) if inputs_dir else oracle_inputs(dataset)
    total = build_schedule(cfg, inputs.num_objects)[-1].end
    done = metrics.exists() and any(json.loads(l)["iteration"] == total for l in metrics.read_text().splitlines())
    if done and TrainConfig.from_yaml(out / "config.yaml", run_config=True) != cfg:
        raise SystemExit(f"{out} holds a run of another config (the defaults changed?); remove it or pick another --work")
    if not done:
        if out.exists():
            raise SystemExit(f"{out} holds an unfinished run; remove it or pick another --work")
        train(out, cfg, inputs=inputs, region=region, dataset=dataset, progress=False)
    rows = [json.loads(l) for l in metrics.read_text().splitlines()]
    if not quiet:
        print(f"\n{Path(dataset).name} / {label}: " + (", ".join(f"{k}={v}" for k, v in VARIANTS[name].items()) or "defaults"))
        print(f"{'iter':>5} {'wall s':>7} {'phase':>7} {'rnd':>3} {'PSNR':>6} {'IoU':>6} {'prec':>6} {'recall':>6}")
        for r in rows:
            print(f"{r['iteration']:5d} {r['wall_time']:7.1f} {r['phase']:>7} {r['round']:3d} {r['psnr']:6.2f} "
                  f"{r.get('iou', float('nan')):6.3f} {r.get('precision', float('nan')):6.3f} {r.get('recall', float('nan')):6.3f}", flush=True)
    last = rows[-1]
    final = final_accuracy(out, region)  # the current monitor on the final weights (stratified points)
    return (Path(dataset).name, label, last["wall_time"], last["psnr"], final.get("iou", float("nan")),
            final.get("precision", float("nan")), final.get("recall", float("nan")), max(r.get("iou", 0.0) for r in rows))


def final_accuracy(run: Path, region) -> dict:
    """The training monitor's valid-set accuracy of the run's last checkpoint, measured now on its
    stratified points: a run's own log may hold a uniform-sample IoU, which is 0 for regions of
    1e-6 of the box."""
    cfg = TrainConfig.from_yaml(run / "config.yaml", run_config=True)
    tr = Trainer(load_inputs(run / "inputs"), cfg, torch.device("cpu"))
    tr.load_state_dict(read_checkpoint(run / "checkpoint.pt"))
    return TrainingMonitor(tr, region)()


#: Number formats of the table's value columns: train s, PSNR, final IoU, precision, recall, best IoU.
COLUMN_FORMATS = (".0f", ".2f", ".3f", ".3f", ".3f", ".3f")


def _cell(value: float | tuple[float, float], fmt: str) -> str:
    """One run's value, or ``(mean, sd)`` over seeds as ``mean +- sd``."""
    if isinstance(value, tuple):
        return f"{value[0]:{fmt}} +- {value[1]:{fmt}}"
    return f"{value:{fmt}}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", nargs="+", help="benchgen datasets with valid_region.json")
    ap.add_argument("--work", required=True, help="directory of the runs (DIR/<dataset>/<variant>)")
    ap.add_argument("--variants", default="before,after", help=f"comma-separated, of {','.join(VARIANTS)}")
    ap.add_argument("--seeds", default=None, help="comma-separated seeds: each variant once per seed, with mean and "
                    "standard deviation (default: the config's seed, one run)")
    ap.add_argument("--inputs", default=None, help="per-object inputs (osn preprocess) of a single dataset; default: oracle")
    ap.add_argument("--quiet", action="store_true", help="only the summary table")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides for every variant")
    args = ap.parse_intermixed_args()  # key=value may also follow the options
    overrides = [d for d in args.datasets if "=" in d] + args.overrides  # argparse puts key=value with the datasets
    datasets = [d for d in args.datasets if "=" not in d]
    if args.inputs and len(datasets) > 1:
        ap.error("--inputs belongs to one dataset")
    print_command()
    logging.basicConfig(level=logging.WARNING)
    base = TrainConfig.from_yaml(Path(__file__).resolve().parents[1] / "configs" / "osn-cpu.yaml").to_dict()
    base.update({k: _value(v) for k, v in (o.split("=", 1) for o in overrides)})
    seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [None]
    print("\n| dataset | variant | train s | PSNR | final IoU | precision | recall | best IoU logged |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for d in datasets:
        for name in args.variants.split(","):
            runs = [run_variant(d, name, base, args.inputs, Path(args.work), args.quiet, seed) for seed in seeds]
            rows += runs
            if len(runs) > 1:
                cols = np.array([r[2:] for r in runs], dtype=np.float64)
                mean, sd = cols.mean(0), cols.std(0, ddof=1)
                rows.append((runs[0][0], f"{name}, mean +- sd of {len(runs)} seeds", *zip(mean, sd)))
    for d, name, *values in rows:
        print(f"| {d} | {name} | " + " | ".join(_cell(v, f) for v, f in zip(values, COLUMN_FORMATS)) + " |")


if __name__ == "__main__":
    main()

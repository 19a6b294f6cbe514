"""Learned valid set against training time, before / after the label and field-phase fixes.

    python benchmarks/bench_iou.py DATASET --work DIR [--variants before,after] [--inputs INPUTS]
                                   [--rounds N] [key=value ...]

Trains ``osn train`` runs on ``DATASET`` (a benchgen dataset with ``valid_region.json``; oracle
inputs unless ``--inputs`` gives `osn preprocess` ones) into ``DIR/<variant>``, one after the
other, and prints every metrics line (iteration, wall time, phase, round, PSNR, valid-set IoU /
precision / recall) and a last-line summary per variant. Variants (overrides of the CPU default):

* ``before``: the CPU defaults: ``label_trim: 0.01``, constant scale learning rate
  (``scale_lr_final: 1``), no stage-1 terms in field phases (``w_alone: 0``);
* ``trim``: only ``label_trim: 0.003`` and the scale learning-rate decay (``w_alone: 0``);
* ``after``: ``label_trim: 0.003``, ``scale_lr_final: 0.1``, ``w_alone: 1`` (best at 64 px);
* ``after-trim01``: the same with ``label_trim: 0.01`` (best at 128 px).

``key=value`` override every variant's config (e.g. ``rounds=2``). Runs that already finished in
``DIR`` are read, not retrained. Set ``OMP_NUM_THREADS`` (1-2 on the shared CPU machine).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import yaml

from osn.cli.train import dataset_region
from osn.preprocess.inputs import load_inputs
from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, build_schedule, train

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import print_command  # noqa: E402

VARIANTS = {
    "before": {"label_trim": 0.01, "scale_lr_final": 1.0, "w_alone": 0.0},
    "trim": {"label_trim": 0.003, "scale_lr_final": 0.1, "w_alone": 0.0},
    "after": {"label_trim": 0.003, "scale_lr_final": 0.1, "w_alone": 1.0},
    "after-trim01": {"label_trim": 0.01, "scale_lr_final": 0.1, "w_alone": 1.0},
}


def _value(v: str):
    return yaml.safe_load(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--work", required=True, help="directory of the runs (DIR/<variant>)")
    ap.add_argument("--variants", default="before,after", help=f"comma-separated, of {','.join(VARIANTS)}")
    ap.add_argument("--inputs", default=None, help="per-object inputs (osn preprocess); default: oracle")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides for every variant")
    args = ap.parse_args()
    print_command()
    logging.basicConfig(level=logging.WARNING)
    base = TrainConfig.from_yaml(Path(__file__).resolve().parents[1] / "configs" / "osn-cpu.yaml").to_dict()
    base.update({k: _value(v) for k, v in (o.split("=", 1) for o in args.overrides)})
    region = dataset_region(args.dataset)
    inputs = load_inputs(args.inputs) if args.inputs else oracle_inputs(args.dataset)
    summary = []
    for name in args.variants.split(","):
        cfg = TrainConfig.from_dict({**base, **VARIANTS[name]})
        out = Path(args.work) / name
        metrics = out / "metrics.jsonl"
        total = build_schedule(cfg, inputs.num_objects)[-1].end
        done = metrics.exists() and any(json.loads(l)["iteration"] == total for l in metrics.read_text().splitlines())
        if not done:
            if out.exists():
                raise SystemExit(f"{out} holds an unfinished run; remove it or pick another --work")
            train(out, cfg, inputs=inputs, region=region, dataset=args.dataset, progress=False)
        rows = [json.loads(l) for l in metrics.read_text().splitlines()]
        print(f"\n{name}: " + ", ".join(f"{k}={v}" for k, v in VARIANTS[name].items()) or name)
        print(f"{'iter':>5} {'wall s':>7} {'phase':>7} {'rnd':>3} {'PSNR':>6} {'IoU':>6} {'prec':>6} {'recall':>6}")
        for r in rows:
            print(f"{r['iteration']:5d} {r['wall_time']:7.1f} {r['phase']:>7} {r['round']:3d} {r['psnr']:6.2f} "
                  f"{r.get('iou', float('nan')):6.3f} {r.get('precision', float('nan')):6.3f} {r.get('recall', float('nan')):6.3f}")
        last = rows[-1]
        summary.append((name, last["wall_time"], last["psnr"], last.get("iou"), last.get("precision"), last.get("recall"),
                        max(r.get("iou", 0.0) for r in rows)))
    print("\nvariant   wall s   PSNR    IoU   prec  recall  best IoU")
    for name, w, p, i, pr, rc, best in summary:
        print(f"{name:8s} {w:7.1f} {p:6.2f} {i:6.3f} {pr:6.3f} {rc:6.3f} {best:8.3f}")


if __name__ == "__main__":
    main()

"""Which pair bounds limit trained runs' valid sets, one row per run (a seed study in one table).

    python benchmarks/bench_valid_limits.py RUN [RUN ...] [--data DATASET] [--points N]

Each ``RUN`` is an ``osn train`` run directory; its dataset (with ``valid_region.json``) is the one
``run.json`` names unless ``--data`` gives it. Prints per run the learned valid set's IoU,
precision and recall against the exact region and, per pair bound ``s_i / s_j < B_ij`` of the
region, the share of the region the set misses there (too tight) and its volume past it (too
loose), both in units of the region's volume: ``osn evaluate``'s estimator
(:func:`osn.evaluate.valid_set.valid_set_accuracy`, ``--points`` per stratum, seed 0) without
rendering anything, seconds per run. Where IoU moves between seeds, the pair columns say which
bound moved and in which direction (docs/experiments/).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchutil import print_command

from osn.cli.train import dataset_region
from osn.evaluate.valid_set import valid_set_accuracy
from osn.model.run import load_run
from scenecore.dataset import read_json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="osn train run directories (the same dataset)")
    ap.add_argument("--data", help="the dataset the runs were trained on (default: the one in each run.json)")
    ap.add_argument("--points", type=int, default=100_000, help="Monte-Carlo points per stratum")
    args = ap.parse_args()
    print_command()
    rows, pairs = [], []
    for run_dir in args.runs:
        meta = Path(run_dir) / "run.json"
        data = args.data or (read_json(meta).get("dataset") if meta.exists() else None)
        region = dataset_region(data)
        if region is None:
            raise SystemExit(f"{run_dir}: no dataset with valid_region.json (give it with --data)")
        acc = valid_set_accuracy(load_run(run_dir), region, points=args.points)
        by_pair = {e["pair"]: e for e in acc["limits"]}
        pairs += [p for p in by_pair if p not in pairs]
        rows.append((run_dir, acc, by_pair))
    print("| run | IoU (P / R) | " + " | ".join(f"{p}: missed / excess" for p in pairs) + " |")
    print("|---|---|" + "---|" * len(pairs))
    for run_dir, acc, by_pair in rows:
        cells = [f"{by_pair[p]['missed']:.3f} / {by_pair[p]['excess']:.3f}" if p in by_pair else "-" for p in pairs]
        print(f"| {run_dir} | {acc['iou']:.3f} ({acc['precision']:.3f} / {acc['recall']:.3f}) | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()

"""Which pair bounds limit trained runs' valid sets, one row per run (a seed study in one table).

    python benchmarks/bench_valid_limits.py RUN [RUN ...] [--data DATASET] [--points N]
    python benchmarks/bench_valid_limits.py RUN [RUN ...] --largest 3 [--pool] [--out JSON]

Each ``RUN`` is an ``osn train`` run directory; its dataset (with ``valid_region.json``) is the one
``run.json`` names unless ``--data`` gives it. Prints per run the learned valid set's IoU,
precision and recall against the exact region and, per pair bound ``s_i / s_j < B_ij`` of the
region, the share of the region the set misses there (too tight) and its volume past it (too
loose), both in units of the region's volume: ``osn evaluate``'s estimator
(:func:`osn.evaluate.valid_set.valid_set_accuracy`, ``--points`` per stratum, seed 0) without
rendering anything, seconds per run. Where IoU moves between seeds, the pair columns say which
bound moved and in which direction (docs/experiments/).

With ``--largest K`` (runs of any datasets) each row is instead a run's K bounds cut most and K
overreached most, each with the final label pool's rays of that pair (``label_pool.json``:
0 means nothing in training could set that bound; ``--pool`` first writes the record of a run
trained before training wrote it, from its checkpoint). ``--out`` writes that table as JSON.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchutil import command_line, print_command, print_tables

from results_json import table, write_results

from osn.cli.train import dataset_region
from osn.evaluate.valid_set import valid_set_accuracy
from osn.model.run import load_run
from osn.train.labels import POOL_FILE
from osn.train.loop import record_final_pool
from scenecore.dataset import load_scene, read_json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="osn train run directories (the same dataset)")
    ap.add_argument("--data", help="the dataset the runs were trained on (default: the one in each run.json)")
    ap.add_argument("--points", type=int, default=100_000, help="Monte-Carlo points per stratum")
    ap.add_argument("--largest", type=int, default=0, metavar="K",
                    help="per run, its K bounds cut most and K overreached most, with their label rays (any datasets)")
    ap.add_argument("--pool", action="store_true",
                    help="write label_pool.json into finished runs trained without it (from their checkpoints)")
    ap.add_argument("--out", type=Path, default=None, help="results JSON of the --largest table")
    args = ap.parse_args()
    print_command()
    rows, pairs = [], []
    for run_dir in args.runs:
        meta = Path(run_dir) / "run.json"
        data = args.data or (read_json(meta).get("dataset") if meta.exists() else None)
        region = dataset_region(data)
        if region is None:
            raise SystemExit(f"{run_dir}: no dataset with valid_region.json (give it with --data)")
        if args.pool and not (Path(run_dir) / POOL_FILE).exists():
            record_final_pool(run_dir)
        names = {o.id: o.name for o in load_scene(data).objects}
        acc = valid_set_accuracy(load_run(run_dir), region, points=args.points, names=names)
        by_pair = {e["pair"]: e for e in acc["limits"]}
        pairs += [p for p in by_pair if p not in pairs]
        rows.append((run_dir, acc, by_pair))
    if args.largest:
        largest(rows, args.largest, args.out)
        return
    print("| run | IoU (P / R) | " + " | ".join(f"{p}: missed / excess" for p in pairs) + " |")
    print("|---|---|" + "---|" * len(pairs))
    for run_dir, acc, by_pair in rows:
        cells = [f"{by_pair[p]['missed']:.3f} / {by_pair[p]['excess']:.3f}" if p in by_pair else "-" for p in pairs]
        print(f"| {run_dir} | {acc['iou']:.3f} ({acc['precision']:.3f} / {acc['recall']:.3f}) | " + " | ".join(cells) + " |")


def largest(rows: list, k: int, out: Path | None) -> None:
    """Per run its ``k`` bounds cut most and ``k`` overreached most (over 1% of the region), each
    ``pair share (label rays)``; printed, and written to ``out``."""
    def rays(e: dict) -> str:
        return f"{e['pool_rays']}{', a minority' if e['pool_minority'] else ''}" if "pool_rays" in e else "?"

    def cells(limits: list[dict], key: str, fmt: str) -> str:
        worst = sorted((e for e in limits if e[key] > 0.01), key=lambda e: -e[key])[:k]
        return "; ".join(f"{e['pair']} {fmt.format(e[key])} ({rays(e)})" for e in worst) or "-"

    columns = ["run", "IoU (P / R)", "cut most: share of the region missed (label rays)",
               "overreached most: volume past it / the region's (label rays)"]
    body = [[str(run_dir), f"{acc['iou']:.3f} ({acc['precision']:.3f} / {acc['recall']:.3f})",
             cells(acc["limits"], "missed", "{:.1%}"), cells(acc["limits"], "excess", "{:.3f}")] for run_dir, acc, _ in rows]
    tables = {"valid_limits_largest": table(columns, body)}
    print_tables(tables)
    if out is not None:
        write_results(out, "valid_limits", command_line(), tables,
                      {"runs": [{"run": str(run_dir), **{x: acc[x] for x in ("iou", "precision", "recall", "limits")}}
                                for run_dir, acc, _ in rows]}, Path(__file__).resolve().parents[1])
        print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""The default demo's results, as README shows them: ``make demo`` timed end to end, its table.

Run on a fresh clone (the figure README quotes is what a new user gets)::

    python3 benchmarks/bench_demo.py --out benchmarks/results/demo.json          # runs `make demo`
    python3 benchmarks/bench_demo.py --work runs/demo --out /tmp/demo.json       # a finished demo, not timed

Standard library only, so that it can start ``make demo`` before the virtual environment exists.
Writes one results JSON (:mod:`benchmarks.results_json`'s layout): the command, the commit, the
machine, the time, the wall seconds from ``make demo`` to its table (set-up included), each
stage's seconds, and the demo's results table with the valid set's accuracy. ``scripts/docs_generate.py``
renders its tables into README.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import print_command  # noqa: E402
from results_json import table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

#: Columns of the demo's table: metrics.json key, header, digits (as ``osn evaluate``'s report).
COLUMNS = [("psnr", "PSNR ↑", 2), ("ssim", "SSIM ↑", 3), ("lpips", "LPIPS ↓", 3), ("ssimae", "SSIMAE ↓", 3),
           ("pq", "PQ ↑", 1), ("miou", "mIoU ↑", 1)]


def _mean_std(ms: list[float], digits: int) -> str:
    """``metrics.json``'s ``[mean, std]`` over the ground truths, as the report prints it."""
    mean, std = ms
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def demo_tables(work: Path) -> tuple[dict, dict]:
    """``(tables, data)`` of a finished demo under ``work``: the results table and the valid set."""
    metrics = json.loads((work / "report" / "metrics.json").read_text())
    stages = json.loads((work / "stages.json").read_text())
    rows = []
    for name, row in metrics["table"].items():
        rows.append([name] + [_mean_std(row[k], d) if k in row else "" for k, _, d in COLUMNS])
    v = metrics["valid_set"]
    err = metrics.get("scale_error") or []
    valid = [[f"{v['iou']:.3f}", f"{v['precision']:.3f}", f"{v['recall']:.3f}",
              f"{sum(err) / len(err):.3f}" if err else ""]]
    seconds = {k: round(r["seconds"], 1) for k, r in stages.items()}
    tables = {
        "results": table(["method", *(h for _, h, _ in COLUMNS)], rows),
        "valid_set": table(["valid-set IoU", "precision", "recall", "relative scale error of matches"], valid),
        "stages": table(["stage", "seconds"], [[k, f"{s:.0f}" + (" (background)" if stages[k].get("background") else "")]
                                               for k, s in seconds.items()]),
    }
    data = {"valid_set": v, "scale_error_mean": sum(err) / len(err) if err else None, "stage_seconds": seconds,
            "demo_command": metrics.get("command")}
    return tables, data


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path, help="results JSON to write")
    ap.add_argument("--work", type=Path, default=None,
                    help="a finished demo's work directory to read instead of running `make demo` (not timed)")
    a = ap.parse_args(argv)
    print_command()
    work, wall, command = a.work, None, "make demo"
    if work is None:
        work = REPO / "runs" / "demo"
        t0 = time.perf_counter()
        subprocess.run(["make", "demo"], cwd=REPO, check=True)
        wall = time.perf_counter() - t0
    else:
        command = f"osn demo --work {work}"
    tables, data = demo_tables(work)
    data["wall_seconds"] = None if wall is None else round(wall, 1)
    # Other jobs on the machine slow every stage: say how loaded it was (1-minute load average).
    data["load_average_at_end"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    write_results(a.out, "demo", command, tables, data, cwd=REPO)
    print(f"wrote {a.out}" + (f" (make demo: {wall:.0f} s from start to table, set-up included)" if wall else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

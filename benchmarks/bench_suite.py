"""The paper's scene suite: generation time per preset at 64 and 128 px, and OSN on each at 64 px.

1. ``benchgen suite`` at ``--resolution 64`` and at the presets' default (128 px), G=50: wall time,
   the valid region's share of the Eq. 1 box, verification (the two tables side by side).
2. ``osn demo --preset P --resolution 64 --max-views 10`` (oracle inputs, the CPU training config) on each 64 px
   dataset (linked, not re-rendered): training PSNR, valid-set IoU against the exact region, best
   of N and the highest-score solution through the scorer, and the stage times.

Everything resumes (datasets and demo stages), so a killed run is rerun with the same command.
Prints the command first, then one table per step; writes ROOT/bench_suite.json. Run:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_suite.py --root /tmp/bench_suite [--skip-osn] [--presets a,b]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchgen.render.suite import SUITE_PRESETS, run_suite

from benchutil import command_line, print_command

#: Test views per ground truth in OSN's evaluation (evenly spread; the demo's default is 30): the
#: scoring of 50 ground truths dominates a preset's time, and 10 views keep the suite near an hour.
MAX_VIEWS = 10


def osn_on(preset: str, dataset: Path, work: Path, workers: int) -> dict:
    """``osn demo`` at 64 px on an already generated dataset; its stage records and report figures."""
    work.mkdir(parents=True, exist_ok=True)
    link = work / "dataset"
    if not link.exists():
        link.symlink_to(dataset.resolve(), target_is_directory=True)
    cmd = [sys.executable, "-m", "osn.cli", "demo", "--work", str(work), "--preset", preset, "--resolution", "64", "--inputs-from", "oracle",
           "--workers", str(workers), "--max-views", str(MAX_VIEWS)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["?"])[-1], "seconds": time.perf_counter() - t0}
    m = json.loads((work / "report" / "metrics.json").read_text())
    stages = json.loads((work / "stages.json").read_text())
    best = next(k for k in m["table"] if k.startswith("best of"))
    return {
        "train_psnr": stages["train"]["summary"]["psnr"],
        "iou": m["valid_set"]["iou"],
        "precision": m["valid_set"]["precision"],
        "recall": m["valid_set"]["recall"],
        "best_of": best,
        "best_psnr": m["table"][best]["psnr"][0],
        "highest_psnr": m["table"]["highest score"]["psnr"][0],
        "true_scales_psnr": m["table"]["true scales"]["psnr"][0],
        "unposed_fraction": m["extra"].get("unposed_object_fraction", 0.0),
        "seconds": {k: round(r["seconds"]) for k, r in stages.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default="/tmp/bench_suite", help="working directory (datasets, demo runs, results)")
    ap.add_argument("--presets", default=",".join(SUITE_PRESETS), help="comma-separated presets")
    ap.add_argument("--workers", type=int, default=2, help="rendering processes")
    ap.add_argument("--skip-osn", action="store_true", help="only the generation tables")
    ap.add_argument("--skip-128", action="store_true", help="only the 64 px generation")
    args = ap.parse_args()
    print_command()
    print(f"load average at start: {os.getloadavg()}", flush=True)
    root = Path(args.root)
    presets = [p for p in args.presets.split(",") if p]
    results: dict = {"command": command_line()}
    quiet = lambda line: None  # noqa: E731 - the suite's per-preset lines; the tables are printed below
    rows = {64: run_suite(root / "64", presets, resolution=64, workers=args.workers, progress=False, echo=quiet)}
    if not args.skip_128:
        rows[128] = run_suite(root / "128", presets, workers=args.workers, progress=False, echo=quiet)
    print(f"\ngeneration, G=50, --workers {args.workers} (load average now {os.getloadavg()[0]:.1f}):")
    print("| preset | rig | objects | train / test | " + " | ".join(f"{r} px: time, verified, valid share" for r in rows) + " |")
    print("|---|---|---|---|" + "---|" * len(rows))
    for i, p in enumerate(presets):
        r0 = rows[64][i]
        cells = [f"{rows[r][i].seconds:.0f} s, {rows[r][i].verified}/{rows[r][i].configurations}, {rows[r][i].share:.3g}" for r in rows]
        print(f"| {p} | {r0.protocol} | {r0.objects} | {r0.train_frames} / {r0.test_frames} | " + " | ".join(cells) + " |")
    results["generation"] = {str(r): [vars(x) for x in v] for r, v in rows.items()}
    if not args.skip_osn:
        print(f"\nOSN at 64 px (oracle inputs, configs/osn-cpu.yaml, {MAX_VIEWS} test views per ground truth), through osn demo:", flush=True)
        print("| preset | training PSNR | valid-set IoU (P / R) | best of N PSNR | highest score PSNR | true scales PSNR | unposed test pixels | train / evaluate time |")
        print("|---|---|---|---|---|---|---|---|")
        results["osn"] = {}
        for p in presets:
            r = osn_on(p, root / "64" / p, root / "osn" / p, args.workers)
            results["osn"][p] = r
            if "error" in r:
                print(f"| {p} | failed: {r['error']} ||||||| ", flush=True)
                continue
            print(f"| {p} | {r['train_psnr']:.2f} dB | {r['iou']:.3f} ({r['precision']:.3f} / {r['recall']:.3f}) | "
                  f"{r['best_psnr']:.2f} dB ({r['best_of']}) | {r['highest_psnr']:.2f} dB | {r['true_scales_psnr']:.2f} dB | {100 * r['unposed_fraction']:.2f}% | "
                  f"{r['seconds'].get('train', 0)} s / {r['seconds'].get('evaluate', 0)} s |", flush=True)
    (root / "bench_suite.json").write_text(json.dumps(results, indent=1, default=str))
    print(f"\nwrote {root / 'bench_suite.json'}")


if __name__ == "__main__":
    main()

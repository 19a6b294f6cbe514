"""``benchgen score`` speed and memory: the streaming scorer against a naive loop, in one run.

Builds a synthetic prediction directory from a generated dataset: N candidates, the G
ground-truth configurations themselves followed by perturbed copies (noise and a brightness
shift of a configuration's colours; its depth and ids hard-linked), written as PNG / EXR on the
evaluated views only. Then, each in a fresh process (so that its peak memory is its own):

* ``benchgen score`` (streaming, exact) on N candidates, and on the first N / 2 (same chunk size for
  N >= 512: peak memory must not grow with N);
* the naive loop: for each ground truth g, for each candidate, read it and score it (PSNR on the
  same masks), on the first ``--naive-gt`` ground truths (extrapolated to G; its matches are
  checked against the scorer's).

Peak memory: ``ru_maxrss`` of the process and of its worker processes.

    python benchmarks/bench_score.py DATASET --work DIR [-n 1000] [--views 30] [--workers 2] [--naive-gt 2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchutil import print_command


def build_predictions(dataset: Path, pred: Path, n: int, views: int, seed: int = 0) -> None:
    """Candidates ``0000..`` in ``pred``: configuration ``i % G``, exact for i < G, else perturbed."""
    from PIL import Image

    from scenecore import dataset as D
    from benchgen.score.truth import evaluated_views

    marker = pred / ".built.json"
    spec = {"dataset": str(dataset.resolve()), "n": n, "views": views, "seed": seed, "builder": 2}
    if marker.exists() and json.loads(marker.read_text()) == spec:
        return
    scene = D.load_scene(dataset)
    frames = evaluated_views(scene, views)
    G = scene.num_configurations
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    for g in range(min(G, n)):
        src = [D.frame_paths(dataset, f.name, g) for f in frames]
        gt_rgb = [D.read_rgb(p.rgb).astype(np.float64) for p in src]
        for i in range(g, n, G):
            cand = pred / f"{i:04d}"
            for kind in ("rgb", "depth", "ids"):
                (cand / kind).mkdir(parents=True, exist_ok=True)
            sigma, shift = (0.0, 0.0) if i < G else (rng.uniform(1, 12), rng.uniform(-10, 10))
            for f, p, rgb in zip(frames, src, gt_rgb):
                noisy = np.clip(rgb + shift + sigma * rng.standard_normal(rgb.shape), 0, 255).round().astype(np.uint8)
                Image.fromarray(noisy).save(cand / "rgb" / f"{f.name}.png", compress_level=1)
                for kind, path in (("depth", p.depth), ("ids", p.ids)):
                    if not (cand / kind / path.name).exists():
                        os.link(path, cand / kind / path.name)
    marker.write_text(json.dumps(spec))
    print(f"built {n} candidates x {len(frames)} views in {time.perf_counter() - t0:.0f} s: {pred}", flush=True)


def naive(dataset: Path, pred: Path, views: int, num_gt: int) -> dict:
    """For each of the first ``num_gt`` ground truths, read and score every candidate (PSNR)."""
    from scenecore import dataset as D
    from benchgen.score import metrics as M
    from benchgen.score.predictions import PredictionDir
    from benchgen.score.truth import load_truth

    truth = load_truth(dataset, views)
    source = PredictionDir(pred, truth.scene, [f.name for f in truth.frames])
    t0 = time.perf_counter()
    matches = []
    for g in range(num_gt):
        gt = np.stack([D.read_rgb(D.frame_paths(dataset, f.name, g).rgb) for f in truth.frames]) / 255.0
        mask = truth.masks(g)
        best = max(range(len(source)), key=lambda n: (np.nanmean(M.psnr(source.load(n).rgb / 255.0, gt, mask)), -n))
        matches.append(source.names[best])
    return {"seconds": time.perf_counter() - t0, "matches": matches}


def measure(args: argparse.Namespace) -> None:
    """One measurement in this process: prints a JSON line with time, peak memory and results."""
    t0 = time.perf_counter()
    if args.measure == "naive":
        out = naive(Path(args.dataset), Path(args.pred), args.views, args.naive_gt)
    else:
        from benchgen.cli import main as benchgen

        cmd = ["score", args.pred, "--data", args.dataset, "--out", args.out, "--max-views", str(args.views),
               "--workers", str(args.workers), "--quiet"]
        rc = benchgen(cmd)
        metrics = json.loads((Path(args.out) / "metrics.json").read_text())
        out = {"rc": rc, "timings": metrics["timings"], "matches": [r["match"] for r in metrics["per_ground_truth"]]}
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(json.dumps({**out, "wall_s": time.perf_counter() - t0, "peak_mib": own, "peak_worker_mib": kids}))


def run_measure(args: argparse.Namespace, mode: str, pred: Path, out: Path) -> dict:
    cmd = [sys.executable, __file__, args.dataset, "--work", args.work, "--measure", mode, "--pred", str(pred),
           "--out", str(out), "--views", str(args.views), "--workers", str(args.workers), "--naive-gt", str(args.naive_gt)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode:
        sys.exit(f"measurement {mode} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset")
    p.add_argument("--work", required=True, help="directory for the synthetic predictions and reports (reused)")
    p.add_argument("-n", type=int, default=1000, help="candidates N")
    p.add_argument("--views", type=int, default=30, help="evaluated test views (0 = all)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--naive-gt", type=int, default=2, help="ground truths the naive loop runs (extrapolated to G)")
    p.add_argument("--skip-small", action="store_true", help="skip the N / 2 run")
    p.add_argument("--measure", default=None, help=argparse.SUPPRESS)
    p.add_argument("--pred", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure:
        measure(args)
        return 0
    print_command()
    work, dataset = Path(args.work), Path(args.dataset)
    pred = work / f"pred_n{args.n}_v{args.views}"
    build_predictions(dataset, pred, args.n, args.views)
    scene = json.loads((dataset / "scene.json").read_text())
    G, size = scene["num_configurations"], f"{scene['image']['width']}x{scene['image']['height']}"
    print(f"N={args.n} x G={G} x {args.views or 'all'} views at {size}, workers={args.workers}, "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}", flush=True)
    runs = [(args.n, pred)]
    if not args.skip_small:
        small = work / f"pred_n{args.n // 2}_v{args.views}"
        small.mkdir(parents=True, exist_ok=True)
        for name in sorted(n for n in os.listdir(pred) if not n.startswith("."))[: args.n // 2]:
            if not (small / name).exists():
                (small / name).symlink_to((pred / name).resolve())
        runs.append((args.n // 2, small))
    fast = {}
    for n, where in runs:
        r = run_measure(args, "score", where, work / f"score_n{n}")
        fast[n] = r
        t = r["timings"]
        print(f"benchgen score N={n:5d}: {r['wall_s']:6.1f} s wall (ground truth {t['ground_truth_s']:.1f} s, candidate "
              f"pass {t['candidate_pass_s']:.1f} s, metrics {t['metrics_s']:.1f} s, report {t['report_s']:.1f} s); "
              f"peak memory {r['peak_mib']:.0f} MiB main, {r['peak_worker_mib']:.0f} MiB largest worker", flush=True)
    if args.naive_gt:
        r = run_measure(args, "naive", pred, work / "naive")
        same = r["matches"] == fast[args.n]["matches"][: args.naive_gt]
        print(f"naive loop     N={args.n:5d}: {r['seconds']:6.1f} s for {args.naive_gt} of {G} ground truths -> "
              f"{r['seconds'] * G / args.naive_gt:.0f} s for all G (extrapolated), without metrics; peak memory "
              f"{r['peak_mib']:.0f} MiB; same matches as benchgen score: {same}")
        print(f"speed-up of the candidate pass: {r['seconds'] * G / args.naive_gt / fast[args.n]['timings']['candidate_pass_s']:.0f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

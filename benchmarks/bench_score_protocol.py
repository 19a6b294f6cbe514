"""``benchgen score`` at a protocol's full size: the path before against today's, in one process.

On one dataset and one prediction directory, one after the other in this process:

* ``on the fly`` (only with ``--on-the-fly``): the path before the masks were stored: the ground
  truth's co-visibility masks computed from its depth and ids (what a dataset written before
  ``configs/GGG/covisibility.npz`` existed still gets), candidates scored in float64 with torch's
  own thread count beside the reading workers (``bestofn.EXACT_FLOAT32`` and
  ``bestofn.THREADS_BESIDE_WORKERS`` False), and everything ``before`` does;
* ``before``: stored masks and exact float32 products, but every candidate file decoded and
  checked in the pass (``bestofn.COLOUR_ONLY`` False), the colours sent from the reading workers
  to this process, which scores them (``bestofn.SCORE_IN_WORKERS`` False), the ground truth read
  through the dataset's reader (``truth.DIRECT_PNG`` False) and the matched metrics computed in
  this process (``scorer.METRICS_IN_WORKERS`` False);
* ``now``: today's path: the pass decodes the candidates' colour only (depth and ids checked up to
  their headers) and each worker scores the chunks it reads, the ground truth's PNGs decoded by
  Pillow directly, the matched candidates' metrics computed in the ``--workers`` processes;
* ``benchgen score``: the command itself on the same inputs (it also hashes every file it reads
  for the report's provenance and checks the dataset's verification).

All must give the same PSNR matrix and the same matches, bit for bit, and ``before`` and ``now``
the same matched metrics (every value of every row, per view too; checked). Each
row reports wall seconds by phase and the CPU seconds of this process and its workers. The
candidates are N symlinks to the dataset's own ``configs/GGG`` (candidate i is configuration
i mod G: a valid candidate with colour, depth and ids, every file read and checked like any
method's). Every dataset file is read once before timing, so no path pays for a cold page cache.

    python benchmarks/bench_score_protocol.py DATASET --work DIR [-n 1000] [--views 0] [--workers 2] [--no-lpips] [--on-the-fly]

Writes ``benchmarks/results/score_speed.json`` (``--results``), the table docs/predictions.md shows.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

from benchutil import command_line, print_command
from results_json import table, write_results

REPO = Path(__file__).resolve().parents[1]


def build_predictions(dataset: Path, pred: Path, n: int, num_configs: int) -> None:
    """``pred/NNNN`` -> ``dataset/configs/GGG`` with g = i mod G (kept when already there)."""
    pred.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        link = pred / f"{i:04d}"
        target = (dataset / "configs" / f"{i % num_configs:03d}").resolve()
        if link.is_symlink() and Path(os.readlink(link)) == target:
            continue
        if link.is_symlink():
            link.unlink()
        link.symlink_to(target)


def warm(dataset: Path) -> int:
    """Read every file of the dataset once (page cache); returns the bytes read."""
    total = 0
    for p in sorted(dataset.rglob("*")):
        if p.is_file():
            total += len(p.read_bytes())
    return total


def cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (the scorer's workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def switches() -> list[tuple[object, str]]:
    """The module switches of today's speed-ups (True: today's path)."""
    from benchgen.score import bestofn, scorer, truth

    return [(bestofn, "COLOUR_ONLY"), (bestofn, "SCORE_IN_WORKERS"), (truth, "DIRECT_PNG"), (scorer, "METRICS_IN_WORKERS")]


def run_path(dataset: Path, pred: Path, out: Path, views: int, workers: int, lpips: bool, stored: bool,
             now: bool = True) -> dict:
    """Load the ground truth and score, as ``benchgen score`` does, with or without stored masks,
    with or without today's speed-ups (``now``)."""
    from scenecore import dataset as D
    from benchgen.score import bestofn
    from benchgen.score.predictions import PredictionDir
    from benchgen.score.report import write_report
    from benchgen.score.scorer import score
    from benchgen.score.truth import evaluated_views, load_truth

    bestofn.EXACT_FLOAT32 = bestofn.THREADS_BESIDE_WORKERS = stored
    for module, name in switches():
        setattr(module, name, now)
    c0, t0 = cpu_seconds(), time.perf_counter()
    scene = D.load_scene(dataset)
    source = PredictionDir(pred, scene, [f.name for f in evaluated_views(scene, views)])
    truth = load_truth(dataset, views, workers, stored_masks=stored)
    t_truth = time.perf_counter() - t0
    res = score(truth, source, with_lpips=lpips, workers=workers)
    res.timings = {"ground_truth_s": t_truth, **res.timings}
    write_report(res, out, source.method, "bench_score_protocol", str(dataset), str(pred))
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    bestofn.EXACT_FLOAT32 = bestofn.THREADS_BESIDE_WORKERS = True
    for module, name in switches():
        setattr(module, name, True)
    return {"wall_s": wall, "cpu_s": cpu, "timings": res.timings, "matrix": res.matrix, "mask": truth.mask,
            "rows": res.per_ground_truth, "note": truth.masks_note}


def part_costs(dataset: Path, pred: Path, views: int, sample: int = 8) -> dict:
    """CPU milliseconds per candidate and view of the candidate pass's two parts, on the first
    ``sample`` candidates, best of three, one thread: reading and checking the files (all decoded,
    or the colour decoded and depth and ids checked up to their headers), and the products against
    all G truths (float64 and exact float32)."""
    import torch

    from scenecore import dataset as D
    from benchgen.score import bestofn
    from benchgen.score.predictions import PredictionDir
    from benchgen.score.truth import evaluated_views, load_truth

    scene = D.load_scene(dataset)
    source = PredictionDir(pred, scene, [f.name for f in evaluated_views(scene, views)])
    truth = load_truth(dataset, views)
    energy = bestofn.truth_energy(truth)
    sample = min(sample, len(source))
    per = sample * truth.num_views

    def best(fn) -> float:
        out = []
        for _ in range(3):
            t0 = time.process_time()
            fn()
            out.append(time.process_time() - t0)
        return 1e3 * min(out) / per

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rgbs = [source.load(n).rgb for n in range(sample)]
        costs = {"read": best(lambda: [source.load(n) for n in range(sample)]),
                 "read_colour": best(lambda: [source.load_rgb(n) for n in range(sample)])}
        for name, exact in (("products_float64", False), ("products_float32", True)):
            bestofn.EXACT_FLOAT32 = exact
            costs[name] = best(lambda: bestofn.view_psnr(rgbs, truth, energy))
    finally:
        bestofn.EXACT_FLOAT32 = True
        torch.set_num_threads(threads)
    return costs


def metric_differences(a: list[dict], b: list[dict]) -> dict[str, float]:
    """Largest absolute difference of each metric between two runs' rows (means and per-view
    values; NaN where both are NaN counts as equal, NaN against a number as infinite)."""
    out: dict[str, float] = {}
    for ra, rb in zip(a, b, strict=True):
        values = [(k, ra[k], rb[k]) for k in ra if k not in ("per_view", "match", "configuration", "match_index")]
        values += [(k, ra["per_view"][k], rb["per_view"][k]) for k in ra["per_view"]]
        for k, x, y in values:
            x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
            d = np.where(np.isnan(x) & np.isnan(y), 0.0, np.abs(x - y))
            out[k] = max(out.get(k, 0.0), float(np.where(np.isnan(d), np.inf, d).max(initial=0.0)))
    return out


def run_cli(dataset: Path, pred: Path, out: Path, views: int, workers: int, lpips: bool) -> dict:
    from benchgen.cli import main as benchgen

    cmd = ["score", str(pred), "--data", str(dataset), "--out", str(out), "--workers", str(workers), "--quiet"]
    cmd += ["--max-views", str(views)] * bool(views) + ["--no-lpips"] * (not lpips)
    c0, t0 = cpu_seconds(), time.perf_counter()
    rc = benchgen(cmd)
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    if rc:
        sys.exit(f"benchgen score exited with {rc}")
    m = json.loads((out / "metrics.json").read_text())
    return {"wall_s": wall, "cpu_s": cpu, "timings": m["timings"], "matrix": np.load(out / "psnr_matrix.npy"),
            "rows": m["per_ground_truth"], "note": m.get("covisibility_note", "")}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset")
    p.add_argument("--work", required=True, help="directory for the prediction links and the reports (reused)")
    p.add_argument("-n", type=int, default=1000, help="candidates N")
    p.add_argument("--views", type=int, default=0, help="evaluated test views (0 = all)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS in the matched metrics")
    p.add_argument("--on-the-fly", action="store_true", help="also time the path before the masks were stored")
    p.add_argument("--results", default=str(REPO / "benchmarks" / "results" / "score_speed.json"))
    args = p.parse_args()
    print_command()
    from scenecore.cli import blas_on_one_thread

    blas_on_one_thread()  # as the benchgen command line does
    from scenecore import dataset as D

    dataset, work = Path(args.dataset).resolve(), Path(args.work)
    scene = D.load_scene(dataset)
    G = scene.num_configurations
    stored = sum(D.covisibility_path(dataset, g).exists() for g in range(G))
    if stored != G:
        sys.exit(f"{dataset}: {stored} of {G} configurations store co-visibility masks; rerun 'benchgen generate' "
                 "with the same options to add them")
    pred = work / f"pred_n{args.n}"
    build_predictions(dataset, pred, args.n, G)
    views = args.views or len(scene.test_frames)
    size = f"{scene.width}x{scene.height}"
    load0 = os.getloadavg()[0]
    print(f"N={args.n} x G={G} x {views} views at {size}, workers={args.workers}, LPIPS {'off' if args.no_lpips else 'on'}, "
          f"{os.cpu_count()} cores, load average {load0:.1f}", flush=True)
    t0 = time.perf_counter()
    nbytes = warm(dataset)
    print(f"read the dataset once ({nbytes / 2**20:.0f} MiB) in {time.perf_counter() - t0:.1f} s", flush=True)
    lpips = not args.no_lpips
    runs = {}
    paths = [("on the fly", lambda: run_path(dataset, pred, work / "score_fly", args.views, args.workers, lpips, False, False))]
    paths = paths[: args.on_the_fly] + [
        ("before", lambda: run_path(dataset, pred, work / "score_before", args.views, args.workers, lpips, True, False)),
        ("now", lambda: run_path(dataset, pred, work / "score_stored", args.views, args.workers, lpips, True)),
        ("benchgen score", lambda: run_cli(dataset, pred, work / "score_cli", args.views, args.workers, lpips))]
    for name, fn in paths:
        load = os.getloadavg()[0]
        r = runs[name] = fn()
        r["load"] = (load, os.getloadavg()[0])
        t = r["timings"]
        print(f"{name:15s} {r['wall_s']:7.1f} s wall, {r['cpu_s']:7.1f} s CPU ("
              + ", ".join(f"{k.removesuffix('_s').replace('_', ' ')} {v:.1f}" for k, v in t.items() if k != "total_s")
              + f"); load average {os.getloadavg()[0]:.1f}", flush=True)
    old, new, cli = runs["before"], runs["now"], runs["benchgen score"]
    same = (np.array_equal(old["matrix"], new["matrix"], equal_nan=True) and np.array_equal(old["mask"], new["mask"])
            and np.array_equal(new["matrix"], cli["matrix"], equal_nan=True)
            and [r["match"] for r in old["rows"]] == [r["match"] for r in new["rows"]] == [r["match"] for r in cli["rows"]])
    if "on the fly" in runs:
        fly = runs["on the fly"]
        same = same and np.array_equal(fly["matrix"], new["matrix"], equal_nan=True) and np.array_equal(fly["mask"], new["mask"])
    differences = metric_differences(old["rows"], new["rows"])
    same_metrics = not any(differences.values())
    costs = part_costs(dataset, pred, args.views)
    print("CPU per candidate and view (one thread): " + ", ".join(f"{k} {v:.3f} ms" for k, v in costs.items()))
    ratio = old["wall_s"] / new["wall_s"]
    print(f"same masks, PSNR matrix and matches: {same}; same matched metrics, bit for bit: {same_metrics}"
          + ("" if same_metrics else f" (largest differences: {differences})")
          + f"; speed-up {ratio:.2f}x wall, {old['cpu_s'] / new['cpu_s']:.2f}x CPU")
    if not same:
        sys.exit("the paths disagree")

    def row(label: str, r: dict) -> list[str]:
        t = r["timings"]
        return [label, f"{t['ground_truth_s']:.0f}", f"{t['candidate_pass_s']:.0f}", f"{t['metrics_s']:.0f}",
                f"{t.get('digests_s', 0.0):.0f}", f"{r['wall_s']:.0f}", f"{r['cpu_s']:.0f}", f"{old['wall_s'] / r['wall_s']:.2f}x",
                f"{old['cpu_s'] / r['cpu_s']:.2f}x", f"{r['load'][0]:.1f} / {r['load'][1]:.1f}"]

    columns = ["path", "ground truth (s)", "candidate pass (s)", "matched metrics (s)", "digests (s)", "total wall (s)",
               "CPU (s)", "speed-up (wall)", "speed-up (CPU)", "load average at start / end"]
    rows = [row("masks computed, float64 pass on torch's threads, as before", runs["on the fly"])] if "on the fly" in runs else []
    rows += [row("before: every candidate file decoded in the pass and scored in this process, ground truth through imageio, "
                 "metrics in this process", old),
             row("now: colour only in the pass, scored where it is read, ground truth through Pillow, metrics in the workers", new),
             row("`benchgen score` (with provenance digests)", cli)]
    nv = args.n * views / 1e3
    parts = [["read and check one candidate's files in full (colour PNG, depth EXR, id PNG; before)", f"{costs['read']:.2f}",
              f"{costs['read'] * nv:.0f}"],
             ["colour decoded and checked, depth and ids checked up to their headers (now)", f"{costs['read_colour']:.2f}",
              f"{costs['read_colour'] * nv:.0f}"],
             ["products against all G ground truths, float64", f"{costs['products_float64']:.2f}",
              f"{costs['products_float64'] * nv:.0f}"],
             ["products against all G ground truths, exact float32", f"{costs['products_float32']:.2f}",
              f"{costs['products_float32'] * nv:.0f}"]]
    protocol = f"N = {args.n}, G = {G}, {views} views, {size}, --workers {args.workers}, LPIPS {'off' if args.no_lpips else 'on'}"
    data = {"dataset": str(dataset), "n": args.n, "num_configurations": G, "views": views, "size": size,
            "workers": args.workers, "lpips": lpips, "protocol": protocol, "load_average_at_start": load0,
            "load_average_at_end": os.getloadavg()[0], "identical": same, "identical_metrics": same_metrics,
            "metric_max_abs_difference": differences, "speed_up_wall": ratio,
            "cpu_ms_per_candidate_view": costs,
            "runs": {k: {"wall_s": v["wall_s"], "cpu_s": v["cpu_s"], "timings": v["timings"], "note": v["note"],
                         "load_average": v["load"]}
                     for k, v in runs.items()}}
    write_results(Path(args.results), "score_speed", command_line(), {"score_speed": table(columns, rows),
                  "score_speed_parts": table(["part of the candidate pass", "CPU ms per candidate and view",
                                              f"CPU s for N x V = {args.n} x {views}"], parts)},
                  data, REPO)
    print(f"wrote {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Best of N against a spray, unguarded and guarded by fidelity, on a finished demo.

    python benchmarks/bench_fidelity.py --work runs/demo --out benchmarks/results/fidelity.json \\
        [--scratch DIR] [-n 1000] [--max-views 30] [--seed 0] [--workers 2]

Reads a finished ``osn demo`` work directory (its dataset, its run and the run's ``samples.npz``:
OSN's N valid samples). Draws N scale vectors uniformly over the scale network's whole box (the
spray: most lie outside the valid region) and writes them as a samples file (their network scores
included). Both sets then go through exactly what a user runs: ``osn evaluate RUN --samples FILE
--candidates DIR --max-views K`` (the layered search pre-selects the candidates it renders; the
true-scales row is left out, it does not depend on the samples) and ``benchgen score
DIR/preselected --data DATASET --max-views K``, whose report holds the unguarded best of N, the
fidelity check of each candidate's training renders and best of N over the faithful candidates.

Writes a results JSON (``results_json``): tables ``fidelity`` (guarded and unguarded best of N,
the structure metrics, the share of faithful candidates), ``coverage`` (coverage and precision at
PSNR levels) and ``shortfall`` (how far below the best candidate each set's candidates render the
training video on their worst frame: the tolerance's margin on both sides), and every figure
under ``data``, with each step's wall seconds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import command_line, print_command  # noqa: E402
from results_json import table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SETS = ("OSN samples", "uniform spray")


def in_region(run_dir: Path, dataset: Path, sbar: np.ndarray) -> np.ndarray:
    """Whether each de-normalised scale vector ``sbar (N, K)`` of the run lies in the dataset's exact
    valid region (the ground truth: this benchmark measures, it is no method)."""
    from scenecore import dataset as D
    from osn.evaluate.units import actual_scales
    from osn.model.run import load_run

    run = load_run(run_dir)
    scene = D.load_scene(dataset)
    scales = np.ones((len(sbar), scene.num_objects))
    scales[:, [o.id for o in run.inputs.objects]] = actual_scales(run.inputs, sbar)
    return np.asarray(D.load_valid_region(dataset, scene.num_objects).contains(scales), bool)


def spray_samples(run_dir: Path, dataset: Path, n: int, seed: int, out: Path) -> dict:
    """``n`` scale vectors uniform over the run's whole normalised box, written as a samples file;
    returns the shares the network and the exact region hold valid."""
    from osn.model.run import load_run
    from osn.sample.configurations import Samples

    run = load_run(run_dir)
    K = run.inputs.num_objects
    s_free = np.random.default_rng(seed).random((n, K - 1))
    sbar = run.sbar(s_free)
    score = run.scores(s_free)
    Samples(s_free, sbar, score, 0.5, seed).save(out)
    osn = Samples.load(run_dir / "samples.npz")
    return {"spray_network_valid": float(np.mean(score > 0.5)), "spray_region_valid": float(in_region(run_dir, dataset, sbar).mean()),
            "osn_region_valid": float(in_region(run_dir, dataset, osn.sbar).mean())}


def candidates_in_region(work: Path, samples: Path, names: list[str]) -> np.ndarray:
    """Region membership of scored candidates named ``sample_NNNNN`` (their index in ``samples``)."""
    from osn.sample.configurations import Samples

    sbar = Samples.load(samples).sbar[[int(n.rsplit("_", 1)[1]) for n in names]]
    return in_region(work / "run", work / "dataset", sbar)


def _run(cmd: list[str]) -> float:
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=REPO, check=True)
    return time.perf_counter() - t0


def evaluate_and_score(work: Path, samples: Path, out: Path, max_views: int, workers: int) -> dict:
    """``osn evaluate --candidates`` then ``benchgen score`` on the pre-selected candidates;
    returns both metrics files and the wall seconds of each step."""
    cands, report, scored = out / "candidates", out / "report", out / "score"
    t_eval = _run([sys.executable, "-m", "osn.cli", "evaluate", str(work / "run"), "--data", str(work / "dataset"),
                   "--samples", str(samples), "--candidates", str(cands), "--out", str(report),
                   "--max-views", str(max_views), "--no-true-scales"])
    t_score = _run([sys.executable, "-m", "benchgen.cli", "score", str(cands / "preselected"), "--data",
                    str(work / "dataset"), "--out", str(scored), "--max-views", str(max_views), "--workers", str(workers),
                    "--quiet"])
    score = json.loads((scored / "metrics.json").read_text())
    return {"evaluate": json.loads((report / "metrics.json").read_text()), "score": score, "evaluate_s": t_eval,
            "score_s": t_score, "in_region": candidates_in_region(work, samples, score["candidates"]).tolist()}


def _ms(summary: dict | None, key: str, digits: int) -> str:
    if not summary or key not in summary or summary[key]["mean"] is None:
        return "none"
    return f"{summary[key]['mean']:.{digits}f} ± {summary[key]['std']:.{digits}f}"


def tables(results: dict[str, dict], levels: list[float]) -> dict:
    rows, cov_rows, short_rows = [], [], []
    for name, r in results.items():
        s, f = r["score"], r["score"]["fidelity"]
        g = f.get("summary")
        rows.append([name, str(s["num_candidates"]), f"{f['num_faithful']} ({100 * f['faithful_share']:.0f}%)",
                     _ms(g, "psnr", 2), _ms(s["summary"], "psnr", 2), _ms(g, "ssimae", 3), _ms(s["summary"], "ssimae", 3),
                     _ms(g, "pq", 1), _ms(s["summary"], "pq", 1), _ms(g, "miou", 1)])
        c = s["coverage"]
        lv = np.asarray(c["levels"])
        pick = [int(np.argmin(np.abs(lv - x))) for x in levels]
        cov_rows.append([name] + [f"{100 * c['ground_truths'][i]:.0f}% / {100 * c['ground_truths_faithful'][i]:.0f}%" for i in pick]
                        + [f"{100 * c['candidates'][i]:.0f}% / {100 * c['candidates_faithful'][i]:.0f}%" for i in pick])
        sh = np.asarray(f["shortfall_db"])
        ok, inside = np.asarray(f["faithful"], bool), np.asarray(r["in_region"], bool)

        def q(x: np.ndarray, how) -> str:
            return f"{how(x):.2f}" if x.size else "none"

        short_rows.append([name, f"{inside.sum()} / {len(sh)}", q(sh[inside], np.median), q(sh[inside], np.max),
                           q(sh[~inside], np.min), q(sh[~inside], np.median), f"{(ok & inside).sum()} / {(ok & ~inside).sum()}"])
    return {
        "fidelity": table(["samples", "candidates scored", "faithful", "best of N, faithful: PSNR ↑", "best of N, all: PSNR ↑",
                           "SSIMAE ↓ faithful", "SSIMAE ↓ all", "PQ ↑ faithful", "PQ ↑ all", "mIoU ↑ faithful"], rows),
        "coverage": table(["samples"] + [f"coverage ≥ {x:g} dB (all / faithful)" for x in levels]
                          + [f"precision ≥ {x:g} dB (all / faithful)" for x in levels], cov_rows),
        "shortfall": table(["samples", "candidates in the valid region", "shortfall inside: median (dB)", "largest",
                            "shortfall outside: smallest (dB)", "median", "faithful inside / outside"], short_rows),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, type=Path, help="a finished `osn demo` work directory")
    ap.add_argument("--out", required=True, type=Path, help="results JSON to write")
    ap.add_argument("--scratch", type=Path, default=None, help="where samples, candidates and reports go (default WORK/fidelity)")
    ap.add_argument("-n", type=int, default=1000, help="scale vectors in the spray (OSN's come from WORK/run/samples.npz)")
    ap.add_argument("--max-views", type=int, default=30, help="test views evaluated, as the demo")
    ap.add_argument("--seed", type=int, default=0, help="seed of the spray")
    ap.add_argument("--workers", type=int, default=2, help="benchgen score --workers")
    a = ap.parse_args(argv)
    print_command("benchmarks/bench_fidelity.py", argv)
    t0 = time.perf_counter()
    scratch = a.scratch or a.work / "fidelity"
    scratch.mkdir(parents=True, exist_ok=True)
    spray = scratch / "spray_samples.npz"
    shares = spray_samples(a.work / "run", a.work / "dataset", a.n, a.seed, spray)
    results = {SETS[0]: evaluate_and_score(a.work, a.work / "run" / "samples.npz", scratch / "osn", a.max_views, a.workers),
               SETS[1]: evaluate_and_score(a.work, spray, scratch / "spray", a.max_views, a.workers)}
    mean = results[SETS[0]]["score"]["summary"]["psnr"]["mean"]
    levels = [float(np.floor(mean)) - 2, float(np.floor(mean)) - 1, float(np.floor(mean))]
    data = {"shares": shares, "n": a.n, "max_views": a.max_views, "seed": a.seed, "levels": levels,
            "wall_s": time.perf_counter() - t0}
    for name, r in results.items():
        s, e = r["score"], r["evaluate"]
        err = e.get("scale_error") or []
        data[name] = {"evaluate_s": r["evaluate_s"], "score_s": r["score_s"], "summary": s["summary"],
                      "fidelity": {k: v for k, v in s["fidelity"].items() if k != "per_ground_truth"},
                      "coverage": s["coverage"], "evaluate_table": e["table"], "in_region": r["in_region"],
                      "scale_error_mean": float(np.mean(err)) if err else None}
    command = command_line("benchmarks/bench_fidelity.py", argv)
    write_results(a.out, "fidelity", command, tables(results, levels), data, REPO)
    for t in tables(results, levels).values():
        print("| " + " | ".join(t["columns"]) + " |")
        for row in t["rows"]:
            print("| " + " | ".join(row) + " |")
        print()
    print(f"wall {data['wall_s']:.0f} s; results: {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""OSN as published against the default, side by side on one demo's dataset and inputs.

    python benchmarks/bench_paper_vs_default.py --work runs/demo --out benchmarks/results/paper_vs_default.json \\
        [--seeds 0,1,2] [--configs configs/osn-paper.yaml,configs/osn-cpu.yaml] [-n 1000] [--max-views 30]

Reads a finished ``osn demo`` work directory (its dataset and the inputs its run trained on: SfM's
for the default demo), trains each config once per seed (the config's ``seed`` replaced), in turn
so that machine load hits both alike, draws ``n`` samples and evaluates best of N as the demo does
(LPIPS and the true-scales row left out: they do not separate the configs and cost time). Writes a
results JSON (``results_json``) with one row per run and one per config (mean ± std over seeds):
training PSNR, valid-set IoU, best of N, highest score, their margin and the training time.
Runs already finished under ``--work``/paper-vs-default/ are read, not retrained.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_heldout import _mean_std  # noqa: E402
from benchutil import command_line, print_command  # noqa: E402
from results_json import table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def run_one(cfg_path: Path, seed: int, work: Path, out: Path, n: int, max_views: int) -> dict:
    """Train, sample and evaluate one config at one seed under ``out`` (read back when done)."""
    from osn.cli.train import dataset_region
    from osn.evaluate.bestofn import EvalConfig, evaluate
    from osn.model.run import load_run
    from osn.preprocess.inputs import load_inputs
    from osn.sample.configurations import sample_configurations
    from osn.train import TrainConfig, read_metrics, train

    done = out / "result.json"
    if done.exists():
        return json.loads(done.read_text())
    dataset = work / "dataset"
    cfg = TrainConfig.from_dict({**TrainConfig.from_yaml(cfg_path).to_dict(), "seed": seed})
    t0 = time.perf_counter()
    train(out / "run", cfg, inputs=load_inputs(work / "run" / "inputs"), region=dataset_region(dataset), progress=False)
    train_s = time.perf_counter() - t0
    last = read_metrics(out / "run" / "metrics.jsonl")[-1]
    run = load_run(out / "run")
    samples = sample_configurations(run, n, seed=0)
    res = evaluate(run, dataset, samples, EvalConfig(max_views=max_views, lpips=False, true_scales=False))
    best = next(k for k in res.table if k.startswith("best of"))
    rec = {"config": cfg_path.name, "seed": seed, "train_psnr": last["psnr"], "iou": res.valid_set["iou"],
           "precision": res.valid_set["precision"], "recall": res.valid_set["recall"],
           "best": res.table[best]["psnr"][0], "highest": res.table["highest score"]["psnr"][0], "train_s": train_s}
    done.write_text(json.dumps(rec))
    return rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="a finished `osn demo` work directory")
    ap.add_argument("--out", type=Path, required=True, help="results JSON to write")
    ap.add_argument("--configs", default="configs/osn-paper.yaml,configs/osn-cpu.yaml", help="comma-separated training configs")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated training seeds")
    ap.add_argument("-n", type=int, default=1000, help="samples drawn per run")
    ap.add_argument("--max-views", type=int, default=30, help="test views evaluated per ground truth")
    a = ap.parse_args(argv)
    print_command("benchmarks/bench_paper_vs_default.py", argv)
    configs = [REPO / c if not Path(c).is_absolute() else Path(c) for c in a.configs.split(",")]
    seeds = [int(s) for s in a.seeds.split(",")]
    root = a.work / "paper-vs-default"
    recs = []
    for seed in seeds:  # seed-major: both configs see the same machine state
        for cfg in configs:
            rec = run_one(cfg, seed, a.work, root / f"{cfg.stem}-seed{seed}", a.n, a.max_views)
            recs.append(rec)
            print(json.dumps(rec), flush=True)
    fmt = lambda v, d: f"{v:.{d}f}"  # noqa: E731
    cols = ["config", "seed", "training PSNR", "valid-set IoU", f"best of {a.n}", "highest score", "margin (dB)", "train s"]
    rows = [[r["config"], str(r["seed"]), fmt(r["train_psnr"], 2), fmt(r["iou"], 3), fmt(r["best"], 2),
             fmt(r["highest"], 2), fmt(r["best"] - r["highest"], 2), fmt(r["train_s"], 0)] for r in recs]
    summary = []
    for cfg in configs:
        rs = [r for r in recs if r["config"] == cfg.name]
        ms = lambda k, d: _mean_std(k, f"{{:.{d}f}}")  # noqa: E731  (sample std, as every benchmark's table)
        summary.append([cfg.name, f"{len(rs)} seeds", ms([r["train_psnr"] for r in rs], 2), ms([r["iou"] for r in rs], 3),
                        ms([r["best"] for r in rs], 2), ms([r["highest"] for r in rs], 2),
                        ms([r["best"] - r["highest"] for r in rs], 2), ms([r["train_s"] for r in rs], 0)])
    short = [0, 3, 4, 5, 6, 7]  # README's: without the seed count and the training PSNR
    tables = {"runs": table(cols, rows), "summary": table(cols, summary),
              "summary_short": table([f"config ({len(seeds)} seeds)"] + [cols[i] for i in short[1:]],
                                     [[r[i] for i in short] for r in summary])}
    command = command_line("benchmarks/bench_paper_vs_default.py", argv)
    write_results(a.out, "paper_vs_default", command, tables, {"runs": recs, "dataset": str(a.work / "dataset")}, cwd=REPO)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

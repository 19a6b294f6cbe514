"""Which of this toolkit's additions to OSN earn their place: the default minus each family of them.

On scenes of the procedural family's development split (tune here; the held-out split is reported
once, by ``bench_heldout.py``), ``osn demo`` trains the CPU default, the default with one family
of additions set to its neutral value (:data:`FAMILIES`; each option's category and neutral value
are in docs/training.md, Options), and optionally the paper's configuration, from SfM inputs (the
published path). The inputs are not recomputed per configuration: every run of a scene starts
from the SfM, oracle and ground-truth stages of one ``bench_heldout.py`` run of that scene
(``--base LABEL``, run first with ``bench_heldout.py --root ROOT --split development``, with
``--presets`` for suite presets), so a
difference between two rows is the training configuration's alone. Per run the figures of
``bench_heldout.py`` (valid-set IoU, best of N minus the highest-score solution, training time);
per configuration mean ± std over scenes and training seeds, the paired difference of IoU
from the default's run of the same scene and seed, and on how many scenes that difference exceeds
the default's own range over training seeds (``--spread-seeds``: extra seeds of the default
alone). Everything resumes; ``--finished-only`` makes the tables from the runs that finished
training and starts none (a queue stopped early still gives its tables). Run:

    .venv/bin/python benchmarks/bench_ablation.py --root /tmp/dev3 --base cand --seeds 3
        [--presets dining-table,chessboard-8] [--families label-rule,free-space] [--train-seeds 0,1]
        [--spread-seeds 1,2] [--jobs 2] [--executor ray]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import yaml
from bench_heldout import FIELDS, _mean_std, _measured, presets_arg, run_one, scene_dir, scene_key, seed_work
from results_json import table

from benchutil import add_executor_args, finish_parallel, print_command, run_parallel

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = ROOT / "configs" / "osn-cpu.yaml"
PAPER_CONFIG = ROOT / "configs" / "osn-paper.yaml"

#: Families of additions: what each is for, and the neutral values that switch it off
#: (``field.X`` is a field option). The last six single out one option of a family each (the
#: two whose ``auto`` differs between exact and noisy inputs, and four never measured alone), so
#: that each can be judged alone. The band against other objects was a sixth until it became a
#: constant (``osn.train.trainer.FREE_BAND_OBJECTS``; its row in the tables was measured before).
FAMILIES: dict[str, tuple[str, dict[str, Any]]] = {
    "label-rule": ("a sample may violate a few contact rays; silhouette bleeds dropped; positives replayed; "
                   "the room's depth corrected by its measured bias",
                   {"final_label_trim": 0.0, "pair_minority": 0.0, "label_replay": 0.0, "anchor_bias": 0.0}),
    "free-space": ("density carved where another object owns the pixel",
                   {"w_free": 0.0}),
    "depth-terms": ("robust depth loss, silhouette depth, distortion loss",
                    {"depth_robust": 0.0, "w_edge": 0.0, "w_distortion": 0.0}),
    "anchor-terms": ("the room's hidden-surface smoothness, guided samples, colour planes",
                     {"w_hidden_smooth": 0.0, "anchor_guide_samples": 0, "field.anchor_planes": 0}),
    "final-scale-phase": ("a last scale phase on the final fields", {"final_scale_iters": 0}),
    "field-resolution": ("objects' grids a voxel per pixel", {"field.object_resolution": 0}),
    "object-terms": ("opacity loss; stage-1 terms in every field step", {"w_opacity": 0.0, "w_alone": 0.0}),
    "scale-optimiser": ("the scale network's phases, rate and decay as retuned here",
                        {"scale_iters": 100, "scale_lr": 0.001, "scale_lr_final": 1.0}),
    "robust-depth": ("the Cauchy depth loss alone", {"depth_robust": 0.0}),
    "silhouette-depth": ("the silhouette-depth term alone", {"w_edge": 0.0}),
    "label-replay": ("scale samples replayed around earlier positives, alone", {"label_replay": 0.0}),
    "pair-minority": ("silhouette bleeds dropped from the labels, alone", {"pair_minority": 0.0}),
    "distortion": ("the distortion loss alone", {"w_distortion": 0.0}),
    "anchor-bias": ("the room's depth on label rays corrected by its measured bias, alone", {"anchor_bias": 0.0}),
}

def config_for(name: str, train_seed: int) -> dict[str, Any]:
    """The training config of row ``name`` (``default``, ``paper`` or a family) at ``train_seed``."""
    base = yaml.safe_load((PAPER_CONFIG if name == "paper" else DEFAULT_CONFIG).read_text())
    off = FAMILIES[name][1] if name in FAMILIES else {}
    for key, value in off.items():
        if key.startswith("field."):
            base["field"][key.removeprefix("field.")] = value
        else:
            base[key] = value
    base["seed"] = train_seed
    return base


def default_spread(runs: list[dict[str, Any]], key: str = "iou") -> dict[Any, float]:
    """Per scene, the range (max - min) of the default's figure ``key`` over its training seeds: the
    noise a family's paired difference on that scene must exceed to count (one seed: none)."""
    by_scene: dict[Any, list[float]] = {}
    for r in runs:
        if r["config"] == "default" and "error" not in r and _measured(r.get(key)):
            by_scene.setdefault(scene_key(r["seed"]), []).append(r[key])
    return {k: max(v) - min(v) for k, v in by_scene.items() if len(v) > 1}


def beyond_spread(deltas: dict[Any, float], spread: dict[Any, float]) -> str:
    """How many scenes' paired IoU differences ``deltas`` (scene -> difference) exceed the default's
    spread there, lower and higher: ``"lower 3, higher 0 of 6"``; ``-`` without a measured spread."""
    scenes = [k for k in deltas if k in spread]
    if not scenes:
        return "-"
    lower = sum(deltas[k] < -spread[k] for k in scenes)
    higher = sum(deltas[k] > spread[k] for k in scenes)
    return f"lower {lower}, higher {higher} of {len(scenes)}"


def _by_scene(runs: list[dict[str, Any]]) -> list[tuple[Any, list[dict[str, Any]]]]:
    """``runs`` grouped by scene (:func:`bench_heldout.scene_key` order)."""
    groups: dict[Any, list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault(scene_key(r["seed"]), []).append(r)
    return sorted(groups.items())


def _mean_of(runs: list[dict[str, Any]], key: str) -> str:
    """Mean of ``key`` over ``runs`` (a scene's training seeds) to three decimals; ``-`` if none measured it."""
    xs = [r[key] for r in runs if _measured(r.get(key))]
    return f"{sum(xs) / len(xs):.3f}" if xs else "-"


def ablation_tables(runs: list[dict[str, Any]], names: list[str]) -> dict[str, dict]:
    """Per configuration mean ± std of each figure, IoU paired with the default's same run, and
    per scene whether that difference exceeds the default's spread over training seeds
    (:func:`default_spread`; the extra seeds of ``--spread-seeds``)."""
    ok = [r for r in runs if "error" not in r]
    ref = {(r["seed"], r["train_seed"]): r for r in ok if r["config"] == "default"}
    spread = default_spread(ok)
    spread_psnr = default_spread(ok, "best_psnr")
    shared = {r["train_seed"] for r in ok if r["config"] != "default"} or {r["train_seed"] for r in ok}

    def paired(r: dict[str, Any], key: str) -> float | None:
        d = ref.get((r["seed"], r["train_seed"]), {})
        return r[key] - d[key] if _measured(r.get(key)) and _measured(d.get(key)) else None

    rows, departures = [], []
    for name in names:
        # The default's extra training seeds measure its spread; its row is over the seeds the
        # families share, so that every row averages the same runs.
        rs = [r for r in ok if r["config"] == name and r["train_seed"] in shared]
        if not rs:
            continue
        # A figure a run could not give (no best of N without a learned set) is left out of its mean.
        xs = {k: [r[k] for r in rs if _measured(r.get(k))] for k, _ in FIELDS}
        cells = [_mean_std(xs[k], fmt) + (f" ({len(xs[k])} of {len(rs)})" if len(xs[k]) < len(rs) else "") for k, fmt in FIELDS]
        deltas = [x for r in rs if (x := paired(r, "iou")) is not None]
        off = (", ".join(f"{k}={v}" for k, v in FAMILIES[name][1].items()) if name in FAMILIES
               else "configs/osn-paper.yaml" if name == "paper" else "")
        rows.append([name, off, str(len(rs)), *cells, _mean_std(deltas, "{:+.3f}") if name != "default" else ""])
        why = (FAMILIES[name][0] if name in FAMILIES else "OSN as published: every addition off" if name == "paper"
               else "every addition on")
        per_scene = " / ".join(_mean_of(scene_runs, "iou") for _, scene_runs in _by_scene(rs))

        def per_scene_paired(key: str) -> dict[Any, float]:
            ds = {k: [x for r in v if (x := paired(r, key)) is not None] for k, v in _by_scene(rs)}
            return {k: sum(v) / len(v) for k, v in ds.items() if v}

        beyond = psnr = ""
        if name != "default":
            beyond = beyond_spread(per_scene_paired("iou"), spread)
            # Best of N's PSNR, paired: an addition may earn its place by the renders, not the set.
            d_psnr = [x for r in rs if (x := paired(r, "best_psnr")) is not None]
            psnr = _mean_std(d_psnr, "{:+.2f}") + (f" ({b})" if (b := beyond_spread(per_scene_paired("best_psnr"), spread_psnr)) != "-" else "")
        departures.append([name if name in ("default", "paper") else f"without {name}", why, per_scene, cells[0],
                           _mean_std(deltas, "{:+.3f}") if name != "default" else "", beyond,
                           cells[3], psnr, cells[6]])
    if spread:  # per scene in the order of the rows' columns; "-" where the default has one seed
        order = sorted({scene_key(r["seed"]) for r in ok if r["config"] == "default"})
        departures.append(["default's spread", "IoU range over its training seeds, per scene",
                           " / ".join(f"{spread[k]:.3f}" if k in spread else "-" for k in order), "", "", "", "", "", ""])
    per_run = [[r["config"], str(r["seed"]), str(r["train_seed"]),
                *(fmt.format(r[k]) if r.get(k) is not None else "-" for k, fmt in FIELDS),
                r.get("error") or r.get("note", "")] for r in sorted(runs, key=lambda r: (r["config"], scene_key(r["seed"]), r["train_seed"]))]
    heads = ["IoU", "precision", "recall", "best of N - highest score (dB)", "scale error of matches", "training PSNR",
             "training time (s)"]
    heads_d = ["configuration", "what the family does", "IoU per scene (mean over training seeds)", "IoU", "IoU - default's", "scenes beyond the default's spread",
               "best of N - highest score (dB)", "best of N PSNR - default's (dB; scenes beyond its spread)", "training time (s)"]
    return {"departures": table(heads_d, departures),
            # The IoU and PSNR verdicts alone, for the README.
            "departures_short": table([heads_d[i] for i in (0, 3, 4, 5, 7)], [[r[i] for i in (0, 3, 4, 5, 7)] for r in departures
                                                                              if r[0] != "default's spread"]),
            "ablation": table(["config", "switched off", "runs", *heads, "IoU - default's (paired)"], rows),
            "ablation_per_run": table(["config", "scene", "training seed", *heads, "note"], per_run)}


def plan_runs(root: Path, base: str, source: str, names: list[str], train_seeds: list[int], spread_seeds: list[int],
              seeds: list[Any], finished_only: bool) -> tuple[list[tuple], list[str]]:
    """The runs to make, each ``(row, training seed, scene, config path, label, osn demo arguments)``
    with its config written under ``root/ablation-configs`` and its directory started from the base
    run's inputs (:func:`bench_heldout.seed_work`); and, with ``finished_only``, the runs left out
    because their training has not finished (named ``"ROW scene S training seed T"``)."""
    configs = root / "ablation-configs"
    configs.mkdir(parents=True, exist_ok=True)
    jobs, not_run = [], []
    # Configuration-major: whole rows finish first, so a stopped run still leaves complete rows.
    # The default's spread seeds last: they only qualify the rows above.
    for name, t in [(n, t) for n in names for t in train_seeds] + [("default", t) for t in spread_seeds]:
        path = configs / f"{name}-s{t}.yaml"
        path.write_text(yaml.safe_dump(config_for(name, t), sort_keys=False))
        for seed in seeds:
            label = f"abl-{name}-s{t}"
            if finished_only and not (scene_dir(root, seed) / f"{label}-{source}" / ".done" / "train.json").is_file():
                not_run.append(f"{name} scene {seed} training seed {t}")
                continue
            # Oracle rows too start from the SfM base run where there is one (its preprocess wrote
            # both inputs): the same stages, so that a row's two sources differ in their inputs alone.
            jobs.append((name, t, seed, str(path), label, seed_work(root, seed, base, label, source, prefer_sfm=True)))
    return jobs, not_run


def main() -> int:
    from benchgen.scene.procedural import SPLITS, parse_seeds

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, required=True, help="a bench_heldout.py root of the development split")
    ap.add_argument("--base", default="default", help="the bench_heldout.py label whose runs every run starts from: its "
                    "SfM runs (LABEL-colmap) where they exist, whose preprocess stage wrote the oracle's inputs too")
    ap.add_argument("--seeds", type=int, default=3, help="the first K development seeds (default: 3)")
    ap.add_argument("--seed-list", default=None, help="explicit development seeds instead (A:B or a list)")
    ap.add_argument("--presets", default="", help="suite presets added to the scenes, comma-separated (their base runs "
                    "from bench_heldout.py --presets)")
    ap.add_argument("--families", default=",".join(FAMILIES), help=f"families to switch off (default: all: {', '.join(FAMILIES)})")
    ap.add_argument("--paper", action="store_true", help="also train configs/osn-paper.yaml")
    ap.add_argument("--train-seeds", default="0", help="training seeds, comma-separated (default: 0)")
    ap.add_argument("--spread-seeds", default="", help="extra training seeds of the default alone, comma-separated: its "
                    "IoU range per scene over all its seeds is the spread a family's difference must exceed")
    ap.add_argument("--source", choices=("colmap", "oracle"), default="colmap", help="inputs (default: colmap, the published "
                    "path); oracle runs start from the same SfM base runs where there are, so only the inputs differ")
    ap.add_argument("--finished-only", action="store_true", help="tables from the runs whose training finished (an "
                    "unfinished run's evaluation completes); the others are listed as not run, none is started")
    ap.add_argument("-n", type=int, default=1000, help="sampled configurations N (default: 1000)")
    ap.add_argument("--max-views", type=int, default=30, help="test views per ground truth (default: 30)")
    add_executor_args(ap)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "ablation.json", help="results JSON")
    args = ap.parse_args()
    print_command()
    split = SPLITS["development"]
    seeds = parse_seeds(args.seed_list) if args.seed_list else list(split)[: args.seeds]
    if outside := [s for s in seeds if s not in split]:
        ap.error(f"seeds {outside} are not in the development split (never tune on held-out seeds)")
    seeds += presets_arg(ap, args.presets, "development")
    families = [f for f in args.families.split(",") if f]
    if bad := [f for f in families if f not in FAMILIES]:
        ap.error(f"unknown family {bad[0]!r} (expected one of {', '.join(FAMILIES)})")
    train_seeds = [int(s) for s in args.train_seeds.split(",") if s]
    spread_seeds = [t for s in args.spread_seeds.split(",") if s and (t := int(s)) not in train_seeds]
    names = ["default", *families, *(["paper"] if args.paper else [])]
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    threads = max(1, cores // max(1, args.jobs))
    jobs, not_run = plan_runs(args.root, args.base, args.source, names, train_seeds, spread_seeds, seeds, args.finished_only)
    jobs = [(name, t, seed, (seed, args.source, args.root, path, label, args.n, args.max_views, threads, extra))
            for name, t, seed, path, label, extra in jobs]
    if not_run:
        print(f"not run ({len(not_run)}, --finished-only): " + "; ".join(not_run), flush=True)
    runs: list[dict[str, Any]] = []
    t0 = time.perf_counter()

    def report(name: str, t: int, r: dict[str, Any]) -> None:
        r = {**r, "config": name, "train_seed": t}
        runs.append(r)
        text = r.get("error") or " ".join(f"{k} {fmt.format(r[k])}" for k, fmt in FIELDS if r.get(k) is not None)
        print(f"{name} scene {r['seed']} training seed {t}: {text} ({r['seconds']:.0f} s)", flush=True)

    if args.executor == "ray":
        import ray

        ray.init(address=args.address)
    for (name, t), r in run_parallel(run_one, [((name, t), a) for name, t, _, a in jobs], args.jobs, args.executor, threads):
        report(name, t, r)
    return finish_parallel(args.out, "ablation", ablation_tables(runs, names),
                           {"split": "development", "seeds": seeds, "train_seeds": train_seeds, "spread_seeds": spread_seeds,
                            "source": args.source, "not_run": not_run,
                            "base": args.base, "families": {f: {"why": FAMILIES[f][0], "off": FAMILIES[f][1]} for f in families}},
                           t0, args.jobs, ROOT, runs)

if __name__ == "__main__":
    sys.exit(main())

"""OSN on scenes nobody tuned it on: K seeds of the procedural family, from SfM inputs and the oracle's.

For each seed of the chosen split (``benchgen/scene/procedural.py``; report on ``held-out``, tune on
``development``): the family's dataset at its default size (64 px, G = 20, 30 test views), then
``osn demo`` on it exactly as a user runs it (``--spec`` of the dataset's own spec, SfM at the
demo's resolution with ``--inputs-from colmap``, or ``--inputs-from oracle``; ``-n 1000``,
``--max-views 30``), each source in its own work directory sharing the one dataset. Per run:
valid-set IoU / precision / recall against the exact region, best of N minus the highest-score
solution (dB, through the scorer), the mean scale error of the matches, training PSNR and time.
Per source: mean ± std over seeds and the worst seed's IoU. Everything resumes (datasets and demo
stages), so a killed run is rerun with the same command. ``--with LABELS`` puts the finished runs of
other configurations of the same root (``--label paper --inputs-of default`` runs, say) in the
same tables, read from their reports without running anything.

``--presets`` adds suite presets to the development split's scenes at the family's size (64 px,
G = 20; the defaults were tuned on them, so never in a held-out report): ``PRESET`` in a table's
scene column where a seed stands otherwise.

Runs go in ``--jobs`` parallel processes (each with the machine's cores shared out) or, with
``--executor ray``, as Ray tasks on a cluster with a shared file system (``--address``). Prints the
command first, then one row per run as it finishes and the pooled table; writes ``--out`` (JSON,
the layout of ``results_json.py``). Run:

    .venv/bin/python benchmarks/bench_heldout.py --root /tmp/heldout --seeds 3 [--split held-out]
        [--sources colmap,oracle] [--config configs/osn-paper.yaml --label paper] [--jobs 2]
        [--split development --presets dining-table,chessboard-8] [--with paper]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Union

from results_json import table

from benchutil import add_executor_args, finish_parallel, print_command, run_parallel
from osn.cli.stages import stage_error

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("colmap", "oracle")
#: Attempts of a run refused because its dataset is in use (see ``run_one``).
RETRIES_IN_USE = 10

#: A scene: a seed of the procedural family or the name of a suite preset.
Scene = Union[int, str]


def scene_dir(root: Path, scene: Scene) -> Path:
    """Where ``scene``'s dataset and runs live: ``root/random-SEED`` or ``root/preset-NAME``."""
    return root / (f"random-{scene}" if isinstance(scene, int) else f"preset-{scene}")


def scene_key(scene: Scene) -> tuple:
    """Sort key of scenes: seeds in order, then presets by name."""
    return (1, scene) if isinstance(scene, str) else (0, scene)


def scene_spec(scene: Scene) -> Any:
    """The spec of a family seed, or of a preset at the family's size (resolution, G)."""
    from benchgen.scene.procedural import DEFAULTS, random_spec
    from benchgen.scene.spec import load_preset

    if isinstance(scene, int):
        return random_spec(scene)
    return load_preset(scene).with_overrides(resolution=DEFAULTS["resolution"], configs=DEFAULTS["configs"])


#: Demo stages whose outputs depend on the scene and the inputs only: copied from the base run.
UPSTREAM_STAGES = ("generate", "sfm-video", "preprocess", "ground-truth")
UPSTREAM_DIRS = ("sfm", "sfm_video", "oracle")


def seed_work(root: Path, seed: Scene, base: str, label: str, source: str, prefer_sfm: bool = False) -> list[str]:
    """Start ``SCENE/LABEL-SOURCE`` from the base run ``SCENE/BASE-SOURCE``'s inputs (its upstream
    stage records and outputs, hard links where the file system allows), so ``osn demo`` resumes at
    training; the ``osn demo`` arguments its records need (a base run from SfM inputs recorded the
    size of its SfM video, which oracle inputs alone would not ask for).

    A preprocess stage writes both the oracle's and SfM's inputs, so with ``prefer_sfm`` any run
    starts from the SfM base run ``SCENE/BASE-colmap`` where that finished its inputs: then a
    scene's runs from the two sources differ in their inputs alone."""
    here = scene_dir(root, seed)
    finished = lambda run: all((run / ".done" / f"{s}.json").is_file() for s in ("preprocess", "ground-truth"))  # noqa: E731
    src = here / f"{base}-colmap"
    if not (prefer_sfm and finished(src)):
        src = here / f"{base}-{source}"
    if not finished(src):
        raise SystemExit(f"{src}: no finished inputs to start from (run bench_heldout.py --label {base} first)")
    options = json.loads((src / ".done" / "preprocess.started.json").read_text()).get("options", {})
    extra = ["--sfm-resolution", str(options["sfm_resolution"])] if "sfm_resolution" in options else []
    dst = here / f"{label}-{source}"
    if (dst / ".done").is_dir():
        return extra
    tmp = dst.with_name(dst.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / ".done").mkdir(parents=True)
    for stage in UPSTREAM_STAGES:
        for suffix in (".json", ".started.json"):
            if (f := src / ".done" / f"{stage}{suffix}").is_file():
                shutil.copy2(f, tmp / ".done" / f.name)
    for d in UPSTREAM_DIRS:
        if (src / d).is_dir():
            shutil.copytree(src / d, tmp / d, copy_function=_link_or_copy)
    (tmp / "dataset").symlink_to((here / "dataset").resolve(), target_is_directory=True)
    tmp.rename(dst)
    return extra


def _link_or_copy(a: str, b: str) -> None:
    try:
        os.link(a, b)
    except OSError:
        shutil.copy2(a, b)


def dataset_for(seed: Scene, root: Path, threads: int) -> Path:
    """The dataset of ``seed`` (:func:`scene_spec`) under :func:`scene_dir` (generated or resumed)."""
    from benchgen.scene.spec import dump_spec

    d = scene_dir(root, seed)
    d.mkdir(parents=True, exist_ok=True)
    spec = d / "spec.yaml"
    if not spec.is_file():
        spec.write_text(dump_spec(scene_spec(seed)))
    cmd = [sys.executable, "-m", "benchgen.cli", "generate", "--spec", str(spec), "--out", str(d / "dataset"), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(threads))
    if proc.returncode != 0:
        raise RuntimeError(f"seed {seed}: benchgen generate failed: {(proc.stderr.strip().splitlines() or ['?'])[-1]}")
    return d / "dataset"


def _dataset_or_error(seed: Scene, root: Path, threads: int) -> str | None:
    try:
        dataset_for(seed, root, threads)
    except RuntimeError as e:
        return str(e)
    return None


def _env(threads: int) -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


def run_one(seed: Scene, source: str, root: Path, config: str | None, label: str, n: int, max_views: int, threads: int,
            extra: Sequence[str] = ()) -> dict[str, Any]:
    """``osn demo`` of one seed from one source on its dataset (already generated), with ``extra``
    arguments (:func:`seed_work`'s); its figures (or ``error``)."""
    t0 = time.perf_counter()
    dataset = scene_dir(root, seed) / "dataset"
    work = dataset.parent / f"{label}-{source}"
    work.mkdir(parents=True, exist_ok=True)
    link = work / "dataset"
    if not link.exists():
        link.symlink_to(dataset.resolve(), target_is_directory=True)
    cmd = [sys.executable, "-m", "osn.cli", "demo", "--work", str(work), "--spec", str(dataset / "spec.yaml"),
           "--inputs-from", source, "-n", str(n), "--max-views", str(max_views), "--workers", "1"]
    if config:
        cmd += ["--config", config]
    cmd += list(extra)
    for _ in range(RETRIES_IN_USE):
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(threads))
        # The seed's other run may hold the shared dataset's lock for the seconds its generate and
        # ground-truth stages take to find everything rendered: wait and resume.
        if proc.returncode == 0 or "in use by" not in proc.stderr:
            break
        time.sleep(30)
    (work / "bench.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        if (found := empty_set_figures(work)) is not None:
            return {"seed": seed, "source": source, **found, "seconds": time.perf_counter() - t0}
        error = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"seed": seed, "source": source, "error": error, "seconds": time.perf_counter() - t0}
    return {"seed": seed, "source": source, **figures(work), "seconds": time.perf_counter() - t0}


def empty_set_figures(work: Path) -> dict[str, Any] | None:
    """The figures of a demo work directory whose training finished and whose learned set holds
    no configuration the search finds: a later stage (the sampler, or the export's learned
    intervals) stopped on ``EmptyValidSet``, read from that stage's record; None for any other
    failure.

    A result, not a crash: the valid-set figures are the evaluation's where it ran (on the
    sampler's best-scoring draws, none of them valid), else the training monitor's last (against
    the same exact region); with no valid sample there is no best of N."""
    trained = work / ".done" / "train.json"
    errors = (stage_error(work, name) for name in ("sample", "export"))
    error = next((e for e in errors if e is not None and e["type"] == "EmptyValidSet"), None)
    if error is None or not trained.is_file():
        return None
    t = json.loads(trained.read_text())
    evaluated = work / ".done" / "evaluate.json"
    if evaluated.is_file():
        v, where = json.loads(evaluated.read_text())["summary"]["valid_set"], "the evaluation"
    else:
        v, where = _last_monitor(work / "run" / "metrics.jsonl"), "the training monitor"
    return {"iou": v.get("iou", t["summary"]["iou"]), "precision": v.get("precision"), "recall": v.get("recall"),
            "best_minus_highest_db": None, "scale_error": None, "train_psnr": t["summary"]["psnr"],
            "train_seconds": t["seconds"], **limit_figures(work, v), "note": f"no valid configuration (valid-set figures from {where}): {error['message']}"}


def limit_figures(work: Path, valid_set: dict[str, Any]) -> dict[str, Any]:
    """What limits a run's learned set (``heldout_limits``' figures) from its valid-set record:
    :func:`set_limits`, the objects SfM dropped and the IoU their absence allows."""
    return {**set_limits(valid_set.get("limits", [])), "dropped": dropped_objects(work),
            "iou_without_dropped": valid_set.get("iou_without_dropped")}


def set_limits(limits: list[dict[str, Any]]) -> dict[str, Any]:
    """The exact bounds that limit a learned set most (a report's ``valid_set.limits``): the one
    it cuts most (``largest_miss``: the pair, the share of the region missed there, and the final
    label pool's rays of that pair, None where the run did not record them) and the one it
    reaches farthest beyond (``largest_excess``: the same with its volume there in units of the
    region's); None where no bound is wrong that way."""
    out: dict[str, Any] = {}
    for key, share in (("largest_miss", "missed"), ("largest_excess", "excess")):
        worst = max(limits, key=lambda e: e[share], default=None)
        out[key] = ([worst["pair"], worst[share], worst.get("pool_rays")]
                    if worst is not None and worst[share] > 0 else None)
    return out


def dropped_objects(work: Path) -> list[str]:
    """The objects a demo run's preprocessing dropped (SfM registered none, or it contradicted its
    masks), by name, from the stage's record. They train nothing and bound nothing; only runs from
    SfM inputs train without them (the oracle's preprocessing runs SfM as a record only)."""
    rec, train = work / ".done" / "preprocess.json", work / ".done" / "train.started.json"
    if not (rec.is_file() and train.is_file()) or json.loads(train.read_text())["options"].get("inputs") != "colmap":
        return []
    return [o["name"] for o in json.loads(rec.read_text())["summary"]["objects"] if "error" in o]


def finished_figures(root: Path, seed: Scene, label: str, source: str) -> dict[str, Any] | None:
    """The figures of the run ``SCENE/LABEL-SOURCE`` as :func:`run_one` left them, read without
    running anything; None where that run did not finish (no report, and no sampler that found
    nothing after a finished training)."""
    work = scene_dir(root, seed) / f"{label}-{source}"
    if (work / "report" / "metrics.json").is_file() and (work / "stages.json").is_file():
        found = figures(work)
    else:
        found = empty_set_figures(work)
    return None if found is None else {"seed": seed, "source": source, **found, "seconds": 0.0}


def _last_monitor(path: Path) -> dict[str, Any]:
    """The last record of a run's ``metrics.jsonl`` that holds valid-set figures ({} if none)."""
    last: dict[str, Any] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            if "iou" in rec:
                last = rec
    return last


def figures(work: Path) -> dict[str, Any]:
    """The figures of a finished demo work directory (its report and stage records)."""
    m = json.loads((work / "report" / "metrics.json").read_text())
    stages = json.loads((work / "stages.json").read_text())
    best = next(k for k in m["table"] if k.startswith("best of"))
    errors = [e for e in m.get("scale_error", []) if e is not None]
    return {
        "iou": m["valid_set"]["iou"], "precision": m["valid_set"]["precision"], "recall": m["valid_set"]["recall"],
        "best_minus_highest_db": m["table"][best]["psnr"][0] - m["table"]["highest score"]["psnr"][0],
        "best_psnr": m["table"][best]["psnr"][0], "highest_psnr": m["table"]["highest score"]["psnr"][0],
        "scale_error": statistics.fmean(errors) if errors else None,
        "train_psnr": stages["train"]["summary"]["psnr"], "train_seconds": stages["train"]["seconds"],
        "stage_seconds": {k: round(r["seconds"]) for k, r in stages.items()},
        **limit_figures(work, m["valid_set"]),
        **({} if _measured(m["valid_set"]["iou"]) else
           {"note": "IoU not measured: " + m["valid_set"].get("not_measured", "no point of the exact region in the learned "
                    f"scale box ({m['extra'].get('gt_outside_scale_box', '?')} ground truths outside it)")}),
    }


def _measured(x: Any) -> bool:
    return x is not None and math.isfinite(x)


def _mean_std(xs: list[float], fmt: str) -> str:
    """``mean ± std`` (sample standard deviation; a single value alone)."""
    if not xs:
        return "-"
    if len(xs) == 1:
        return fmt.format(xs[0])
    return f"{fmt.format(statistics.fmean(xs))} ± {fmt.replace('+', '').format(statistics.stdev(xs))}"


FIELDS = (("iou", "{:.3f}"), ("precision", "{:.3f}"), ("recall", "{:.3f}"), ("best_minus_highest_db", "{:+.2f}"),
          ("scale_error", "{:.3f}"), ("train_psnr", "{:.2f}"), ("train_seconds", "{:.0f}"))
HEADERS = ["IoU", "precision", "recall", "best of N - highest score (dB)", "scale error of matches", "training PSNR",
           "training time (s)"]


def tables(runs: list[dict[str, Any]]) -> dict[str, dict]:
    """Per run and pooled per configuration (``config``, in the order runs name it) and source."""
    ok = [r for r in runs if "error" not in r]
    labels = list(dict.fromkeys(r["config"] for r in runs))
    order = lambda r: (labels.index(r["config"]), scene_key(r["seed"]), r["source"])  # noqa: E731
    per_seed = [[r["config"], str(r["seed"]), r["source"], *(fmt.format(r[k]) if r.get(k) is not None else "-" for k, fmt in FIELDS),
                 r.get("note", "")] for r in sorted(ok, key=order)]
    per_seed += [[r["config"], str(r["seed"]), r["source"], *["-"] * len(FIELDS), f"failed: {r['error']}"]
                 for r in sorted(runs, key=order) if "error" in r]
    pooled = []
    for label in labels:
        for source in SOURCES:
            rs = [r for r in ok if r["source"] == source and r["config"] == label]
            if not rs:
                continue
            # A figure a run could not give (no best of N from an empty learned set) is left out of
            # its mean; the count beside it says how many runs it averages.
            cells = []
            for k, fmt in FIELDS:
                # NaN: not measured (the valid-set accuracy's rule when no point of the exact
                # region fell in the scale box the run learned in), left out like None.
                xs = [r[k] for r in rs if _measured(r.get(k))]
                cells.append(_mean_std(xs, fmt) + (f" ({len(xs)} of {len(rs)})" if len(xs) < len(rs) else ""))
            ious = [r["iou"] for r in rs if _measured(r.get("iou"))]
            pooled.append([label, source, str(len(rs)), *cells, f"{min(ious):.3f}" if ious else "-"])
    heads = ["config", "inputs", "seeds", *HEADERS, "worst seed's IoU"]
    # README's: the set, best of N's margin, the time and the worst seed.
    short = [heads.index(c) for c in ("config", "inputs", "seeds", "IoU", "best of N - highest score (dB)",
                                      "training time (s)", "worst seed's IoU")]
    limits = [[r["config"], str(r["seed"]), r["source"], fmt_limit(r.get("largest_miss"), "{:.1%}"),
               fmt_limit(r.get("largest_excess"), "{:.3g}"), ", ".join(r.get("dropped", [])) or "-",
               "-" if r.get("iou_without_dropped") is None else f"{r['iou_without_dropped']:.3f}"]
              for r in sorted(ok, key=order)]
    return {"heldout_pooled": table(heads, pooled),
            "heldout_short": table([heads[i] for i in short], [[r[i] for i in short] for r in pooled]),
            "heldout_per_seed": table(["config", "scene", "inputs", *HEADERS, "note"], per_seed),
            "heldout_limits": table(["config", "scene", "inputs", "largest miss: bound (share of the region)",
                                     "largest excess: bound (volume / the region's)", "dropped by SfM",
                                     "IoU without the dropped objects' bounds"], limits)}


def fmt_limit(limit: list | None, fmt: str) -> str:
    """``pair (share; N label rays)`` of :func:`set_limits`; ``-`` for none (or a run without a report)."""
    if limit is None:
        return "-"
    rays = f"; {limit[2]} label rays" if len(limit) > 2 and limit[2] is not None else ""
    return f"{limit[0]} ({fmt.format(limit[1])}{rays})"


def presets_arg(ap: argparse.ArgumentParser, text: str, split: str) -> list[str]:
    """The ``--presets`` names (comma-separated); an argparse error for an unknown name, or for any
    preset with a split other than ``development`` (the defaults were tuned on them)."""
    from benchgen.scene.spec import preset_names

    names = [x for x in text.split(",") if x]
    if bad := [x for x in names if x not in preset_names()]:
        ap.error(f"unknown preset {bad[0]!r} (expected one of {', '.join(preset_names())})")
    if names and split != "development":
        ap.error("--presets: suite presets are development scenes (the defaults were tuned on them), "
                 f"not for the {split} split")
    return names


def main() -> int:
    from benchgen.scene.procedural import SPLITS, parse_seeds

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, required=True, help="working directory (datasets and runs; resumed)")
    ap.add_argument("--split", choices=tuple(SPLITS), default="held-out", help="which split's seeds (default: held-out)")
    ap.add_argument("--seeds", type=int, default=3, help="the first K seeds of the split (default: 3)")
    ap.add_argument("--seed-list", default=None, help="explicit seeds instead (A:B or a list); must lie in --split")
    ap.add_argument("--presets", default="", help="suite presets added to the scenes at the family's size, comma-separated "
                    "(development split only: the defaults were tuned on them)")
    ap.add_argument("--sources", default="colmap,oracle", help="inputs to train from (default: colmap,oracle)")
    ap.add_argument("--config", default=None, help="YAML training config passed to osn demo (default: the CPU defaults)")
    ap.add_argument("--label", default="default", help="name of the config in the table and the run directories")
    ap.add_argument("--inputs-of", default=None, metavar="LABEL",
                    help="start every run from the SfM, oracle and ground-truth stages of LABEL's finished runs "
                         "(train and evaluate only: a new training config on the same inputs)")
    ap.add_argument("--with", dest="also", default="", metavar="LABELS",
                    help="comma-separated labels whose finished runs of the same scenes and sources join the tables "
                         "beside --label's (read, never started; the ones not finished are listed)")
    ap.add_argument("--conditions", default="", metavar="TEXT",
                    help="what the tables' provenance line should add (runs resumed from an older commit, other load)")
    ap.add_argument("-n", type=int, default=1000, help="sampled configurations N (default: 1000)")
    ap.add_argument("--max-views", type=int, default=30, help="test views per ground truth (default: 30)")
    add_executor_args(ap)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "heldout.json", help="results JSON")
    args = ap.parse_args()
    print_command()
    split = SPLITS[args.split]
    seeds = parse_seeds(args.seed_list) if args.seed_list else list(split)[: args.seeds]
    if outside := [s for s in seeds if s not in split]:
        ap.error(f"seeds {outside} are not in the {args.split} split")
    seeds += presets_arg(ap, args.presets, args.split)
    sources = [s for s in args.sources.split(",") if s]
    if bad := [s for s in sources if s not in SOURCES]:
        ap.error(f"unknown source {bad[0]!r} (expected colmap or oracle)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    threads = max(1, cores // max(1, args.jobs))
    # Source-major, so that a seed's two runs rarely start together (they share its dataset).
    jobs = [(seed, src) for src in sources for seed in seeds]
    extra = {(seed, src): seed_work(args.root, seed, args.inputs_of, args.label, src) if args.inputs_of else []
             for seed, src in jobs}
    runs: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    job_args = lambda seed, src: (seed, src, args.root, args.config, args.label, args.n, args.max_views, threads,  # noqa: E731
                                  extra[seed, src])

    def report(r: dict[str, Any], label: str = args.label) -> None:
        r = {**r, "config": label}
        runs.append(r)
        text = r.get("error") or " ".join(f"{k} {fmt.format(r[k])}" for k, fmt in FIELDS if r.get(k) is not None)
        print(f"{label} seed {r['seed']} {r['source']}: {text} ({r['seconds']:.0f} s)", flush=True)

    failed: dict[int, str] = {}
    if args.executor == "ray":
        import ray

        ray.init(address=args.address)
    made = [(s, (s, args.root, threads)) for s in seeds]
    for seed, err in run_parallel(_dataset_or_error, made, args.jobs, args.executor, threads):
        if err:
            failed[seed] = err
    calls = [((s, src), job_args(s, src)) for s, src in jobs if s not in failed]
    for _, r in run_parallel(run_one, calls, args.jobs, args.executor, threads):
        report(r)
    for seed, err in failed.items():
        for src in sources:
            report({"seed": seed, "source": src, "error": err, "seconds": 0.0})
    not_finished, also = [], [x for x in args.also.split(",") if x]
    for label in also:
        for seed, src in jobs:
            if (r := finished_figures(args.root, seed, label, src)) is not None:
                report(r, label)
            else:
                not_finished.append(f"{label} seed {seed} {src}")
    if not_finished:
        print(f"not finished ({len(not_finished)}, --with): " + "; ".join(not_finished), flush=True)
    return finish_parallel(args.out, "heldout", tables(runs),
                           {"split": args.split, "seeds": seeds, "label": args.label, "config": args.config,
                            "with": also, "not_finished": not_finished,
                            **({"conditions": args.conditions} if args.conditions else {})},
                           t0, args.jobs, ROOT, runs)

if __name__ == "__main__":
    sys.exit(main())

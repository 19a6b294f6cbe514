"""``osn demo``: the whole pipeline on the embedded Gnome-House scene, resumable stage by stage.

benchgen generate -> per-object SfM (pycolmap) and oracle inputs -> train -> sample N ->
best-of-N evaluation and report -> export -> Blender add-on zip. Each stage records its wall time
(``WORK/stages.json``); running the same command again skips finished stages and resumes the
interrupted one (generation and training resume internally).
"""

from __future__ import annotations

import argparse
import logging
import shlex
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from scenecore.cli import UserError, subcommand

from osn.cli.stages import Stage, run_stages

log = logging.getLogger(__name__)


def _scaled_config(iterations: int | None, config_file: str | None):
    """Training config, with every phase length scaled so field iterations total ``iterations``."""
    from osn.train import TrainConfig

    cfg = TrainConfig.from_yaml(config_file) if config_file else TrainConfig()
    if iterations:
        total = cfg.stage1_iters + cfg.rounds * cfg.field_iters
        f = iterations / max(total, 1)
        cfg = replace(
            cfg,
            stage1_iters=max(1, round(cfg.stage1_iters * f)),
            field_iters=max(1, round(cfg.field_iters * f)),
            scale_iters=max(1, round(cfg.scale_iters * f)),
            final_scale_iters=max(1, round(cfg.final_scale_iters * f)),
        )
    return cfg


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"field": {"kind": ...}}`` -> ``{"field.kind": ...}``, so a difference names its key."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def demo_command(args: argparse.Namespace) -> str:
    """The ``osn demo`` command line that reproduces ``args`` (every option, defaults included)."""
    parts = ["osn", "demo"]
    for k, v in sorted(vars(args).items()):
        if k in ("func", "debug", "resume_hint") or v is None:
            continue
        parts += ["-n" if k == "n" else f"--{k.replace('_', '-')}", str(v)]
    return shlex.join(parts)


def run_demo(args: argparse.Namespace) -> dict[str, Any]:
    """Run (or resume) every stage under ``args.work``; returns the stage records."""
    work = Path(args.work)
    dataset, sfm, oracle_dir, run_dir = work / "dataset", work / "sfm", work / "oracle", work / "run"
    report_dir, export_dir = work / "report", work / "export"
    train_cfg = _scaled_config(args.iterations, args.train_config)  # also what the train stage depends on

    def generate() -> dict:
        from benchgen.render.generate import generate as gen
        from benchgen.scene.spec import load_preset, spec_from_dict

        spec = load_preset(args.preset)
        if args.resolution or args.configs:
            d = spec.to_dict()
            if args.resolution:
                d["resolution"] = [args.resolution, args.resolution]
            if args.configs:
                d["configs"] = args.configs
            spec = spec_from_dict(d, f"{args.preset} (demo overrides)")
        s = gen(spec, dataset, workers=args.workers, progress=True)
        if not s.passed:
            raise UserError(f"{dataset}: the generated benchmark failed its invariance verification (see verification.json)")
        for line in s.lines():
            print(f"  {line}")
        return {"frames_rendered": s.frames_rendered, "render_seconds": s.render_seconds}

    def preprocess() -> dict:
        from scenecore import dataset as D
        from scenecore.dataset import atomic_write_json

        from osn.preprocess.inputs import InputsError, save_inputs
        from osn.preprocess.oracle import oracle_inputs
        from osn.preprocess.sfm import PreprocessConfig
        from osn.preprocess.video import preprocess_dataset

        video = D.read_training_video(dataset, D.load_scene(dataset))  # read once for both
        save_inputs(oracle_dir, oracle_inputs(dataset, video=video))
        try:
            inputs, report = preprocess_dataset(dataset, PreprocessConfig(on_failure="skip"),
                                                progress=lambda m: print(f"  {m} ...", flush=True), video=video)
        except InputsError as e:
            if args.inputs == "colmap":
                raise
            # The oracle path goes on; the SfM failure is part of the result.
            print(f"  SfM failed: {e}")
            return {"sfm_error": str(e)}
        save_inputs(sfm, inputs)
        atomic_write_json(sfm / "preprocess_report.json", {"objects": report.objects, "dropped": report.dropped})
        for r in report.objects:
            if "error" in r:
                print(f"  SfM dropped object {r['id']} ({r['name']}): {r['error']}")
            elif "rotation_error_deg_max" in r:
                print(f"  SfM object {r['id']} ({r['name']}): {100 * r['registered_fraction']:.0f}% of frames, "
                      f"rotation error max {r['rotation_error_deg_max']:.2f} deg")
        return {"objects": report.objects, "dropped": report.dropped}

    def train() -> dict:
        from osn.preprocess.inputs import load_inputs
        from osn.cli.train import train_on_dataset
        from osn.train import read_metrics

        resume = (run_dir / "checkpoint.pt").exists()
        inputs = None if resume else load_inputs(sfm if args.inputs == "colmap" else oracle_dir)
        train_on_dataset(dataset, run_dir, train_cfg, inputs=inputs, resume=resume)  # measured against its exact region
        last = read_metrics(run_dir / "metrics.jsonl")[-1]
        print(f"  training: PSNR {last.get('psnr', float('nan')):.2f} dB, valid-set IoU {last.get('iou', float('nan')):.3f} "
              f"after {last['wall_time']:.0f} s")
        return {k: last.get(k) for k in ("psnr", "iou", "wall_time", "iteration")}

    def sample() -> dict:
        from osn.model.run import load_run
        from osn.sample.configurations import sample_configurations

        s = sample_configurations(load_run(run_dir), args.n, args.threshold, args.seed)
        s.save(run_dir / "samples.npz")
        return {"n": len(s.sbar), "fell_back": s.fell_back}

    def evaluate() -> dict:
        from osn.evaluate.bestofn import EvalConfig
        from osn.evaluate.bestofn import evaluate as ev
        from osn.evaluate.report import write_report
        from osn.model.run import load_run
        from osn.sample.configurations import Samples

        run = load_run(run_dir)
        res = ev(run, dataset, Samples.load(run_dir / "samples.npz"), EvalConfig(max_views=args.max_views))
        write_report(res, report_dir, run_dir, demo_command(args))
        return {"table": res.table, "valid_set": res.valid_set, "scale_error": res.scale_error}

    def export() -> dict:
        from osn.export.from_run import export_run

        # the configurations the sample stage drew and evaluated, and the dataset's test cameras
        export_run(run_dir, export_dir, dataset=dataset)
        return {}

    def addon() -> dict:
        from osn.export.addon_build import build_addon_zip

        z = build_addon_zip(work)
        return {"zip": str(z)}

    # What each stage's outputs depend on: a rerun with other values stops instead of mixing them.
    train_options = {f"train.{k}": v for k, v in _flat(train_cfg.to_dict()).items()}
    stages = [
        Stage("generate", f"benchgen: render the {args.preset} benchmark", generate,
              {"preset": args.preset, "resolution": args.resolution, "configs": args.configs}),
        Stage("preprocess", "per-object SfM (pycolmap) and oracle inputs", preprocess),
        Stage("train", f"train per-object fields and the scale network on {args.inputs} inputs", train,
              {"inputs": args.inputs, **train_options}),
        Stage("sample", f"draw {args.n} valid configurations", sample,
              {"n": args.n, "threshold": args.threshold, "seed": args.seed}),
        Stage("evaluate", "best-of-N evaluation against every ground truth", evaluate, {"max_views": args.max_views}),
        Stage("export", "export volumes, meshes, trajectories and the scale network", export),
        Stage("addon", "build the Blender add-on zip", addon),
    ]
    return run_stages(stages, work)


def _cmd_demo(args: argparse.Namespace) -> int:
    from osn.evaluate.report import summary_lines

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    records = run_demo(args)
    work = Path(args.work)
    ev = records["evaluate"]["summary"]
    print()
    print("\n".join(summary_lines(ev["table"], ev["valid_set"], ev["scale_error"])))
    print("stage times: " + ", ".join(f"{k} {r['seconds']:.0f} s" for k, r in records.items()))
    print(f"total this invocation: {time.perf_counter() - t0:.0f} s")
    print(f"report:  {work / 'report' / 'report.md'}")
    print(f"export:  {work / 'export'}")
    print(f"add-on:  {records['addon']['summary']['zip']}  (Blender: Edit > Preferences > Get Extensions > Install from Disk)")
    return 0


def add_demo_parser(sub: argparse._SubParsersAction) -> None:
    p = subcommand(sub, "demo", _cmd_demo, "run the whole pipeline on the embedded Gnome-House scene (resumable)",
                   description="Generate the benchmark, preprocess (SfM + oracle), train, sample N configurations, "
                   "evaluate best-of-N against every ground truth, export for Blender and build the add-on. Run it "
                   "again to resume: finished stages are skipped.")
    p.add_argument("--work", default="runs/demo", help="working directory for every output")
    p.add_argument("--preset", default="gnome-house-demo", help="benchgen preset (see `benchgen presets`)")
    p.add_argument("--resolution", type=int, default=None, help="square image size (default: the preset's)")
    p.add_argument("--configs", type=int, default=None, help="ground-truth configurations G (default: the preset's)")
    p.add_argument("--iterations", type=int, default=None,
                   help="field iterations in total (stage 1 + rounds); every phase is scaled (default: the CPU config's)")
    p.add_argument("--train-config", help="YAML training config (default: the built-in CPU config)")
    p.add_argument("--inputs", choices=["oracle", "colmap"], default="oracle",
                   help="train on oracle per-object inputs (perfect SfM) or on the pycolmap output")
    p.add_argument("-n", type=int, default=1000, help="number of sampled configurations N")
    p.add_argument("--threshold", type=float, default=0.5, help="validity threshold of sampling")
    p.add_argument("--max-views", type=int, default=30, help="test views evaluated per ground truth (0 = all)")
    p.add_argument("--workers", type=int, default=2, help="rendering processes for benchgen")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled configurations (the export carries those)")

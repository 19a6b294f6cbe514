"""``osn demo``: the whole pipeline on a preset (the embedded Gnome-House scene by default) or on
the user's own scene spec (``--spec FILE``), resumable stage by stage.

benchgen generate (the video, the exact region, the configurations) -> per-object SfM (pycolmap)
and oracle inputs -> train -> sample N -> best-of-N evaluation and report -> export -> Blender
add-on zip. The ground truths' test views and their verification (``benchgen generate``'s
slowest part, read only by the evaluation) render in the background at the lowest CPU priority
while training runs on one core. Each stage records its wall time
(``WORK/stages.json``); running the same command again skips finished stages and resumes the
interrupted one (generation and training resume internally).
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import shlex
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch

from scenecore import dataset as D
from scenecore.atomic import atomic_write_json
from scenecore.cli import UserError, deprecated_alias, subcommand

from benchgen.render.generate import generate
from benchgen.scene.spec import SceneSpec, dump_spec, load_preset, load_spec, spec_from_dict
from osn.cli.preprocess import add_sfm_size_options, auto_or_int
from osn.cli.stages import BackgroundCommand, Stage, run_stages
from osn.cli.train import add_config_options, train_on_dataset, training_config
from osn.evaluate.bestofn import EvalConfig, evaluate
from osn.evaluate.report import summary_lines, write_report
from osn.export.addon_build import build_addon_zip
from osn.export.from_run import export_run
from osn.model.run import load_run
from osn.preprocess.inputs import InputsError, load_inputs, save_inputs, with_video
from osn.preprocess.oracle import oracle_inputs
from osn.preprocess.sfm import PreprocessConfig, pipeline_config
from osn.preprocess.video import preprocess_dataset, training_inputs
from osn.sample.configurations import Samples, sample_configurations
from osn.train import read_metrics
from osn.train.run_config import upgrade_run_config

log = logging.getLogger(__name__)


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"field": {"kind": ...}}`` -> ``{"field.kind": ...}``, so a difference names its key."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`_flat`."""
    out: dict[str, Any] = {}
    for key, v in flat.items():
        *parents, last = key.split(".")
        node = out
        for k in parents:
            node = node.setdefault(k, {})
        node[last] = v
    return out


def recorded_train_options(old: dict[str, Any]) -> dict[str, Any]:
    """The train stage's options as an older version recorded them, read as today's
    (:func:`osn.train.run_config.upgrade_run_config`: options added since at the value the run
    trained with, removed ones dropped where they held today's value); ``ValueError`` where not."""
    train = {k[len("train."):]: v for k, v in old.items() if k.startswith("train.")}
    today = upgrade_run_config(_nest(train))
    return {**{k: v for k, v in old.items() if not k.startswith("train.")},
            **{f"train.{k}": v for k, v in _flat(today).items()}}


def demo_command(args: argparse.Namespace) -> str:
    """The ``osn demo`` command line that reproduces ``args`` (every option, defaults included)."""
    parts = ["osn", "demo"]
    for k, v in sorted(vars(args).items()):
        if k in ("func", "debug", "resume_hint") or v is None:
            continue
        parts += ["-n" if k == "n" else f"--{k.replace('_', '-')}", str(v)]  # every dest is its option's name
    return shlex.join(parts)


@dataclass(frozen=True)
class DemoPaths:
    """Where each stage of ``osn demo`` writes, under ``--work``."""
    work: Path

    @property
    def dataset(self) -> Path:
        return self.work / "dataset"

    @property
    def ground_truth_log(self) -> Path:
        return self.work / "ground-truth.log"

    @property
    def sfm(self) -> Path:
        return self.work / "sfm"

    @property
    def sfm_video(self) -> Path:
        return self.work / "sfm_video"

    @property
    def oracle(self) -> Path:
        return self.work / "oracle"

    @property
    def run(self) -> Path:
        return self.work / "run"

    @property
    def report(self) -> Path:
        return self.work / "report"

    @property
    def candidates(self) -> Path:
        return self.work / "candidates"

    @property
    def export(self) -> Path:
        return self.work / "export"


# Each stage is a function of the options and the paths, run by osn.cli.stages (skip when done,
# refuse changed options).


#: The scene of ``osn demo`` without ``--preset`` or ``--spec``.
DEFAULT_PRESET = "gnome-house-demo"


def _scene(args: argparse.Namespace) -> SceneSpec:
    """The scene as given: ``--spec FILE``, else ``--preset NAME`` (default :data:`DEFAULT_PRESET`)."""
    return load_spec(args.spec) if args.spec else load_preset(args.preset or DEFAULT_PRESET)


def _scene_name(args: argparse.Namespace) -> str:
    return str(args.spec) if args.spec else args.preset or DEFAULT_PRESET


def _scene_options(args: argparse.Namespace) -> dict[str, str]:
    """What the rendered stages record of the scene: the preset's name, or a digest of the spec's
    content (an edited spec file is another scene; a moved one is not)."""
    if args.spec:
        return {"spec_sha256": hashlib.sha256(dump_spec(_scene(args)).encode()).hexdigest()}
    return {"preset": args.preset or DEFAULT_PRESET}


def _demo_spec(args: argparse.Namespace, resolution: int | None, configs: int | None) -> SceneSpec:
    """The scene with the demo's overrides (None keeps the scene's value)."""
    spec = _scene(args)
    if not (resolution or configs):
        return spec
    d = spec.to_dict()
    if resolution:
        d["resolution"] = [resolution, resolution]
    if configs:
        d["configs"] = configs
    return spec_from_dict(d, f"{_scene_name(args)} (demo overrides)")


def _generate(spec, out: Path, args: argparse.Namespace, video_only: bool = False, ground_truth: bool = True) -> dict:
    s = generate(spec, out, workers=args.workers, progress=True, video_only=video_only, ground_truth=ground_truth)
    for line in s.lines():
        print(f"  {line}")
    return {"frames_rendered": s.frames_rendered, "render_seconds": s.render_seconds}


def stage_generate(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Render what training needs of the benchmark (the scene with the demo's resolution/configs
    overrides): the training video, the exact region and the configurations."""
    return _generate(_demo_spec(args, args.resolution, args.configs), p.dataset, args, ground_truth=False)


def ground_truth_command(args: argparse.Namespace, p: DemoPaths) -> list[str]:
    """``benchgen generate`` finishing the dataset from its own spec: the configurations' test
    views and the verification (what it already holds is not rendered again)."""
    return [sys.executable, "-m", "benchgen.cli", "generate", "--spec", str(p.dataset / "spec.yaml"),
            "--out", str(p.dataset), "--workers", str(args.workers), "--quiet"]


def _ground_truth_summary(p: DemoPaths) -> dict:
    v = D.load_verification(p.dataset)
    cfgs = v.get("configurations", [])
    return {"log": str(p.ground_truth_log), "configurations": len(cfgs), "passed": bool(v.get("passed"))}


def stage_ground_truth(args: argparse.Namespace, p: DemoPaths) -> BackgroundCommand:
    """Start rendering the ground truths' test views and verifying every configuration, beside
    the next stages (``benchgen generate`` exits 1 when a configuration fails verification)."""
    job = BackgroundCommand(ground_truth_command(args, p), p.ground_truth_log, lambda: _ground_truth_summary(p))
    print(f"  {shlex.join(job.cmd)}  (log: {job.log})")
    return job.start()


#: ``--sfm-resolution auto`` with ``--inputs-from colmap``: the training video rendered again at this
#: size (rounded up to a multiple of the benchmark's) for SfM: large enough that SfM registers
#: nearly every frame of every gnome-house object (smaller frames lose the ring-toy's first ones)
#: and the valid set learned from it holds steady over SfM and training seeds (docs/preprocess.md;
#: measurements in docs/experiments/).
SFM_SIZE = 768


def sfm_width(args: argparse.Namespace, dataset_width: int) -> int:
    """Width of the frames SfM runs on: ``--sfm-resolution``; ``auto`` is the benchmark's own frames
    with oracle inputs (SfM is then only a record) and :data:`SFM_SIZE` with SfM inputs."""
    r = args.sfm_resolution
    if r in (None, "auto"):
        return -(-SFM_SIZE // dataset_width) * dataset_width if args.inputs_from == "colmap" else dataset_width
    if r < dataset_width or r % dataset_width:
        raise UserError(f"--sfm-resolution {r} must be a multiple of the benchmark's {dataset_width} px "
                        "(SfM's poses and depths are brought down to its frames)")
    return r


def sfm_downscale(args: argparse.Namespace, dataset_width: int) -> int:
    """How many times larger the SfM video is than the benchmark's frames (1: SfM on them)."""
    return sfm_width(args, dataset_width) // dataset_width


def stage_sfm_video(args: argparse.Namespace, p: DemoPaths, width: int) -> dict:
    """The training video again at ``width`` px for SfM (the same scene; the video alone: SfM
    reads only its frames and masks, its ground truth only measures SfM's accuracy)."""
    return _generate(_demo_spec(args, width, None), p.sfm_video, args, video_only=True)


def demo_preprocess_config(args: argparse.Namespace, sfm_width: int) -> PreprocessConfig:
    """The demo's SfM settings for frames ``sfm_width`` wide: ``osn preprocess``'s defaults for them
    (:func:`osn.preprocess.sfm.pipeline_config`) with the demo's ``--anchor-downscale`` and ``--crop-margin``."""
    try:
        return pipeline_config(sfm_width, anchor_downscale=args.anchor_downscale, crop_margin=args.crop_margin)
    except ValueError as e:  # out of range
        raise UserError(f"--anchor-downscale {args.anchor_downscale} / --crop-margin {args.crop_margin}: {e}") from None


def _sfm_lines(objects: list[dict]) -> list[str]:
    out = []
    for r in objects:
        if "error" in r:
            out.append(f"SfM dropped object {r['id']} ({r['name']}): {r['error']}")
        elif "rotation_error_deg_max" in r:
            out.append(f"SfM object {r['id']} ({r['name']}): {100 * r['registered_fraction']:.0f}% of frames, "
                       f"rotation error max {r['rotation_error_deg_max']:.2f} deg")
    return out


def stage_preprocess(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Oracle inputs (ablation) and per-object SfM (on the SfM video when there is one: its poses
    and depths brought down to the benchmark's frames, which the fields then learn); an SfM
    failure is a result unless SfM trains."""
    scene = D.load_scene(p.dataset)
    factor = sfm_downscale(args, scene.width)
    video = D.read_training_video(p.dataset, scene)  # read once for both
    save_inputs(p.oracle, oracle_inputs(p.dataset, video=video))
    sfm_source = p.sfm_video if factor > 1 else p.dataset
    try:
        cfg = demo_preprocess_config(args, scene.width * factor)
        inputs, report = preprocess_dataset(sfm_source, cfg, progress=lambda m: print(f"  {m} ...", flush=True),
                                            video=video if factor == 1 else None, workers=args.workers)
        inputs = training_inputs(inputs, factor, cfg)
        if factor > 1:  # SfM saw the video larger; the fields learn the benchmark's own frames, as any method does
            inputs = with_video(inputs, video[0], video[2], p.dataset / "train")
    except InputsError as e:
        if args.inputs_from == "colmap":
            raise
        print(f"  SfM failed: {e}")
        return {"sfm_error": str(e)}
    save_inputs(p.sfm, inputs)
    atomic_write_json(p.sfm / "preprocess_report.json", {"objects": report.objects, "dropped": report.dropped})
    for line in _sfm_lines(report.objects):
        print(f"  {line}")
    return {"objects": report.objects, "dropped": report.dropped}


def stage_train(args: argparse.Namespace, p: DemoPaths, cfg: Any, beside: BackgroundCommand | None = None) -> dict:
    """Train (or resume) on the chosen inputs, monitored against the dataset's exact region.

    If ``beside`` (the ground truth's rendering) runs when training starts, training uses one
    intra-op thread to its end: with two threads it is only a little faster on two cores, its
    second thread mostly spinning, and that core renders the ground truth instead. It does not go back to
    all threads when the ground truth ends: the trained fields and scale network depend on the
    thread count (reductions split differently; on the SfM demo two 1-thread trainings are bit for
    bit equal, a 2-thread one is not), so a switch at a moment of the wall clock would make each
    run's result depend on the machine's speed (docs/training.md)."""
    resume = (p.run / "checkpoint.pt").exists()
    inputs = None if resume else load_inputs(p.sfm if args.inputs_from == "colmap" else p.oracle)
    threads = torch.get_num_threads()
    if beside is not None and beside.running():
        torch.set_num_threads(1)
    try:
        train_on_dataset(p.dataset, p.run, cfg, inputs=inputs, resume=resume)
    finally:
        torch.set_num_threads(threads)
    last = read_metrics(p.run / "metrics.jsonl")[-1]
    print(f"  training: PSNR {last.get('psnr', float('nan')):.2f} dB, valid-set IoU {last.get('iou', float('nan')):.3f} "
          f"after {last['wall_time']:.0f} s")
    return {k: last.get(k) for k in ("psnr", "iou", "wall_time", "iteration")}


def stage_sample(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Draw N configurations from the scale network (no ground truth)."""
    s = sample_configurations(load_run(p.run), args.n, args.threshold, args.seed)
    s.save(p.run / "samples.npz")
    return {"n": len(s.sbar), "fell_back": s.fell_back, "chained": s.chained}


def stage_evaluate(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Best of N against every ground truth, the report and its plots."""
    res = evaluate(load_run(p.run), p.dataset, Samples.load(p.run / "samples.npz"), EvalConfig(max_views=args.max_views),
                   candidates_dir=p.candidates)  # for `benchgen score`
    write_report(res, p.report, p.run, demo_command(args))
    return {"table": res.table, "valid_set": res.valid_set, "scale_error": res.scale_error}


def stage_export(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Export the sampled configurations and the dataset's test cameras for Blender."""
    export_run(p.run, p.export, dataset=p.dataset)
    return {}


def stage_addon(args: argparse.Namespace, p: DemoPaths) -> dict:
    """Build the Blender extension zip next to the outputs."""
    return {"zip": str(build_addon_zip(p.work))}


def run_demo(args: argparse.Namespace) -> dict[str, Any]:
    """Run (or resume) every stage under ``args.work``; returns the stage records."""
    p = DemoPaths(Path(args.work))
    width = _demo_spec(args, args.resolution, args.configs).width
    sfm_px = sfm_width(args, width)  # a bad one stops here, before rendering
    sfm_cfg = demo_preprocess_config(args, sfm_px)  # so do bad SfM options
    train_cfg = training_config(args.config, args.field_iterations)  # also what the train stage depends on
    # What each stage's outputs depend on: a rerun with other values stops instead of mixing them.
    train_options = {f"train.{k}": v for k, v in _flat(train_cfg.to_dict()).items()}
    scene = _scene_options(args)
    bench = {**scene, "resolution": args.resolution, "configs": args.configs}
    jobs: dict[str, BackgroundCommand] = {}  # background stages' jobs once started (this invocation)

    def start_ground_truth() -> BackgroundCommand:
        jobs["ground-truth"] = stage_ground_truth(args, p)
        return jobs["ground-truth"]

    stages = [
        Stage("generate", f"benchgen: render the {_scene_name(args)} training video, its exact region and configurations",
              partial(stage_generate, args, p), bench),
    ]
    sfm_res = sfm_px if sfm_px > width else None  # recorded only for a separate SfM video, so existing runs still match
    if sfm_res:
        stages.append(Stage("sfm-video", f"benchgen: render the training video at {sfm_px} px for SfM",
                            partial(stage_sfm_video, args, p, sfm_px), {**scene, "sfm_resolution": sfm_px}))
    stages += [
        Stage("preprocess", "per-object SfM (pycolmap) and oracle inputs", partial(stage_preprocess, args, p),
              {k: v for k, v in (("sfm_resolution", sfm_res), ("anchor_downscale", str(args.anchor_downscale)),
                                 ("crop_margin", str(args.crop_margin)),  # strings, as earlier work directories hold them
                                 # the fields learn the benchmark's frames, not SfM's averaged down
                                 ("training_frames", "benchmark" if sfm_res else None),
                                 ("drop_occluding", sfm_cfg.drop_occluding)) if v not in (None, "auto")}),
        Stage("ground-truth", "benchgen: render every configuration's test views and verify them", start_ground_truth,
              bench, background=True),
        Stage("train", f"train per-object fields and the scale network on {args.inputs_from} inputs",
              lambda: stage_train(args, p, train_cfg, jobs.get("ground-truth")), {"inputs": args.inputs_from, **train_options},
              recorded=recorded_train_options),
        Stage("sample", f"draw {args.n} valid configurations", partial(stage_sample, args, p),
              {"n": args.n, "threshold": args.threshold, "seed": args.seed}),
        Stage("evaluate", "best-of-N evaluation against every ground truth", partial(stage_evaluate, args, p),
              {"max_views": args.max_views}, needs=("ground-truth",)),
        Stage("export", "export volumes, meshes, trajectories and the scale network", partial(stage_export, args, p)),
        Stage("addon", "build the Blender add-on zip", partial(stage_addon, args, p)),
    ]
    return run_stages(stages, p.work)


def _cmd_demo(args: argparse.Namespace) -> int:

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    records = run_demo(args)
    work = Path(args.work)
    ev = records["evaluate"]["summary"]
    print()
    print("\n".join(summary_lines(ev["table"], ev["valid_set"], ev["scale_error"])))
    print("stage times: " + ", ".join(f"{k} {r['seconds']:.0f} s" + (" (in the background)" if r.get("background") else "")
                                      for k, r in records.items()))
    print(f"total this invocation: {time.perf_counter() - t0:.0f} s")
    print(f"report:  {work / 'report' / 'report.md'}")
    print(f"export:  {work / 'export'}")
    print(f"add-on:  {records['addon']['summary']['zip']}  (Blender: Edit > Preferences > Get Extensions > Install from Disk)")
    return 0


def add_demo_parser(sub: argparse._SubParsersAction) -> None:
    p = subcommand(sub, "demo", _cmd_demo, "run the whole pipeline on a preset (default: the embedded Gnome-House "
                   "scene) or on your own scene spec (resumable)",
                   description="Generate the benchmark, preprocess (SfM + oracle), train, sample N configurations, "
                   "evaluate best-of-N against every ground truth, export for Blender and build the add-on. Run it "
                   "again to resume: finished stages are skipped.")
    p.add_argument("--work", default="runs/demo", help="working directory for every output")
    scene = p.add_mutually_exclusive_group()
    scene.add_argument("--preset", help=f"benchgen preset (see `benchgen presets`; default: {DEFAULT_PRESET})")
    scene.add_argument("--spec", help="your own YAML scene spec, as `benchgen generate --spec` takes (docs/benchgen.md)")
    p.add_argument("--resolution", type=int, default=None, help="square image size in pixels (default: the scene's)")
    p.add_argument("--configs", type=int, default=None, help="number G of ground-truth configurations (default: the scene's)")
    add_config_options(p)
    p.add_argument("--inputs-from", choices=["oracle", "colmap"], default="colmap",
                   help="train on the pycolmap output (the method as published) or on oracle per-object inputs "
                   "(ground-truth poses and depths: an ablation, labelled so in the report)")
    p.add_argument("--sfm-resolution", type=auto_or_int, default="auto",
                   help="run SfM on the training video rendered again at this square size (a multiple of the "
                   "benchmark's), its poses and depths brought down to the benchmark's frames, which the fields learn: "
                   "SfM registers only the room at "
                   f"64 px; auto: {SFM_SIZE} px with --inputs-from colmap (SfM registers nearly every frame of every "
                   "gnome-house object), "
                   "the benchmark's own frames with --inputs-from oracle")
    add_sfm_size_options(p)
    p.add_argument("-n", type=int, default=1000, help="number of sampled configurations N")
    p.add_argument("--threshold", type=float, default=0.5, help="validity threshold of sampling")
    p.add_argument("--max-views", type=int, default=30, help="test views evaluated per ground truth (0 = all)")
    p.add_argument("--workers", type=int, default=2,
                   help="rendering processes for benchgen, and objects (and each object's mapper restarts) "
                   "reconstructed at once by SfM (results do not depend on it)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled configurations (the export carries those)")
    deprecated_alias(p, "--iterations", "--field-iterations")
    deprecated_alias(p, "--train-config", "--config")
    deprecated_alias(p, "--inputs", "--inputs-from")

"""``osn oracle`` and ``osn preprocess``: command-line front ends of :mod:`osn.preprocess`."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from scenecore.cli import UserError, subcommand
from scenecore.dataset import atomic_write_json, load_scene, read_training_video
from osn.preprocess.inputs import IGNORE_ID, InputsError, SceneInputs, check_downscale, save_inputs, with_video
from osn.preprocess.oracle import OracleConfig, oracle_inputs
from osn.preprocess.sfm import (
    ANCHOR_SFM_SIZE, CROP_FROM, CROP_MARGIN, PIPELINE_DEFAULTS, PreprocessConfig, PreprocessReport, pipeline_config,
)
from osn.preprocess.video import (
    intrinsics_from_args, load_video, preprocess_dataset, preprocess_video, report_lines, training_inputs,
)


def _cmd_oracle(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    inputs = oracle_inputs(args.dataset, OracleConfig(points_per_frame=args.points_per_frame, seed=args.seed))
    save_inputs(args.out, inputs)
    print(f"oracle inputs for {inputs.num_objects} objects written to {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0


#: ``osn preprocess`` options that are :class:`PreprocessConfig` fields of the same name.
CONFIG_OPTIONS = ("matcher", "min_frames", "on_failure", "seed", "max_features", "upscale", "anchor_downscale",
                  "crop_margin", "grey", "mapper_restarts", "anchor_mapper_restarts", "points_per_frame", "drop_occluding")


def preprocess_config(args: argparse.Namespace, width: int) -> PreprocessConfig:
    """What ``osn preprocess`` runs SfM with on frames ``width`` px wide: its options over the
    pipeline's defaults (:func:`osn.preprocess.sfm.pipeline_config`, shared with ``osn demo``)."""
    try:
        return pipeline_config(width, **{k: getattr(args, k) for k in CONFIG_OPTIONS})
    except ValueError as e:
        raise UserError(f"osn preprocess: {e}") from None


def _cmd_preprocess(args: argparse.Namespace) -> int:
    if args.workers < 1:
        raise UserError(f"osn preprocess: --workers must be >= 1, got {args.workers}")
    if args.work_dir and Path(args.work_dir).exists() and any(Path(args.work_dir).iterdir()):
        raise UserError(f"{args.work_dir}: --work-dir exists and is not empty; name a new directory")
    t0 = time.perf_counter()
    src = Path(args.source)
    progress = (lambda msg: print(f"  {msg} ...", flush=True))
    if (src / "scene.json").exists():
        if args.masks:
            raise UserError(f"{src} is a benchgen dataset: its instance masks are used, drop --masks")
        scene = load_scene(src)
        cfg = preprocess_config(args, scene.width)
        _check_downscale(src, scene.width, scene.height, args.downscale)
        _check_train_video(args.train_video, scene.width // args.downscale, scene.height // args.downscale, len(scene.train_frames))
        inputs, report = preprocess_dataset(src, cfg, progress, work_dir=args.work_dir, workers=args.workers)
    else:
        if args.train_video:
            raise UserError(f"{src}: --train-video needs a benchgen dataset as the source (its video rendered larger)")
        inputs, report, cfg = _preprocess_frames(src, args, progress)
    try:
        inputs = training_inputs(inputs, args.downscale, cfg)
    except InputsError as e:  # an object left without a pixel at the lower resolution
        raise UserError(f"{src}: --downscale {args.downscale}: {e}") from None
    if args.train_video:
        video = read_training_video(args.train_video, load_scene(args.train_video))
        try:
            inputs = with_video(inputs, video[0], video[2], Path(args.train_video) / "train")
        except InputsError as e:  # an object without a pixel of its own in the benchmark's masks
            raise UserError(f"--train-video: {e}") from None
    save_inputs(args.out, inputs)
    atomic_write_json(Path(args.out) / "preprocess_report.json", {"objects": report.objects, "dropped": report.dropped,
                                                                 "seconds": time.perf_counter() - t0})
    print("\n".join(report_lines(report.objects)))
    print(f"per-object inputs written to {args.out} in {time.perf_counter() - t0:.1f} s "
          f"(at most {inputs.meta['sparse_depths_per_frame']} sparse depths per object and frame)")
    return 0


def _check_train_video(dataset: str | None, width: int, height: int, frames: int) -> None:
    """Before SfM: ``--train-video``'s dataset must have the written inputs' size and frame count."""
    if not dataset:
        return
    scene = load_scene(dataset)
    if (scene.width, scene.height, len(scene.train_frames)) != (width, height, frames):
        raise UserError(f"{dataset}: --train-video has {len(scene.train_frames)} training frames of "
                        f"{scene.width}x{scene.height}, the inputs will have {frames} of {width}x{height} "
                        "(set --downscale to the ratio of the two resolutions)")


def _check_downscale(src: Path, width: int, height: int, factor: int) -> None:
    try:
        check_downscale(width, height, factor)
    except InputsError as e:
        raise UserError(f"{src}: --downscale {factor}: {e}") from None


def _preprocess_frames(
    src: Path, args: argparse.Namespace, progress: Callable[[str], None]
) -> tuple[SceneInputs, PreprocessReport, PreprocessConfig]:
    """``osn preprocess FRAMES --masks MASKS``: any video, with known intrinsics and instance masks."""
    if not args.masks:
        raise UserError(f"{src}: not a benchgen dataset (no scene.json), so --masks MASKS_DIR is required")
    images, masks, names = load_video(src, args.masks)
    cfg = preprocess_config(args, images.shape[2])
    _check_downscale(src, images.shape[2], images.shape[1], args.downscale)  # before SfM, not after
    K = intrinsics_from_args(args.intrinsics, args.fov, images.shape[2], images.shape[1])
    ids = sorted(int(i) for i in np.unique(masks) if i not in (255, IGNORE_ID))
    anchor = args.anchor if args.anchor is not None else max(ids, key=lambda i: int((masks == i).sum()))
    if anchor not in ids:
        raise UserError(f"--anchor {anchor} is not an id found in {args.masks} (found {ids})")
    T = len(images)
    inputs, report = preprocess_video(
        images, masks, K, np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1), {i: f"object{i}" for i in ids},
        anchor, cfg, progress, args.work_dir, args.workers,
    )
    inputs.meta["frames"] = names
    return inputs, report, cfg


def auto_or_int(v: str) -> str | int:
    """An argparse type: ``auto`` or an integer."""
    if v == "auto":
        return v
    try:
        return int(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"auto or an integer, not {v!r}") from None


def add_sfm_size_options(p: argparse.ArgumentParser) -> None:
    """``--anchor-downscale`` and ``--crop-margin``, as ``osn preprocess`` and ``osn demo`` both take
    them (``auto``: :func:`osn.preprocess.sfm.pipeline_config` chooses by the SfM frames' width)."""
    p.add_argument("--anchor-downscale", type=auto_or_int, default=PIPELINE_DEFAULTS["anchor_downscale"],
                   help="SfM of the anchor (background), which fills the frame, on frames averaged down by this "
                   "factor (it needs fewer pixels than small objects; at 1024 px upsampled it costs 4x those of 512); "
                   f"auto: to at most {ANCHOR_SFM_SIZE} px")
    p.add_argument("--crop-margin", type=auto_or_int, default=PIPELINE_DEFAULTS["crop_margin"],
                   help="SIFT sees each object's frames cropped to the box of its masks over the video, grown by this "
                   "many pixels (-1: whole frames; SIFT costs every pixel it is given); "
                   f"auto: {CROP_MARGIN} from {CROP_FROM} px up, whole frames below")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``osn oracle`` and ``osn preprocess`` on the ``osn`` command's subparsers."""
    p = subcommand(sub, "oracle", _cmd_oracle, "per-object inputs from a dataset's ground truth (what perfect SfM would give)")
    p.add_argument("dataset", help="benchgen dataset directory")
    p.add_argument("--out", required=True, help="output directory (inputs.json + inputs.npz)")
    p.add_argument("--points-per-frame", type=int, default=0,
                   help="sparse depths kept per object and frame (0: a sixteenth of the frame's pixels, at least 256)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sparse subsampling")

    p = subcommand(
        sub, "preprocess", _cmd_preprocess, "per-object SfM (pycolmap) from frames and instance masks",
        description="Per-object SfM with pycolmap: SIFT inside each object's mask, matching, incremental mapping "
        "with the known pinhole camera. SOURCE is a benchgen dataset (its masks and intrinsics are used, and the "
        "result is aligned to its ground truth to report accuracy) or a directory of frames with --masks.",
    )
    p.add_argument("source", help="benchgen dataset directory, or a directory of video frames (PNG/JPG, sorted by name)")
    p.add_argument("--masks", help="directory of instance-id PNGs named like the frames (255 = no object)")
    p.add_argument("--intrinsics", help="pinhole intrinsics fx,fy,cx,cy in pixels (frames directory only)")
    p.add_argument("--fov", type=float, help="horizontal field of view in degrees, centred principal point (frames directory only)")
    p.add_argument("--anchor", type=int, help="id of the anchor (background) object; default: the id covering most pixels")
    p.add_argument("--out", required=True, help="output directory (inputs.json, inputs.npz, preprocess_report.json)")
    p.add_argument("--work-dir", help="keep each object's COLMAP working directory here (DIR/object_<id>: images/, "
                   "database.db, model/) to open it in COLMAP; default: a temporary directory, removed")
    p.add_argument("--matcher", choices=["auto", "exhaustive", "sequential"], default=PreprocessConfig.matcher,
                   help="feature matching; auto = exhaustive up to 60 frames, sequential beyond")
    p.add_argument("--min-frames", type=int, default=PreprocessConfig.min_frames, help="an object must register at least this many frames")
    p.add_argument("--max-features", type=int, default=PreprocessConfig.max_features, help="SIFT features per frame and object")
    p.add_argument("--upscale", type=int, default=PreprocessConfig.upscale,
                   help="upsample frames by this integer factor before SIFT (objects under ~100 px need 2)")
    add_sfm_size_options(p)
    p.add_argument("--mapper-restarts", type=int, default=PreprocessConfig.mapper_restarts,
                   help="incremental mapping runs per object on the same matches, the best model kept (a small object "
                   "seen nearly in weak perspective has a depth-reversed twin that one run can settle in)")
    p.add_argument("--anchor-mapper-restarts", type=int, default=PreprocessConfig.anchor_mapper_restarts,
                   help="the same for the anchor (a single run is shorter, but the valid set learned from its model spreads "
                   "wider over seeds)")
    p.add_argument("--grey", choices=["auto", "luminance", "principal"], default=PreprocessConfig.grey,
                   help="grey image SIFT sees: luminance, the object's principal colour axis, or auto "
                   "(principal only for objects whose colours differ mostly in hue, e.g. red on blue)")
    p.add_argument("--downscale", type=int, default=1,
                   help="write the inputs (frames, masks, intrinsics) at 1/N of the frames' resolution, after SfM ran on "
                   "the full frames: small objects register only in large frames, the fields train faster on small ones")
    p.add_argument("--train-video", metavar="DATASET",
                   help="with --downscale on a benchgen dataset rendered larger for SfM: train on DATASET's own training "
                   "frames and masks (the benchmark's video, the inputs' size) instead of the SfM frames averaged down, "
                   "which differ from them (area averages, where benchgen renders each pixel's centre ray); SfM's poses and "
                   "depths are kept")
    p.add_argument("--drop-occluding", choices=["training", "all", "none"], default=PreprocessConfig.drop_occluding,
                   help="the sparse depths that lie in front of what the object's other frames saw (SfM's phantoms, "
                   "found without ground truth): 'training' keeps them out of training, the anchor's only after they "
                   "set its near plane (the scene volume); 'all' normalises the anchor without them too; 'none' keeps them")
    p.add_argument("--points-per-frame", type=int, default=PreprocessConfig.points_per_frame,
                   help="sparse depths kept per object and frame for training, at the written resolution, chosen at "
                   "random (0: as the oracle, a sixteenth of the frame's pixels, at least 256); near, far and each "
                   "object's box use all of SfM's depths")
    p.add_argument("--on-failure", choices=["stop", "skip"], default=PIPELINE_DEFAULTS["on_failure"],
                   help="an object that fails to register: stop with its message, or train without it (reported; "
                   "the anchor always stops), as `osn demo` does")
    p.add_argument("--seed", type=int, default=PreprocessConfig.seed,
                   help="every pycolmap random seed, and the seed of the sparse-depth subsampling")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="objects reconstructed at once, and each object's mapper restarts run at once, each on "
                   "one thread (default: this machine's cores, here %(default)s); the result does not depend on it")

"""``benchgen``: generate and check multi-ground-truth benchmark datasets."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from scenecore.cli import UserError, blas_on_one_thread, deprecated_alias, run_cli, subcommand

blas_on_one_thread()  # before the import below brings numpy in

from benchgen.score.command import add_score_command
from benchgen.score.import_command import add_import_command


def _cmd_validate(args: argparse.Namespace) -> int:
    from scenecore.dataset import validate

    problems = validate(args.dataset, check_images=not args.manifest_only)
    for p in problems:
        print(p)
    if problems:
        print(f"benchgen: {len(problems)} problem(s) in {args.dataset}", file=sys.stderr)
        return 1
    print(f"{args.dataset}: valid dataset (format v1)")
    return 0


def _load_spec(args: argparse.Namespace):
    from benchgen.scene.procedural import parse_seeds, random_spec
    from benchgen.scene.spec import load_preset, load_spec

    if sum(x is not None for x in (args.preset, args.spec, args.random)) != 1:
        raise UserError("give exactly one of --preset NAME, --spec FILE or --random SEED")
    if args.protocol is not None and args.random is None:
        raise UserError("--protocol chooses the rig of a --random scene; a preset or spec file sets its own")
    if args.random is not None:
        try:
            seeds = parse_seeds(args.random)
        except ValueError as e:
            raise UserError(f"--random: {e}") from None
        if len(seeds) != 1:
            raise UserError(f"--random: generate builds one scene; got {len(seeds)} seeds (benchgen suite --random A:B builds several)")
        spec = random_spec(seeds[0], args.protocol or "orbit")
    else:
        spec = load_preset(args.preset) if args.preset else load_spec(args.spec)
    return spec.with_overrides(resolution=args.resolution, samples=args.cycles_samples, configs=args.configs, seed=args.seed)


def _report(summary) -> int:
    for line in summary.lines():
        print(line)
    if summary.passed:
        return 0
    # The lines above say everything; stderr gets one line, as for every other failure.
    cfgs = summary.verification.get("configurations", [])
    bad = [c for c in cfgs if not c["passed"]]
    first = f" (configuration {bad[0]['index']:03d}: {'; '.join(bad[0]['failures'])})" if bad else ""
    print(f"benchgen: {summary.root}: verification failed: {len(bad)} of {len(cfgs)} configurations{first}", file=sys.stderr)
    return 1


def _cmd_generate(args: argparse.Namespace) -> int:
    from benchgen.render.generate import generate

    spec = _load_spec(args)
    return _report(generate(spec, args.out, args.workers, args.executor, args.address, progress=not args.quiet,
                            video_only=args.video_only))


def _cmd_verify(args: argparse.Namespace) -> int:
    from benchgen.render.generate import verify_dataset

    return _report(verify_dataset(args.dataset, args.workers, args.executor, args.address, progress=not args.quiet))


def _cmd_suite(args: argparse.Namespace) -> int:
    from benchgen.render.suite import SUITE_PRESETS, run_suite
    from benchgen.scene.spec import SpecError

    from benchgen.scene.procedural import parse_seeds, random_spec

    if args.random is not None and args.presets:
        raise UserError("give --presets or --random, not both")
    if args.protocol is not None and args.random is None:
        raise UserError("--protocol chooses the rig of --random scenes; the presets set their own")
    try:
        if args.random is not None:
            try:
                seeds = parse_seeds(args.random)
            except ValueError as e:
                raise UserError(f"--random: {e}") from None
            presets = [random_spec(s, args.protocol or "orbit") for s in seeds]
        else:
            presets = [p for p in args.presets.split(",") if p] if args.presets else SUITE_PRESETS
        rows = run_suite(args.out, presets, resolution=args.resolution, configs=args.configs,
                         workers=args.workers, executor=args.executor, address=args.address, progress=not args.quiet)
    except SpecError as e:
        raise UserError(str(e)) from None
    failed = [r.preset for r in rows if not r.passed]
    if failed:
        print(f"benchgen: verification failed for {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def _cmd_presets(args: argparse.Namespace) -> int:
    from benchgen.scene.spec import PRESET_DIR, load_preset, preset_names

    for name in preset_names():
        s = load_preset(name)
        print(
            f"{name:16s} {len(s.objects)} objects, {s.rig.protocol} rig, {s.rig.views} cameras x {s.rig.times} times, "
            f"{s.width}x{s.height}, {s.samples} spp, G={s.configs}  ({PRESET_DIR / (name + '.yaml')})"
        )
    return 0


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=int, default=1, help="number of rendering processes (or Ray actors), each holding one Blender scene")
    p.add_argument("--executor", choices=("local", "ray"), default="local", help="run workers as local processes or as Ray actors (needs the 'ray' extra and a shared file system)")
    p.add_argument("--address", default=None, help="Ray cluster address for --executor ray (default: start a local Ray instance)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="benchgen",
        description="Render Gnome-House-style scenes with Blender: one monocular training video plus many "
        "ground-truth scale configurations that all reproduce it, and the exact valid-scale region.",
    )
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    p = subcommand(sub, "validate", _cmd_validate, "check a dataset directory against the format (docs/dataset-format.md)")
    p.add_argument("dataset", help="dataset directory")
    p.add_argument("--manifest-only", action="store_true", help="check JSON files only, not every image")
    p = subcommand(
        sub, "generate", _cmd_generate, "render a multi-ground-truth dataset from a preset or a spec file",
        "Render the training video, the exact valid-scale region, G ground-truth configurations and their test "
        "views, then verify every configuration. Rerunning the same command resumes: only missing files are rendered. "
        "Exit code 0: all configurations verified; 1: a verification failed; 2: bad input; 3: a file could not "
        "be written or read (disk full, no permission).",
    )
    src = p.add_argument_group("scene (one of)")
    src.add_argument("--preset", help="a built-in spec (see 'benchgen presets')")
    src.add_argument("--spec", help="a YAML spec file (docs/benchgen.md)")
    src.add_argument("--random", default=None, metavar="SEED",
                     help="the procedural family's scene for SEED (2-6 random movers, random room, textures, motions and "
                     "rig; 64 px, G=20, 30 test views unless overridden; seeds 0-999: development split, 1000-1999: "
                     "held-out split, docs/benchgen.md). The spec is written to OUT/spec.yaml, so --spec reruns it")
    p.add_argument("--protocol", choices=("orbit", "stereo", "multi-camera"), default=None,
                   help="rig protocol of a --random scene (default: orbit, the paper's 15 x 15 arc)")
    p.add_argument("--out", required=True, help="output dataset directory (created; resumed if it holds the same spec)")
    p.add_argument("--resolution", type=int, default=None, help="square image size in pixels (default: the spec's)")
    p.add_argument("--cycles-samples", type=int, default=None, help="Cycles samples per pixel (default: the spec's)")
    p.add_argument("--configs", type=int, default=None, help="number G of ground-truth configurations (default: the spec's)")
    p.add_argument("--seed", type=int, default=None, help="seed of the configuration sampler and the renderer (default: the spec's)")
    p.add_argument("--video-only", action="store_true",
                   help="render the training video alone (frames, depth, ids): no valid region, configurations, test views "
                   "or verification; e.g. SfM's input at a higher resolution. Rerun without it to render the rest")
    _add_run_options(p)
    deprecated_alias(p, "--samples", "--cycles-samples")
    p = subcommand(
        sub, "verify", _cmd_verify, "re-render every configuration's training frames and check invariance",
        "Rebuild the scene from DATASET/spec.yaml, re-render each configuration's training frames and compare them with "
        "the training video, compare its test views with configuration 000's, write verification.json. "
        "Exit code 1 names the failing configuration and frame.",
    )
    p.add_argument("dataset", help="dataset directory written by 'benchgen generate'")
    _add_run_options(p)
    subcommand(sub, "presets", _cmd_presets, "list the built-in scene specs")
    from benchgen.render.suite import SUITE_PRESETS

    p = subcommand(
        sub, "suite", _cmd_suite, "generate every paper-style preset and tabulate them",
        f"Generate one dataset per preset ({', '.join(SUITE_PRESETS)}) under OUT/<preset>, resumable like 'generate', and "
        "print one table (objects, frames, the exact valid region's share of the paper's Eq. 1 sampling box, narrowest "
        "and widest per-object interval inside it, verification, wall time), also written to OUT/suite.md and "
        "OUT/suite.json. Exit code 0: every configuration of every preset verified; 1: a verification failed; 2: bad input; "
        "3: a file could not be written or read (disk full, no permission).",
    )
    p.add_argument("--out", required=True, help="directory holding one dataset per preset (created; resumed)")
    p.add_argument("--resolution", type=int, default=None, help="square image size in pixels for every preset (default: each preset's)")
    p.add_argument("--configs", type=int, default=None, help="number G of ground-truth configurations per preset (default: each preset's, 50)")
    p.add_argument("--presets", default=None, help=f"comma-separated subset of the suite (default: all of {','.join(SUITE_PRESETS)})")
    p.add_argument("--random", default=None, metavar="A:B",
                   help="instead of the presets, the procedural family's scenes for seeds A to B-1 (also 'S' or a "
                   "comma-separated list), each under OUT/random-SEED; see 'generate --random'")
    p.add_argument("--protocol", choices=("orbit", "stereo", "multi-camera"), default=None,
                   help="rig protocol of the --random scenes (default: orbit)")
    _add_run_options(p)
    add_score_command(sub)
    add_import_command(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, "benchgen")


if __name__ == "__main__":
    sys.exit(main())

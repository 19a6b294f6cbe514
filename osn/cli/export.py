"""``osn export``: command-line front end of :mod:`osn.export`."""

from __future__ import annotations

import argparse

from scenecore.cli import deprecated_alias, subcommand
from osn.export.from_run import DEFAULT_EXPORT_SAMPLES, export_run


def _cmd_export(args: argparse.Namespace) -> int:
    export_run(args.run, args.out, resolution=args.grid_resolution, samples=args.n, seed=args.seed, dataset=args.data)
    return 0


def add_export_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``osn export RUN --out DIR [--data DATASET]`` on the ``osn`` command's subparsers."""
    p = subcommand(
        sub, "export", _cmd_export, "export a trained run for Blender (OpenVDB volumes, meshes, trajectories, scale network)",
        description="Write a versioned export directory (docs/export-and-addon.md) that the Blender add-on imports: "
        "per object its field (density and colour, which the add-on renders as a volume matching OSN's own render) and "
        "an OpenVDB volume, a coloured PLY mesh built from its renders in the training views (a viewport preview), "
        "per-frame poses and cameras, the scale network and "
        "its learned valid intervals, and optionally sampled valid configurations and (with --data) the dataset's "
        "test cameras. Written atomically.",
    )
    p.add_argument("run", help="osn train run directory (config.yaml, inputs/, checkpoint.pt)")
    p.add_argument("--out", required=True, help="export directory (created, or replaces a previous export)")
    p.add_argument("--data", metavar="DATASET", help="the benchgen dataset the run was trained on: its test-rig cameras are exported "
                   "(only with this option, and only for inputs aligned to it)")
    p.add_argument("--grid-resolution", type=int, help="grid samples per axis (default: each field's trained resolution)")
    p.add_argument("-n", type=int, default=None,
                   help="valid configurations to draw through the scale network (0: none); default: the run's "
                   f"samples.npz from `osn sample` when present, else {DEFAULT_EXPORT_SAMPLES}")
    p.add_argument("--seed", type=int, default=0, help="seed of the configurations drawn (unused for samples.npz)")
    deprecated_alias(p, "--resolution", "--grid-resolution")
    deprecated_alias(p, "--samples", "-n")

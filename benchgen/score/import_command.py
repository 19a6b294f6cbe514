"""``benchgen import-renders DIR --data DATASET --out PRED/NAME``: renders of nerfstudio's ``ns-render``
or D-NeRF as one candidate of the prediction format (the work is in :mod:`benchgen.score.importer`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenecore.cli import subcommand

DESCRIPTION = (
    "Import a folder of renders of DATASET's test views (ns-render dataset --split test's --output-path, whose "
    "test/rgb_fine or test/rgb is taken; D-NeRF's renderonly_test_* folder; or any folder of PNG or JPEG files "
    "named by test frame or by index in transforms_test.json's order) as candidate PRED/NAME of the prediction "
    "format (docs/predictions.md), then score PRED with 'benchgen score'. Counts, names and sizes are checked "
    "against DATASET's test views first: one line names what is missing, extra or wrong (exit code 2) and nothing "
    "is written. JPEGs and transparent pixels (composited over white) become 8-bit PNGs; --depth imports depth "
    "maps, converted to planar depth when --depth-kind ray. PRED/NAME is written whole or not at all; an existing "
    "one is replaced only if an import wrote it."
)


def add_import_command(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``import-renders`` on ``benchgen``'s sub-parsers."""
    p = subcommand(sub, "import-renders", _cmd_import, "import ns-render / D-NeRF renders as a candidate to score",
                   DESCRIPTION)
    p.add_argument("renders", metavar="DIR", help="folder of renders, or ns-render's --output-path (its test/rgb_fine or test/rgb)")
    p.add_argument("--data", required=True, metavar="DATASET", help="dataset directory whose test views were rendered")
    p.add_argument("--out", required=True, metavar="PRED/NAME", help="candidate directory to write (PRED is then scored)")
    p.add_argument("--depth", default=None, metavar="DIR",
                   help="folder of depth maps (.npy.gz, .npy or .exr per test view), or ns-render's --output-path "
                   "(its test/raw-depth_fine or test/raw-depth); needs --depth-kind")
    p.add_argument("--depth-kind", choices=("ray", "planar"), default=None,
                   help="what --depth holds: 'ray', the distance along each pixel's ray (nerfstudio's NeRF depth), "
                   "converted to planar depth with DATASET's cameras; 'planar', camera-axis depth (the dataset's)")
    return p


def _cmd_import(args: argparse.Namespace) -> int:
    from benchgen.score.importer import import_renders

    summary = import_renders(args.renders, args.data, args.out, args.depth, args.depth_kind)
    for line in summary.lines():
        print(line)
    pred = Path(args.out).parent
    print(f"score with: benchgen score {pred} --data {args.data}")
    return 0

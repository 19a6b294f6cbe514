"""``benchgen``: generate and check multi-ground-truth benchmark datasets."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from .cliutil import run_cli, subcommand


def _cmd_validate(args: argparse.Namespace) -> int:
    from .dataset import validate

    problems = validate(args.dataset, check_images=not args.manifest_only)
    for p in problems:
        print(p)
    if problems:
        print(f"benchgen: {len(problems)} problem(s) in {args.dataset}", file=sys.stderr)
        return 1
    print(f"{args.dataset}: valid dataset (format v1)")
    return 0


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
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, "benchgen")


if __name__ == "__main__":
    sys.exit(main())

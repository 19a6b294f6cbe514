"""``osn``: train, sample, evaluate and export Object Scale Network models."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from benchgen.cliutil import run_cli, subcommand


def _cmd_demo(args: argparse.Namespace) -> int:
    print("osn demo: the end-to-end pipeline is not built yet.")
    print("Built so far: the dataset format and its validator (`benchgen validate DIR`).")
    print("Not built yet: benchgen generate, osn train/sample/evaluate/export/preprocess, the Blender add-on.")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="osn",
        description="Learn all 3D scene configurations that explain one dynamic monocular video.",
    )
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    subcommand(sub, "demo", _cmd_demo, "run the whole pipeline on the embedded default scene")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, "osn")


if __name__ == "__main__":
    sys.exit(main())

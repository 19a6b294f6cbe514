"""``osn``: preprocess, train, sample, evaluate and export Object Scale Network models."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from scenecore.cli import blas_on_one_thread, run_cli

blas_on_one_thread()  # before the imports below bring numpy in

from osn.cli.demo import add_demo_parser
from osn.cli.evaluate import add_eval_parsers
from osn.cli.export import add_export_parser
from osn.cli.preprocess import add_parsers as add_preprocess_parsers
from osn.cli.train import add_train_parser


def build_parser() -> argparse.ArgumentParser:
    """The ``osn`` parser: one subcommand per pipeline stage, registered by the stage's CLI module."""
    parser = argparse.ArgumentParser(
        prog="osn",
        description="Learn all 3D scene configurations that explain one dynamic monocular video.",
    )
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")

    add_preprocess_parsers(sub)
    add_train_parser(sub)
    add_export_parser(sub)
    add_eval_parsers(sub)
    add_demo_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, "osn")


if __name__ == "__main__":
    sys.exit(main())

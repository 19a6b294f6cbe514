"""What every benchmark prints first: the exact command, so a figure can be reproduced."""

from __future__ import annotations

import shlex
import sys


def print_command() -> None:
    """Print ``command: python benchmarks/NAME.py ARGS`` (flushed, before any figure)."""
    print("command: " + shlex.join(["python", *sys.argv]), flush=True)

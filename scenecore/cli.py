"""Shared command-line plumbing: one-line user errors, ``--debug`` tracebacks, exit codes."""

from __future__ import annotations

import argparse
import os
import sys
import traceback
from typing import Callable, Sequence


def blas_on_one_thread() -> None:
    """numpy's OpenBLAS on one thread, in this process and the processes it starts; the command
    line entry points call it before numpy is imported (later, only child processes see it).

    The toolkit's numpy work is small matrices (poses, rays of one view), which OpenBLAS threads do
    not speed up, yet after each call its idle threads spin in ``sched_yield`` for a while: on two
    cores that spinning takes CPU time from an evaluation's render threads, for the same results.
    torch keeps its own thread pool. A value the user set wins.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit code 2, no traceback."""


#: Exceptions that describe bad input rather than a bug; their message is the whole story.
#: FileExistsError: e.g. ``osn train --out`` naming an existing run without ``--resume``.
USER_ERRORS: tuple[type[BaseException], ...] = (UserError, ValueError, FileNotFoundError, FileExistsError, KeyError)


def run_cli(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None, prog: str
) -> int:
    """Parse ``argv`` and call ``args.func(args)``; map user errors to one line and exit 2."""
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
        return int(rc or 0)
    except KeyboardInterrupt:
        # Subcommands whose rerun needs a flag to continue (``osn train --resume``) say so.
        hint = getattr(args, "resume_hint", "run the same command again to resume")
        print(f"{prog}: interrupted; {hint}", file=sys.stderr)
        return 130
    except USER_ERRORS as e:
        if getattr(args, "debug", False):
            traceback.print_exc()
        msg = str(e) if not isinstance(e, KeyError) else f"missing key {e}"
        # One line even when a library's message (embedded after the file name) spans several.
        msg = " ".join(part.strip() for part in msg.splitlines() if part.strip())
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")


def subcommand(
    subparsers: argparse._SubParsersAction, name: str, func: Callable[[argparse.Namespace], int | None], help: str, description: str | None = None
) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        name, help=help, description=description or help, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    add_common(p)
    p.set_defaults(func=func)
    return p

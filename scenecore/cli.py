"""Shared command-line plumbing: one-line user errors, ``--debug`` tracebacks, exit codes."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import traceback
from typing import Any, Callable, Iterator, Sequence


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

#: Exit code of a file the system would not read or write (disk full, quota, I/O error, no
#: permission, read-only): distinct from 1 (a check failed) and 2 (bad input).
OS_ERROR_EXIT = 3


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that cleanup runs as for Ctrl-C (worker processes
    are ended, temporary files removed); the command then exits ``128 + signal number``."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def os_error_line(e: OSError) -> str:
    """``FILE: cause`` for an error of the system: the file (both of a rename) and its reason."""
    files = " -> ".join(str(f) for f in (e.filename, e.filename2) if f is not None)
    cause = e.strerror or str(e)
    return f"{files}: {cause}" if files else cause


@contextlib.contextmanager
def sigterm_raises() -> Iterator[list[int]]:
    """Turn SIGTERM into :class:`Terminated` and Ctrl-C into ``KeyboardInterrupt`` for the
    ``with`` block (main thread only; else a no-op), recording each signal in the yielded list.

    The record matters because Python ignores an exception raised while a finaliser or a logging
    lock's release runs ("Exception ignored in ..."): a signal landing there would otherwise let
    the command finish as if nothing happened. A process forked inside the block inherits the
    handlers; there SIGTERM restores the default and ends the process, as SIGTERM intends, and
    Ctrl-C raises ``KeyboardInterrupt`` as Python's own handler does.
    """
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    owner = os.getpid()

    def handler(signum: int, _frame: Any) -> None:
        if os.getpid() != owner:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        received.append(signum)
        raise Terminated(signum) if signum == signal.SIGTERM else KeyboardInterrupt

    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, handler)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # a job started with Ctrl-C ignored keeps it so
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, handler)
    try:
        yield received
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def run_cli(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None, prog: str
) -> int:
    """Parse ``argv`` and call ``args.func(args)``; map user errors to one line and exit 2, errors
    of the system on a file (``OSError``) to one line and :data:`OS_ERROR_EXIT`, Ctrl-C to 130 and
    SIGTERM to 143, after the command's cleanup ran."""
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        with sigterm_raises() as received:
            rc = args.func(args)
        if received:  # the exception was swallowed where Python ignores it: still a stop
            return _stopped(prog, args, received[0])
        return int(rc or 0)
    except KeyboardInterrupt as e:
        return _stopped(prog, args, e.signum if isinstance(e, Terminated) else signal.SIGINT)
    except USER_ERRORS as e:
        msg = str(e) if not isinstance(e, KeyError) else f"missing key {e}"
        return _one_line(prog, args, msg, 2)
    except OSError as e:  # after USER_ERRORS: FileNotFoundError and FileExistsError are bad input
        return _one_line(prog, args, os_error_line(e), OS_ERROR_EXIT)


def _stopped(prog: str, args: argparse.Namespace, signum: int) -> int:
    """Say the command was stopped (and how to continue); return ``128 + signum``."""
    # Subcommands whose rerun needs a flag to continue (``osn train --resume``) say so.
    hint = getattr(args, "resume_hint", "run the same command again to resume")
    stopped = "terminated" if signum == signal.SIGTERM else "interrupted"
    print(f"{prog}: {stopped}; {hint}", file=sys.stderr)
    return 128 + int(signum)


def _one_line(prog: str, args: argparse.Namespace, msg: str, code: int) -> int:
    """Print ``PROG: error: MSG`` on one line (the traceback too under ``--debug``); return ``code``."""
    if getattr(args, "debug", False):
        traceback.print_exc()
    # One line even when a library's message (embedded after the file name) spans several.
    msg = " ".join(part.strip() for part in msg.splitlines() if part.strip())
    print(f"{prog}: error: {msg}", file=sys.stderr)
    return code


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")


class DeprecatedAlias(argparse.Action):
    """An old spelling of an option, kept for one release so old scripts still run: hidden from
    ``--help``, parsed exactly as ``target`` (the new spelling's action, whose ``dest`` it shares),
    and one ``WARNING`` line on stderr naming the new spelling. ``default`` is SUPPRESS, so an
    alias not given leaves the new option's default alone (a positional one then is not called)."""

    def __init__(self, option_strings: Sequence[str], dest: str, *, target: argparse.Action, new: str,
                 nargs: int | str | None = None, metavar: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=target.nargs if nargs is None else nargs, const=target.const,
                         default=argparse.SUPPRESS, type=target.type, choices=target.choices, required=False,
                         help=argparse.SUPPRESS, metavar=metavar or target.metavar)
        self.target, self.new = target, new

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        old = option_string or f"the positional {self.metavar or self.dest.upper()}"
        print(f"WARNING {parser.prog}: {old} is deprecated and goes in the next release; use {self.new}", file=sys.stderr)
        self.target(parser, namespace, values, option_string)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str, **positional: Any) -> None:
    """Accept ``old`` as a hidden, warning spelling of ``parser``'s option ``new`` (added before).

    ``old`` not starting with ``-`` is a former positional: it takes ``new``'s dest, and
    ``positional`` gives its ``nargs`` and ``metavar`` (the name the warning shows). ``new`` may
    carry a metavar for the message (``"--data DATASET"``)."""
    target = parser._option_string_actions[new.split()[0]]
    if old.startswith("-"):
        parser.add_argument(old, action=DeprecatedAlias, dest=target.dest, target=target, new=new)
    else:
        parser.add_argument(target.dest, action=DeprecatedAlias, target=target, new=new, **positional)


def subcommand(
    subparsers: argparse._SubParsersAction, name: str, func: Callable[[argparse.Namespace], int | None], help: str, description: str | None = None
) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        name, help=help, description=description or help, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    add_common(p)
    p.set_defaults(func=func)
    return p

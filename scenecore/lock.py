"""Exclusive output locks: one writer per output directory or file (stdlib only, POSIX).

Every command that writes a dataset, a run, an export or a report holds the lock of its output
while it works, so a second command on the same output stops at once with one line naming the
first (``DIR: in use by pid 1234 (osn train ...) on HOST; wait for it or stop it``) instead of
interleaving its files with the first's or deleting the first's live temporary files as a killed
run's leftovers. Clean-up of such leftovers therefore happens only under the lock.

The lock is ``fcntl.flock`` on a file *beside* the output, ``.NAME.lock`` in its parent
directory: the same path whether or not the output exists yet, and outside a directory that a
writer replaces by renaming (``osn export``). The kernel drops the lock when its holder dies, so
a lock file left by a killed process is taken over by the next run without asking. The file
records the holder's pid, host and command for the refusal message; a holder deletes it when it
is done (while still holding it: a waiter that locked the deleted file checks the path again).
Locks are per output: a command's child process writing another output (``osn demo``'s
background ``benchgen generate``) takes that output's own lock. A process that asks again for a
lock it holds gets it (nested calls), and a forked child does not keep its parent's locks.
This module is not imported by the Blender add-on's code paths (``fcntl`` is POSIX only).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shlex
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

from .cli import UserError

__all__ = ["OutputInUse", "lock_path", "read_holder", "output_lock"]

#: A refused writer waits this long for a holder to write its record (or finish releasing).
_SETTLE_SECONDS = 1.0

_HELD: dict[Path, list[int]] = {}  # lock file -> [fd, depth] held by this process
_HELD_GUARD = threading.Lock()


class OutputInUse(UserError):
    """The output is locked by another process: one line naming it, exit code 2."""


def lock_path(output: str | Path) -> Path:
    """The lock file of ``output``: ``.NAME.lock`` beside it (its real path, so aliases share it)."""
    out = Path(output).resolve()
    return out.parent / f".{out.name}.lock"


def read_holder(output: str | Path) -> dict[str, Any] | None:
    """The record of the process holding (or, killed, last holding) ``output``'s lock, or None."""
    try:
        rec = json.loads(lock_path(output).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and isinstance(rec.get("pid"), int) else None


def _command() -> str:
    """This process's command line, short: ``osn train ...`` rather than the interpreter's path."""
    argv = list(getattr(sys, "orig_argv", sys.argv))
    if len(argv) > 1 and not argv[1].startswith("-"):  # python SCRIPT ARGS (a console script)
        argv = argv[1:]
    if argv:
        argv[0] = os.path.basename(argv[0])
    text = " ".join(shlex.join(argv).split())  # no newline may break the one-line message
    return text if len(text) <= 160 else text[:157] + "..."


def _alive(rec: dict[str, Any]) -> bool:
    """False when the record names a process of this host that no longer exists."""
    if rec.get("host") != socket.gethostname():
        return True
    try:
        os.kill(rec["pid"], 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        pass
    return True


def _refusal(output: Path, rec: dict[str, Any] | None) -> OutputInUse:
    if rec is None:
        return OutputInUse(f"{output}: in use by another process; wait for it or stop it")
    return OutputInUse(f"{output}: in use by pid {rec['pid']} ({rec.get('command', '?')}) on "
                       f"{rec.get('host', '?')}; wait for it or stop it")


def _open_locked(path: Path, output: Path) -> int:
    """Open ``path`` and lock it without waiting; raise :class:`OutputInUse` naming the holder."""
    deadline = time.monotonic() + _SETTLE_SECONDS
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except PermissionError:  # another user's lock file: locking needs no write access
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            rec = read_holder(output)
            if (rec is None or not _alive(rec)) and time.monotonic() < deadline:
                # the new holder has not yet replaced a killed one's record, or it is releasing
                time.sleep(0.02)
                continue
            raise _refusal(output, rec) from None
        try:
            same = os.path.samestat(os.stat(path), os.fstat(fd))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # locked a file its last holder deleted on release: lock the one the path names now


def _write_record(fd: int) -> None:
    rec = {"pid": os.getpid(), "host": socket.gethostname(), "command": _command()}
    with contextlib.suppress(OSError):  # a read-only lock file: the lock holds, the message is vaguer
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(rec) + "\n").encode(), 0)


@contextlib.contextmanager
def output_lock(output: str | Path) -> Iterator[Path]:
    """Hold ``output``'s exclusive lock for the ``with`` block; yields the lock file's path.

    Raises:
        OutputInUse: another live process holds it (a ``UserError``: one line, exit code 2).
    """
    path = lock_path(output)
    with _HELD_GUARD:
        held = _HELD.get(path)
        if held is not None:
            held[1] += 1
    if held is None:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = _open_locked(path, Path(output))
        _write_record(fd)
        with _HELD_GUARD:
            _HELD[path] = held = [fd, 1]
    try:
        yield path
    finally:
        with _HELD_GUARD:
            held[1] -= 1
            last = held[1] == 0 and _HELD.get(path) is held
            if last:
                del _HELD[path]
        if last:
            with contextlib.suppress(OSError):
                os.unlink(path)  # while still holding it; see the module docstring
            os.close(held[0])


def _forget_in_child() -> None:
    """A forked child (a worker pool) must not hold its parent's locks past the parent's death."""
    global _HELD_GUARD
    _HELD_GUARD = threading.Lock()  # another thread may have held it at the fork
    for fd, _ in _HELD.values():
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD.clear()


os.register_at_fork(after_in_child=_forget_in_child)

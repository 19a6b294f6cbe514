"""Atomic, shareable file output: every file the toolkit publishes goes through here (numpy + stdlib).

A write goes to a temporary file in the target's directory and is renamed onto the target, so a
reader never sees a truncated file. ``tempfile`` creates that file ``0600`` (and ``mkdtemp``
directories ``0700``); :func:`publish_mode` gives them the mode an ordinary ``open``/``mkdir``
would have had under the process umask before they are published, so a benchmark written under
umask 022 is readable by colleagues and one written under 077 stays private.

A directory whose files must change together (a report, an export) is written the same way:
:func:`atomic_dir` fills a temporary sibling and swaps it in, so a reader sees the old set or the
new one, never a mix. :func:`own_dir` adds a marker file, so that only a directory this toolkit
wrote is ever replaced.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import shutil
import stat
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Collection, Iterator

import numpy as np

from .errors import DatasetError

__all__ = ["current_umask", "publish_mode", "atomic_path", "atomic_write_bytes", "atomic_write_json", "read_json",
           "atomic_dir", "own_dir", "check_own_dir", "unmarked_report", "remove_stale_siblings", "swap_dir"]

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process umask, read without changing it where the system allows.

    ``os.umask`` can only be read by setting it, which races with other threads creating files;
    Linux reports it in ``/proc/self/status``. Elsewhere it is set to the most private value for
    the instant it takes to read it, so a concurrent file is never created more open than asked.
    """
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o077)
        os.umask(mask)
    return mask


def publish_mode(path: str | Path) -> None:
    """Give a file or directory made by ``tempfile`` the mode the umask asks for.

    Files get ``0o666 & ~umask`` and directories ``0o777 & ~umask`` (what ``open`` and ``mkdir``
    give), instead of ``tempfile``'s private ``0o600`` / ``0o700``. Call it before publishing.
    """
    base = 0o777 if stat.S_ISDIR(os.stat(path).st_mode) else 0o666
    os.chmod(path, base & ~current_umask())


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``, else delete it.

    For writers that need a file name (OpenEXR, OpenVDB): the final file appears complete or not
    at all, with the mode the umask gives (see :func:`publish_mode`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        # After the writer: one that recreates the file rather than truncating it gets it right too.
        publish_mode(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        _name_target(e, {tmp: path})
        raise


def _name_target(e: BaseException, renames: dict[str, Path]) -> None:
    """Make an ``OSError`` of a temporary name (or of none: a failed ``write`` has none) name the
    file the user asked for, so that its one-line message says which output failed."""
    if not isinstance(e, OSError):
        return
    name = None if e.filename is None else os.fspath(e.filename)
    if name is None and len(renames) == 1:
        e.filename = str(next(iter(renames.values())))
        return
    for tmp, target in renames.items():
        if name is not None and (name == tmp or name.startswith(tmp + os.sep)):
            e.filename = str(target) + name[len(tmp):]


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same directory, fsync, rename)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"cannot serialise {type(o).__name__}")


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (numpy arrays and scalars become lists and numbers)."""
    atomic_write_bytes(path, (json.dumps(obj, indent=1, default=_json_default) + "\n").encode())


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; raise ``DatasetError`` naming ``path`` when it is missing or not JSON."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: missing file")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None


# --------------------------------------------------------------------------------------------
# Directories
# --------------------------------------------------------------------------------------------


def remove_stale_siblings(out: Path) -> None:
    """Delete temporary siblings of ``out`` left by a killed writer (``kill -9`` skips cleanup).

    ``.NAME.PID.RANDOM.partial`` (being written) and ``.NAME.old-PID`` (the previous directory
    during the swap). Call it under ``out``'s lock (:mod:`scenecore.lock`), so they belong to no
    live writer; names are matched exactly, so the temporaries of ``NAME.other`` are not touched.
    """
    stale = re.compile(rf"\.{re.escape(out.name)}\.(\d+\.[^.]+\.partial|old-\d+)")
    for p in out.parent.glob(f".{glob.escape(out.name)}.*"):
        if stale.fullmatch(p.name):
            shutil.rmtree(p, ignore_errors=True)


def swap_dir(tmp: Path, out: Path) -> None:
    """Rename the finished temporary directory ``tmp`` to ``out``, replacing a previous ``out``."""
    publish_mode(tmp)  # mkdtemp makes it private; an output is shared as the umask allows
    if not out.exists():
        os.rename(tmp, out)
        return
    old = out.with_name(f".{out.name}.old-{os.getpid()}")
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(out: str | Path) -> Iterator[Path]:
    """Yield an empty temporary sibling of ``out``; when the block succeeds it replaces ``out``
    whole (:func:`swap_dir`), else it is deleted and ``out`` is left as it was.

    The caller holds ``out``'s lock and has decided that ``out`` may be replaced. An ``OSError``
    naming a file inside the temporary names it at its place in ``out``.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_siblings(out)
    tmp = tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}.", suffix=".partial", dir=out.parent)
    try:
        yield Path(tmp)
        swap_dir(Path(tmp), out)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        _name_target(e, {tmp: out})
        raise


def check_own_dir(out: str | Path, marker: str, what: str, unmarked: Callable[[Path], bool] | None = None) -> Path:
    """``out`` resolved, if a writer of ``what`` may replace it: missing, an empty directory, or a
    directory holding ``marker`` (or one ``unmarked`` recognises as written before markers).

    Raises:
        FileExistsError: anything else (a user error: one line naming ``out``); its files are kept.
    """
    out = Path(out).resolve()
    if not out.exists() or (out.is_dir() and ((out / marker).is_file() or not any(out.iterdir())
                                              or (unmarked is not None and unmarked(out)))):
        return out
    raise FileExistsError(f"{out}: exists and is not {what} (it holds files this tool did not write); "
                          "choose another --out")


@contextlib.contextmanager
def own_dir(out: str | Path, marker: str, what: str, unmarked: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """:func:`atomic_dir` for a directory of ``what`` (a report): refused unless :func:`check_own_dir`
    allows it, and marked with ``marker`` so that the next writer knows it may replace it."""
    from .lock import output_lock  # fcntl: POSIX only, and the Blender add-on never writes these

    with output_lock(out):
        target = check_own_dir(out, marker, what, unmarked)
        with atomic_dir(target) as tmp:
            yield tmp
            atomic_write_json(tmp / marker, {"written_by": what})


def unmarked_report(out: Path, names: Collection[str], index: str, identify: Callable[[Any], bool]) -> bool:
    """Whether ``out`` is a report directory written before markers existed: nothing but files
    named in ``names``, among them the JSON file ``index``, whose content ``identify`` accepts."""
    try:
        entries = list(out.iterdir())
        return (all(p.name in names and p.is_file() for p in entries) and (out / index).is_file()
                and bool(identify(json.loads((out / index).read_text()))))
    except (OSError, ValueError):
        return False

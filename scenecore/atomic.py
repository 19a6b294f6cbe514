"""Atomic, shareable file output: every file the toolkit publishes goes through here (numpy + stdlib).

A write goes to a temporary file in the target's directory and is renamed onto the target, so a
reader never sees a truncated file. ``tempfile`` creates that file ``0600`` (and ``mkdtemp``
directories ``0700``); :func:`publish_mode` gives them the mode an ordinary ``open``/``mkdir``
would have had under the process umask before they are published, so a benchmark written under
umask 022 is readable by colleagues and one written under 077 stays private.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import DatasetError

__all__ = ["current_umask", "publish_mode", "atomic_path", "atomic_write_bytes", "atomic_write_json", "read_json"]

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
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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

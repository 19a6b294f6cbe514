"""Paths built from names read in files must stay inside the directory they are joined to.

A frame name in ``scene.json`` or a file in ``osn_export.json`` becomes part of a path the toolkit
reads or writes; an absolute name, or one with ``..``, would reach outside the dataset, the export
or the output directory. Standard library only: the Blender add-on carries a copy of scenecore.
"""

from __future__ import annotations

import ntpath
import os
from pathlib import Path
from typing import Any

__all__ = ["name_problem", "join_inside"]


def name_problem(rel: Any) -> str | None:
    """Why ``rel`` is not a plain relative name (``a`` or ``a/b``), or None when it is.

    Checked as text, so the answer is the same on every system: a backslash is a separator on
    Windows and a drive (``C:``) makes a name absolute there, so both are refused everywhere.
    """
    if not isinstance(rel, str) or not rel:
        return "is not a non-empty string"
    if "\x00" in rel:
        return "contains a NUL character"
    if "\\" in rel:
        return "contains a backslash"
    if rel.startswith("/"):
        return "is an absolute path"
    if ntpath.splitdrive(rel)[0]:
        return "names a drive"
    parts = rel.split("/")
    if ".." in parts:
        return "contains '..'"
    if any(p in ("", ".") for p in parts):
        return "has an empty or '.' part"
    return None


def _within(path: str, base: str) -> bool:
    try:
        return os.path.commonpath([path, base]) == base
    except ValueError:  # on different drives (Windows)
        return False


def join_inside(
    base: str | Path, rel: Any, what: str, error: type[Exception] = ValueError, source: str | Path | None = None,
    resolve: bool = False,
) -> Path:
    """``base / rel``, or ``error`` (one line naming ``source`` or ``base``, ``what`` and ``rel``)
    when ``rel`` is not a plain relative name (:func:`name_problem`).

    With ``resolve``, symbolic links are followed too: a file inside ``base`` that links outside
    it is refused with a line naming the file. Use it where the directory comes from someone
    else (an export); names alone suffice where the toolkit made or was pointed at the directory.
    """
    problem = name_problem(rel)
    if problem:
        raise error(f"{source or Path(base)}: {what} {rel!r} {problem}; it must be a relative name inside {Path(base)}")
    path = Path(base) / rel
    if resolve and not _within(os.path.realpath(path), os.path.realpath(base)):
        raise error(f"{path}: a symbolic link leads outside {base} ({what} {rel!r})")
    return path

"""File digests of a score: SHA-256 per file, per group of files and over a set, and the
``sha256sum``-format listings beside ``metrics.json`` (:mod:`benchgen.score.provenance` says what
is hashed, :mod:`benchgen.score.check` compares them again).

Files are hashed in chunks as they are read (:data:`CHUNK`), regular files only
(:func:`scenecore.dataset.images.open_regular`: a FIFO or a device is refused, one line naming it),
and only the size a file had when opened is read.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from scenecore import dataset as D
from scenecore.dataset.images import open_regular, read_pieces

#: Bytes hashed per read.
CHUNK = 1 << 20
PREDICTIONS_LISTING = "predictions.sha256"
DATASET_LISTING = "dataset.sha256"


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a regular file, read in :data:`CHUNK` pieces up to the size it had when
    opened (:func:`scenecore.dataset.images.read_pieces`); ``DatasetError`` naming it when it is
    missing, not a regular file or changed size."""
    fh, size = open_regular(path)
    h = hashlib.sha256()
    with fh:
        for chunk in read_pieces(fh, size, path, CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _escape(rel: str) -> tuple[str, str]:
    """``sha256sum``'s escaping of a name holding a backslash or a newline: ``("\\", escaped)``."""
    if "\\" in rel or "\n" in rel:
        return "\\", rel.replace("\\", "\\\\").replace("\n", "\\n")
    return "", rel


def listing_bytes(files: dict[str, str]) -> bytes:
    """``files`` (relative path -> SHA-256) as ``sha256sum`` lines in sorted path order."""
    lines = []
    for rel in sorted(files):
        prefix, name = _escape(rel)
        lines.append(f"{prefix}{files[rel]}  {name}\n")
    return "".join(lines).encode()


def parse_listing(data: bytes, where: Path) -> dict[str, str]:
    """The inverse of :func:`listing_bytes`; ``DatasetError`` naming ``where`` on a bad line."""
    out = {}
    for k, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        escaped = line.startswith("\\")
        body = line[1:] if escaped else line
        digest, sep, rel = body.partition("  ")
        if not sep or len(digest) != 64:
            raise D.DatasetError(f"{where}: line {k} is not '<sha256>  <path>'")
        if escaped:
            rel = rel.replace("\\\\", "\0").replace("\\n", "\n").replace("\0", "\\")
        out[rel] = digest
    return out


def set_digest(files: dict[str, str]) -> str:
    """One digest of a file set: the SHA-256 of its :func:`listing_bytes`."""
    return hashlib.sha256(listing_bytes(files)).hexdigest()


def tree_files(root: Path, group: str) -> list[str]:
    """Paths relative to ``root`` of every file under ``root/group``, in sorted order; names
    starting with ``.`` are skipped at every level, directory links are followed (a link back to
    a directory it lies in is not entered again). Anything that is not a directory is listed:
    hashing it refuses what is not a regular file."""
    out: list[str] = []

    def walk(d: Path, rel: str, above: frozenset) -> None:
        st = os.stat(d)
        key = (st.st_dev, st.st_ino)
        if key in above:
            return
        with os.scandir(d) as it:
            entries = sorted(it, key=lambda e: e.name)
        for e in entries:
            if e.name.startswith("."):
                continue
            r = f"{rel}/{e.name}" if rel else e.name
            if e.is_dir():  # follows links
                walk(Path(e.path), r, above | {key})
            else:
                out.append(r)

    walk(root / group, group, frozenset())
    return out


# Set before forking workers (:func:`benchgen.score.parallel.ordered_map`), inherited unpickled.
_JOB: dict[str, Any] = {}


def _hash_group(group: str, files: tuple[str, ...] | None) -> dict[str, str]:
    """``rel -> sha256`` of a group's files (``None``: every file under the directory ``group``)."""
    root: Path = _JOB["root"]
    rels = tree_files(root, group) if files is None else list(files)
    base = str(root)  # plain strings: a Path per file costs more than hashing a small one
    return {rel: file_sha256(os.path.join(base, rel)) for rel in rels}


@dataclass
class FileSet:
    """Digests of files under ``root``, by group (a candidate directory, a configuration, a file)."""

    root: Path
    groups: dict[str, dict[str, str]]
    listing: str

    @property
    def files(self) -> dict[str, str]:
        return {rel: h for g in self.groups.values() for rel, h in g.items()}

    def group_digest(self, group: str) -> str:
        """A directory's digest over its files' paths relative to it (identical directories have
        equal digests); a single file's is its own SHA-256."""
        files = self.groups[group]
        if list(files) == [group]:
            return files[group]
        return set_digest({rel[len(group) + 1:]: h for rel, h in files.items()})

    def record(self) -> dict[str, Any]:
        files = self.files
        return {"root": str(self.root), "sha256": set_digest(files), "files": len(files), "listing": self.listing,
                "groups": {g: self.group_digest(g) for g in self.groups}}


def hash_groups(root: str | Path, groups: dict[str, Sequence[str] | None], listing: str, workers: int = 1) -> FileSet:
    """Hash every group of ``root`` (``None``: walk the directory ``group``), in ``workers``
    processes (same result for any number)."""
    from benchgen.score.parallel import ordered_map

    root = Path(root).resolve()
    names = list(groups)
    tasks = [(g, None if groups[g] is None else tuple(groups[g])) for g in names]
    _JOB.update(root=root)
    try:
        hashed = list(ordered_map(_hash_group, tasks, workers))
    finally:
        _JOB.clear()
    return FileSet(root, dict(zip(names, hashed)), listing)

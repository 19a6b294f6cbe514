"""Stored co-visibility masks: ``configs/GGG/covisibility.npz`` (docs/dataset-format.md).

A configuration's co-visibility masks (which test pixels some training frame of that
configuration saw, docs/metrics.md) depend on the dataset only, so ``benchgen generate`` computes
them once and stores them; ``benchgen score`` reads them instead of recomputing them and
``benchgen verify`` recomputes and compares. This module owns the file, not the rule: the rule
(:mod:`benchgen.score.covisibility`) is named by the ``version`` and ``rtol`` stored beside the masks.

One ``.npz`` (zip of ``.npy`` arrays, deflated, no pickles) per configuration, with exactly:

* ``masks``: uint8 ``(V, ceil(H W / 8))``, each row one test view's ``(H, W)`` boolean mask
  flattened row-major and bit-packed by ``numpy.packbits`` (most significant bit first, the last
  byte zero-padded); True = co-visible (evaluated);
* ``views``: unicode ``(V,)``, the names of the dataset's test frames in (time, view) order;
* ``version``: int64 scalar, the version of the mask rule; ``rtol``: float64 scalar, its depth tolerance.

Reads are bounded: the file must be a regular file no larger than such masks can be, and every
member's ``.npy`` header must declare exactly the shape and dtype the manifest implies before any
array is read.
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes
from .images import read_regular
from .model import DatasetError, Frame, Scene, config_dirname

__all__ = ["COVISIBILITY_FILE", "CovisibilityMasks", "covisibility_frames", "covisibility_path", "read_covisibility",
           "write_covisibility"]

COVISIBILITY_FILE = "covisibility.npz"
#: Longest frame name the ``views`` member may hold (characters; a manifest's names are far shorter).
MAX_NAME = 256
_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


@dataclass
class CovisibilityMasks:
    """One configuration's stored masks ``(V, H, W)`` bool over :func:`covisibility_frames`, and
    the rule they were computed with."""

    masks: np.ndarray
    version: int
    rtol: float
    path: Path


def covisibility_path(root: str | Path, config: int) -> Path:
    """``configs/GGG/covisibility.npz`` of configuration ``config``."""
    return Path(root) / "configs" / config_dirname(config) / COVISIBILITY_FILE


def covisibility_frames(scene: Scene) -> list[Frame]:
    """The test frames a mask file covers, in its row order: (time, view)."""
    return sorted(scene.test_frames, key=lambda f: (f.time_index, f.view))


def _row_bytes(scene: Scene) -> int:
    return math.ceil(scene.width * scene.height / 8)


def write_covisibility(root: str | Path, config: int, scene: Scene, masks: np.ndarray, version: int, rtol: float) -> Path:
    """Store configuration ``config``'s masks ``(V, H, W)`` bool (rows as :func:`covisibility_frames`)
    atomically; returns the path."""
    frames = covisibility_frames(scene)
    masks = np.asarray(masks)
    if masks.dtype != bool or masks.shape != (len(frames), scene.height, scene.width):
        raise ValueError(f"masks must be bool {(len(frames), scene.height, scene.width)}, got {masks.dtype} {masks.shape}")
    arrays = {"masks": np.packbits(masks.reshape(len(frames), -1), axis=1),
              "views": np.array([f.name for f in frames], dtype=f"<U{max([1] + [len(f.name) for f in frames])}"),
              "version": np.int64(version), "rtol": np.float64(rtol)}
    buf = io.BytesIO()
    # What numpy.savez_compressed writes, with a fixed member date so that the same masks give
    # the same bytes (generate's output does not depend on when or how it was sharded).
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w") as fh:
                np.lib.format.write_array(fh, np.asarray(a), allow_pickle=False)
    path = covisibility_path(root, config)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _max_file_bytes(scene: Scene) -> int:
    """Most bytes a mask file of this manifest can take: its arrays stored uncompressed plus the
    zip's and the headers' overhead (deflate never grows data by more than a few bytes per block)."""
    V = len(scene.test_frames)
    return 2 * (V * _row_bytes(scene) + V * 4 * MAX_NAME) + 64 * 1024


def _expected(scene: Scene) -> dict[str, tuple[tuple[int, ...], str]]:
    """Member -> (shape, dtype kind and size check) the manifest implies."""
    V = len(scene.test_frames)
    return {"masks.npy": ((V, _row_bytes(scene)), "uint8"), "views.npy": ((V,), "unicode"),
            "version.npy": ((), "int64"), "rtol.npy": ((), "float64")}


def _dtype_ok(dtype: np.dtype, want: str) -> bool:
    if want == "unicode":
        return dtype.kind == "U" and dtype.itemsize <= 4 * MAX_NAME
    return dtype == np.dtype(want)


def _check_headers(zf: zipfile.ZipFile, scene: Scene, path: Path) -> None:
    """Every member is one of :func:`_expected` with exactly its shape and dtype (read from the
    ``.npy`` headers, before any array is allocated)."""
    expected = _expected(scene)
    names = sorted(i.filename for i in zf.infolist())
    if names != sorted(expected):
        raise DatasetError(f"{path}: holds {names}, expected the arrays {sorted(expected)}")
    for name, (shape, want) in expected.items():
        with zf.open(name) as fh:
            version = np.lib.format.read_magic(fh)
            if version not in _HEADERS:
                raise DatasetError(f"{path}: member {name} has .npy format version {version}")
            got_shape, fortran, dtype = _HEADERS[version](fh)
        if got_shape != shape or fortran or not _dtype_ok(dtype, want):
            raise DatasetError(f"{path}: {name[:-4]} is {dtype} {got_shape}, expected {want} {shape} "
                               f"({len(scene.test_frames)} test views of {scene.width}x{scene.height})")


def read_covisibility(root: str | Path, scene: Scene, config: int) -> CovisibilityMasks:
    """Configuration ``config``'s stored masks, checked against the manifest.

    Raises:
        FileNotFoundError: no mask file (a dataset written before they were stored).
        DatasetError: one line naming the file: not a regular file, larger than such masks can
            be, not a readable ``.npz``, a member of another shape or dtype, or view names that
            are not the dataset's test frames in (time, view) order.
    """
    path = covisibility_path(root, config)
    if not path.exists() and not path.is_symlink():
        raise FileNotFoundError(path)
    data = read_regular(path, _max_file_bytes(scene))
    frames = covisibility_frames(scene)
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            _check_headers(zf, scene, path)
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                packed, views, version, rtol = z["masks"], z["views"], int(z["version"]), float(z["rtol"])
    except DatasetError:
        raise
    except Exception as e:  # noqa: BLE001 - any decoding failure (bad zip, CRC, truncated member) is a corrupt file
        raise DatasetError(f"{path}: cannot read the co-visibility masks ({' '.join(str(e).split())})") from None
    if views.tolist() != [f.name for f in frames]:
        first = next((i for i, (a, f) in enumerate(zip(views.tolist(), frames)) if a != f.name), 0)
        raise DatasetError(f"{path}: row {first} is view {views[first]!r}, expected {frames[first].name!r} "
                           "(the dataset's test frames in (time, view) order)")
    if not (math.isfinite(rtol) and rtol >= 0):
        raise DatasetError(f"{path}: rtol is {rtol}, expected a finite tolerance >= 0")
    masks = np.unpackbits(packed, axis=1, count=scene.width * scene.height).astype(bool)
    return CovisibilityMasks(masks.reshape(len(frames), scene.height, scene.width), version, rtol, path)

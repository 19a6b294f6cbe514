"""Unbounded reads: files that never end, block, or inflate far past what they can hold.

A prediction file of ``benchgen score`` that is a FIFO or a link to ``/dev/zero``, a small PNG
or EXR whose header (or compressed data) declares gigabytes of pixels, and an export ``.npz``
member whose ``.npy`` header declares a gigabyte are each refused with one line naming the file,
before anything large is allocated. The malicious files are built small (a PNG's IDAT of
compressed zeros, an EXR written by hand with compressed blocks, a ``.npy`` header with a
truncated body), and allocation is measured with ``tracemalloc`` (numpy and bytes report to it).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import resource
import shutil
import struct
import subprocess
import sys
import tracemalloc
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from benchgen.score.pngread import PngError, decode_rgb
from benchgen.score.predictions import PredictionDir, PredictionError
from scenecore import dataset as D
from scenecore import export_format as core
from tests.synthetic import write_synthetic_dataset

REPO = Path(__file__).resolve().parents[1]
#: Peak Python-visible allocation a refused read may make: far below every bomb built here.
SMALL = 8 << 20


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("bounded") / "ds"
    write_synthetic_dataset(root)
    return root


@pytest.fixture
def pred(dataset: Path, tmp_path: Path) -> Path:
    """A prediction directory with one candidate ``a``, a copy of ``configs/000`` (which scores)."""
    shutil.copytree(dataset / "configs" / D.config_dirname(0), tmp_path / "pred" / "a")
    return tmp_path / "pred"


def _view(pred: Path, dataset: Path, kind: str) -> Path:
    """Candidate ``a``'s file of ``kind`` for the first evaluated view."""
    name = D.load_scene(dataset).test_frames[0].name
    return pred / "a" / kind / (name + {"rgb": ".png", "depth": ".exr", "ids": ".png"}[kind])


def _peak(fn: Callable[[], object]) -> tuple[BaseException | None, int]:
    """The exception ``fn`` raised (None if it returned) and its peak traced allocation in bytes."""
    tracemalloc.start()
    try:
        fn()
        error = None
    except Exception as e:  # noqa: BLE001 - the caller asserts which
        error = e
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return error, peak


def _load(pred: Path, dataset: Path) -> Callable[[], object]:
    scene = D.load_scene(dataset)
    return lambda: PredictionDir(pred, scene, [f.name for f in scene.test_frames]).load(0)


# Loads candidate 0 in a fresh process: exit 2 with the error on stderr, 0 when it loads.
_LOAD_IN_PROCESS = """
import sys
from scenecore import dataset as D
from benchgen.score.predictions import PredictionDir, PredictionError
scene = D.load_scene(sys.argv[2])
try:
    PredictionDir(sys.argv[1], scene, [f.name for f in scene.test_frames]).load(0)
except PredictionError as e:
    sys.exit(f"{e}")
"""


def _load_guarded(pred: Path, dataset: Path) -> subprocess.CompletedProcess:
    """Load candidate 0 in a subprocess with 4 GiB of address space and 60 s: a read that blocks
    or never ends fails the test instead of hanging it or exhausting the machine."""
    limit = lambda: resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))  # noqa: E731
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}  # BLAS buffers stay small
    return subprocess.run([sys.executable, "-c", _LOAD_IN_PROCESS, str(pred), str(dataset)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=60, preexec_fn=limit)


# --------------------------------------------------------------------------------------------
# Prediction files that are not regular files
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["rgb", "depth", "method.json"])
@pytest.mark.parametrize("special", ["FIFO", "link to /dev/zero", "directory"])
def test_prediction_that_is_not_a_regular_file_is_refused(pred: Path, dataset: Path, special: str, kind: str) -> None:
    """A FIFO once blocked ``benchgen score`` forever and a link to /dev/zero read until MemoryError."""
    path = pred / kind if kind == "method.json" else _view(pred, dataset, kind)
    path.unlink(missing_ok=True)
    if special == "FIFO":
        os.mkfifo(path)
    elif special == "directory":
        path.mkdir()
    else:
        path.symlink_to("/dev/zero")
    r = _load_guarded(pred, dataset)
    what = {"FIFO": "a FIFO", "link to /dev/zero": "a device", "directory": "a directory"}[special]
    assert r.returncode == 1 and r.stderr.strip() == f"{path}: not a regular file ({what})", r.stderr[-2000:]


def test_oversized_prediction_png_is_not_read(pred: Path, dataset: Path) -> None:
    """A PNG larger than any PNG of the scene's size can be (a sparse 1 GiB file) is refused unread."""
    path = _view(pred, dataset, "rgb")
    with open(path, "r+b") as fh:
        fh.truncate(1 << 30)
    error, peak = _peak(_load(pred, dataset))
    assert isinstance(error, PredictionError) and str(error).startswith(f"{path}: {1 << 30} bytes, more than"), error
    assert peak < SMALL, peak


# --------------------------------------------------------------------------------------------
# PNGs: the IHDR is checked before inflating, and inflating stops at the size it declares
# --------------------------------------------------------------------------------------------


def _png(width: int, height: int, raw: bytes, bits: int = 16) -> bytes:
    """An RGB PNG whose IHDR says ``width x height`` and whose IDAT inflates to ``raw``."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bits, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def test_png_inflating_past_its_ihdr_is_stopped() -> None:
    """A 64 KiB PNG whose IHDR says 24x16 but whose IDAT inflates to 64 MiB stops inflating at
    the declared size (it was inflated whole, then its length compared)."""
    data = _png(24, 16, bytes(64 << 20))
    assert len(data) < 100_000
    error, peak = _peak(lambda: decode_rgb(data))
    assert isinstance(error, PngError) and "more image data than" in str(error), error
    assert peak < SMALL, peak


@pytest.mark.parametrize("bits", [8, 16])
def test_png_declaring_more_pixels_than_a_reader_allocates_is_refused(bits: int) -> None:
    """With no size expected, an IHDR over ``MAX_IMAGE_PIXELS`` is refused before inflating."""
    data = _png(10_000, 10_000, bytes(16 << 20), bits)
    error, peak = _peak(lambda: decode_rgb(data))
    assert isinstance(error, PngError) and "declares 10000x10000 pixels" in str(error), error
    assert peak < SMALL, peak


def test_prediction_png_of_another_size_is_refused_before_inflating(pred: Path, dataset: Path) -> None:
    """The IHDR's size is compared with the scene's before the 16 MiB of image data are inflated."""
    path = _view(pred, dataset, "rgb")
    path.write_bytes(_png(4000, 4000, bytes(16 << 20)))
    error, peak = _peak(_load(pred, dataset))
    assert isinstance(error, PredictionError) and str(error) == f"{path}: size 4000x4000, expected 24x16 (scene.json)", error
    assert peak < SMALL, peak


# --------------------------------------------------------------------------------------------
# EXRs: the header's data window is checked before decoding
# --------------------------------------------------------------------------------------------


@functools.lru_cache
def _zip_block(raw_bytes: int) -> bytes:
    """An EXR ZIP block of ``raw_bytes`` zero bytes (after EXR's predictor: 0, then 128s)."""
    return zlib.compress(b"\0" + b"\x80" * (raw_bytes - 1), 9)


def _exr(path: Path, width: int, height: int) -> None:
    """A valid single-channel float ``Z`` EXR of zeros, ZIP-compressed 16 lines a block, written by
    hand: 12000 x 12000 takes under 600 KB."""
    def attr(name: bytes, kind: bytes, value: bytes) -> bytes:
        return name + b"\0" + kind + b"\0" + struct.pack("<i", len(value)) + value

    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    header = b"".join([
        b"\x76\x2f\x31\x01", struct.pack("<i", 2),
        attr(b"channels", b"chlist", b"Z\0" + struct.pack("<i", 2) + bytes(4) + struct.pack("<ii", 1, 1) + b"\0"),
        attr(b"compression", b"compression", b"\x03"), attr(b"dataWindow", b"box2i", box),
        attr(b"displayWindow", b"box2i", box), attr(b"lineOrder", b"lineOrder", b"\0"),
        attr(b"pixelAspectRatio", b"float", struct.pack("<f", 1.0)),
        attr(b"screenWindowCenter", b"v2f", struct.pack("<ff", 0.0, 0.0)),
        attr(b"screenWindowWidth", b"float", struct.pack("<f", 1.0)), b"\0",
    ])
    blocks = [struct.pack("<ii", y, len(b)) + b
              for y in range(0, height, 16) for b in [_zip_block(min(16, height - y) * width * 4)]]
    offsets = np.cumsum([len(header) + 8 * len(blocks)] + [len(b) for b in blocks[:-1]])
    path.write_bytes(header + offsets.astype("<u8").tobytes() + b"".join(blocks))


def test_hand_written_exr_is_a_real_exr(tmp_path: Path) -> None:
    """The bombs below are valid files: the same writer at a small size reads back as zeros."""
    _exr(tmp_path / "z.exr", 40, 30)
    depth = D.read_depth(tmp_path / "z.exr")
    assert depth.shape == (30, 40) and not depth.any()


def test_exr_declaring_12000_squared_pixels_is_refused_from_its_header(tmp_path: Path) -> None:
    """A 600 KB EXR of 12000 x 12000 zeros was decoded whole (576 MB) by ``read_depth``."""
    path = tmp_path / "bomb.exr"
    _exr(path, 12_000, 12_000)
    assert path.stat().st_size < 700_000
    error, peak = _peak(lambda: D.read_depth(path))
    assert isinstance(error, D.DatasetError) and str(error).startswith(f"{path}: declares 12000x12000 pixels"), error
    assert peak < SMALL, peak


def test_prediction_exr_of_another_size_is_refused_before_decoding(pred: Path, dataset: Path) -> None:
    """A 4000 x 4000 depth EXR (64 MB decoded) for a 24 x 16 scene is refused from its header."""
    path = _view(pred, dataset, "depth")
    _exr(path, 4000, 4000)
    error, peak = _peak(_load(pred, dataset))
    assert isinstance(error, PredictionError) and str(error) == f"{path}: size 4000x4000, expected 24x16 (scene.json)", error
    assert peak < SMALL, peak


# --------------------------------------------------------------------------------------------
# Export arrays: .npy headers are checked against the manifest's sizes before loading
# --------------------------------------------------------------------------------------------


def _npz(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name + ".npy", data)
    return buf.getvalue()


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _write_export(root: Path, arrays: dict[str, bytes]) -> None:
    """A minimal valid export (one anchor object over two frames, two sampled configurations)
    whose ``arrays.npz`` holds ``arrays`` (``.npy`` bytes), every checksum right."""
    root.mkdir(exist_ok=True)
    (root / "objects").mkdir(exist_ok=True)
    (root / "objects" / "0.vdb").write_bytes(b"not read by read_export")
    (root / "arrays.npz").write_bytes(_npz(arrays))
    files = [{"path": rel, "bytes": (root / rel).stat().st_size,
              "sha256": hashlib.sha256((root / rel).read_bytes()).hexdigest()} for rel in ("arrays.npz", "objects/0.vdb")]
    obj = {"id": 0, "name": "room", "is_anchor": True, "bbox": [[-1, -1, -1], [1, 1, 1]], "grid_shape": [4, 4, 4],
           "scale_range": [0.5, 2.0], "valid_interval": [1.0, 1.0], "volume": "objects/0.vdb", "mesh": None}
    manifest = {"format": core.EXPORT_FORMAT, "version": core.EXPORT_VERSION, "timestamps": [0.0, 1.0],
                "camera": {"width": 8, "height": 6, "K": [[8, 0, 4], [0, 8, 3], [0, 0, 1]]}, "arrays": "arrays.npz",
                "objects": [obj], "scale_network": None, "samples": {"count": 2, "array": "samples_sbar"},
                "test_cameras": None, "files": files}
    (root / core.MANIFEST_NAME).write_text(json.dumps(manifest))


def _good_arrays() -> dict[str, bytes]:
    poses = np.tile(np.eye(4), (2, 1, 1))
    return {"camera_to_scene": _npy(poses), "obj0_frames": _npy(np.arange(2)), "obj0_object_to_scene": _npy(poses),
            "samples_sbar": _npy(np.ones((2, 1)))}


def test_minimal_export_reads(tmp_path: Path) -> None:
    _write_export(tmp_path / "e", _good_arrays())
    assert core.read_export(str(tmp_path / "e")).samples.shape == (2, 1)


def _huge_npy_header(shape: tuple[int, ...]) -> bytes:
    """A ``.npy`` header declaring float64 ``shape`` followed by only 64 bytes of data."""
    head = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    head["shape"] = shape
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, head)
    return buf.getvalue() + bytes(64)


@pytest.mark.parametrize("case", ["1 GiB header, truncated body", "a million samples where two are declared"])
def test_export_array_larger_than_the_manifest_allows_is_refused_before_loading(tmp_path: Path, case: str) -> None:
    """An ``arrays.npz`` member was loaded whole, whatever its size: a 1 GiB ``.npy`` header over
    a truncated body allocated the gigabyte before failing, and a million samples (a few KiB
    compressed) loaded though the manifest declares two."""
    arrays = _good_arrays()
    if case.startswith("1 GiB"):
        arrays["samples_sbar"] = _huge_npy_header((1 << 27, 1))
    else:
        arrays["samples_sbar"] = _npy(np.ones((1_000_000, 1)))
    _write_export(tmp_path / "e", arrays)
    error, peak = _peak(lambda: core.read_export(str(tmp_path / "e")))
    path = tmp_path / "e" / "arrays.npz"
    assert isinstance(error, core.ExportFormatError) and str(error).startswith(f"{path}: arrays declare"), error
    assert "\n" not in str(error) and peak < SMALL, peak

"""The prediction format of ``benchgen score`` (docs/predictions.md): its one owner.

A prediction directory ``PRED`` holds one sub-directory per candidate solution; each mirrors a
configuration directory of the dataset::

    PRED/
      method.json                 optional: {"name": ..., "notes": ...}, copied into the report
      CAND/rgb/NAME.png           every evaluated test frame NAME: 8- or 16-bit RGB or RGBA
      CAND/depth/NAME.exr         optional: planar depth (for SSIMAE), every candidate or none
      CAND/ids/NAME.png           optional: instance ids (for PQ / mIoU), every candidate or none
      CAND/train/rgb/NAME.png     optional: its render of every training frame NAME (fidelity,
                                  benchgen.score.fidelity), every candidate or none

so a dataset's ``configs/GGG`` is itself a valid candidate. Candidates are taken in sorted name
order; directories starting with ``.`` are skipped. The same checks apply to candidates given as
in-memory arrays (:class:`MemorySource`, for renderers such as ``osn evaluate``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol, Sequence

import numpy as np

from scenecore import dataset as D
from benchgen.score.pngread import PngError, decode_ids, decode_rgb, ids_png_size, max_png_bytes, png_size

METHOD_FILE = "method.json"
SUFFIX = {"rgb": ".png", "depth": ".exr", "ids": ".png"}
#: A candidate's renders of the training video: ``CAND/train/rgb/NAME.png`` per training frame.
TRAIN = "train"
#: Most bytes of ``method.json`` (a name and notes copied into the report).
MAX_METHOD_BYTES = 1 << 20


class PredictionError(ValueError):
    """A prediction is missing or malformed; the message names the file and the problem."""


@dataclass
class Candidate:
    """One candidate solution on the evaluated views (in the order of the ground truth's frames).

    ``rgb`` ``(V, H, W, 3)``: uint8, uint16 (full 16-bit range) or float in [0, 1];
    ``depth`` ``(V, H, W)`` float planar depth (``+inf`` = nothing hit) or None;
    ``ids`` ``(V, H, W)`` uint8 instance ids (255 = no object) or None.
    """

    rgb: np.ndarray
    depth: np.ndarray | None = None
    ids: np.ndarray | None = None


class CandidateSource(Protocol):
    """N candidates, loaded one at a time by index (so that memory does not grow with N)."""

    names: list[str]
    has_depth: bool
    has_ids: bool

    def load(self, index: int) -> Candidate:
        """Candidate ``index``, checked (raises :class:`PredictionError` naming what is wrong)."""
        ...

    # Optional (``getattr(source, "has_train", False)``): ``has_train`` and ``load_train(index)``,
    # the candidate's renders of the training frames ``(T, H, W, 3)`` in time order, checked.
    # Optional: ``load_rgb(index)``, the colour ``(V, H, W, 3)`` alone for the candidate pass
    # (:meth:`PredictionDir.load_rgb`); without it the pass takes ``load(index).rgb``.


# --------------------------------------------------------------------------------------------
# Checks shared by files and arrays
# --------------------------------------------------------------------------------------------


def rgb_problem(where: str | Path, rgb: np.ndarray, scene: D.Scene) -> str | None:
    """One line naming ``where`` when one view's colour ``(H, W, 3)`` is malformed (else None)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        return f"{where}: expected an (H, W, 3) RGB image, got shape {rgb.shape}"
    if p := D.size_problem(Path(where), rgb.shape[:2], scene):
        return p
    if rgb.dtype in (np.uint8, np.uint16):
        return None
    if not np.issubdtype(rgb.dtype, np.floating):
        return f"{where}: colour must be uint8, uint16 or float, got {rgb.dtype}"
    bad = int((~np.isfinite(rgb)).sum())
    return f"{where}: {bad} non-finite colour values" if bad else None


def depth_problem(where: str | Path, depth: np.ndarray, scene: D.Scene) -> str | None:
    """One line naming ``where`` when one view's planar depth ``(H, W)`` is malformed: not float,
    wrong size, NaN or -inf (``+inf`` marks pixels where nothing is hit, as in the dataset)."""
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        return f"{where}: expected an (H, W) float depth map, got {depth.shape} {depth.dtype}"
    if p := D.size_problem(Path(where), depth.shape, scene):
        return p
    nan, neg = int(np.isnan(depth).sum()), int(np.isneginf(depth).sum())
    if nan or neg:
        return f"{where}: {nan} NaN and {neg} -inf depths (+inf marks pixels where nothing is hit)"
    return None


def ids_problem(where: str | Path, ids: np.ndarray, scene: D.Scene) -> str | None:
    """One line naming ``where`` when one view's instance ids ``(H, W)`` uint8 are malformed:
    wrong dtype or size, or ids naming no object of the scene."""
    if ids.ndim != 2 or ids.dtype != np.uint8:
        return f"{where}: instance ids must be an (H, W) uint8 map, got {ids.shape} {ids.dtype}"
    return D.size_problem(Path(where), ids.shape, scene) or D.ids_problem(Path(where), ids, scene.num_objects)


PROBLEMS: dict[str, Callable[[str | Path, np.ndarray, D.Scene], str | None]] = {
    "rgb": rgb_problem, "depth": depth_problem, "ids": ids_problem}


def check_candidate(c: Candidate, name: str, scene: D.Scene, num_views: int, has_depth: bool, has_ids: bool) -> None:
    """Raise :class:`PredictionError` ``"NAME KIND view v: problem"`` for a malformed in-memory candidate."""
    kinds = ["rgb"] + ["depth"] * has_depth + ["ids"] * has_ids
    for kind in kinds:
        arr = getattr(c, kind)
        if arr is None or len(arr) != num_views:
            raise PredictionError(f"{name}: {kind} holds {0 if arr is None else len(arr)} views, expected {num_views}")
        for v in range(num_views):
            if p := PROBLEMS[kind](f"{name} {kind} view {v}", np.asarray(arr[v]), scene):
                raise PredictionError(p)


# --------------------------------------------------------------------------------------------
# Prediction directories
# --------------------------------------------------------------------------------------------


def read_method(pred: Path) -> dict:
    """``PRED/method.json`` (an object; ``{}`` when absent), a regular file of at most
    :data:`MAX_METHOD_BYTES`."""
    path = pred / METHOD_FILE
    if not path.exists():
        return {}
    try:
        d = json.loads(D.read_regular(path, MAX_METHOD_BYTES))
    except D.DatasetError as e:  # its message names the file
        raise PredictionError(str(e)) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PredictionError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(d, dict):
        raise PredictionError(f"{path}: expected a JSON object such as {{\"name\": ..., \"notes\": ...}}")
    return d


def _files(folder: Path) -> set[str] | None:
    """Names in ``folder`` (None when it is not a directory)."""
    return set(os.listdir(folder)) if folder.is_dir() else None


#: What a render written by another tool is, by its file name's ending (lower case), and the
#: ``benchgen import-renders`` call that turns it into this format.
IMPORTABLE = {
    "rgb": {".jpg": "JPEG, expected PNG", ".jpeg": "JPEG, expected PNG"},
    "depth": {".npy.gz": "NumPy depth, expected a planar-depth EXR", ".npy": "NumPy depth, expected a planar-depth EXR"},
}
IMPORT_HINT = {"rgb": "use benchgen import-renders", "depth": "use benchgen import-renders --depth DIR --depth-kind ray|planar"}
JPEG_MAGIC = b"\xff\xd8\xff"


def _missing_view(folder: Path, kind: str, name: str, present: set[str]) -> str:
    """Why ``folder/NAME`` is missing: a file another tool wrote where a PNG or EXR is expected, or none."""
    lower = {p.lower(): p for p in present}
    for ending, what in IMPORTABLE.get(kind, {}).items():
        if (name + ending).lower() in lower:
            return f"{folder / lower[(name + ending).lower()]}: {what} ({IMPORT_HINT[kind]})"
    return f"{folder / (name + SUFFIX[kind])}: missing view"


def _check_kind(cand: Path, kind: str, frames: Sequence[str], required: bool) -> bool:
    """Whether candidate ``cand`` has ``kind``; raises naming the first missing view."""
    present = _files(cand / kind)
    if present is None:
        if required:
            hint = "; renders of ns-render or D-NeRF: use benchgen import-renders" if (cand / "test").is_dir() else ""
            raise PredictionError(f"{cand / kind}: missing directory (needs {kind}/NAME{SUFFIX[kind]} for every test view{hint})")
        return False
    for name in frames:
        if name + SUFFIX[kind] not in present:
            raise PredictionError(_missing_view(cand / kind, kind, name, present))
    return True


class PredictionDir:
    """The candidates of a prediction directory, checked for structure when opened.

    Opening lists every candidate's files (cheap): each must have ``rgb/NAME.png`` for every
    evaluated frame, and depth / ids must be given by every candidate or by none. File contents
    are checked by :meth:`load`, which raises :class:`PredictionError` naming the file.
    """

    def __init__(self, root: str | Path, scene: D.Scene, frames: Sequence[str]) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise PredictionError(f"{self.root}: not a directory (expected one sub-directory per candidate)")
        if (self.root / "rgb").is_dir():
            raise PredictionError(f"{self.root}: holds rgb/ itself; put each candidate in a sub-directory (PRED/CAND/rgb/NAME.png)")
        self.scene, self.frames = scene, list(frames)
        self.method = read_method(self.root)
        self.names = sorted(e.name for e in os.scandir(self.root) if e.is_dir() and not e.name.startswith("."))
        if not self.names:
            raise PredictionError(f"{self.root}: no candidate directories (expected CAND/rgb/NAME.png per test view)")
        first = self.root / self.names[0]
        self.has_depth = (first / "depth").is_dir()
        self.has_ids = (first / "ids").is_dir()
        # The training frames in time order (scenecore.dataset.read_training_video's order).
        self.train_frames = [f.name for f in sorted(scene.train_frames, key=lambda f: f.time_index)]
        self.has_train = (first / TRAIN).is_dir()
        for name in self.names:
            self._check_layout(self.root / name, first)

    def _check_layout(self, cand: Path, first: Path) -> None:
        _check_kind(cand, "rgb", self.frames, required=True)
        for kind, expected in (("depth", self.has_depth), ("ids", self.has_ids)):
            if _check_kind(cand, kind, self.frames, required=False) != expected:
                has, lacks = (cand, first) if not expected else (first, cand)
                raise PredictionError(f"{lacks / kind}: missing, but {has / kind} exists "
                                      f"({kind} must be given for every candidate or for none)")
        if (cand / TRAIN).is_dir() != self.has_train:
            has, lacks = (cand, first) if not self.has_train else (first, cand)
            raise PredictionError(f"{lacks / TRAIN}: missing, but {has / TRAIN} exists (renders of the training video "
                                  "must be given for every candidate or for none)")
        if self.has_train:
            if not (cand / TRAIN / "rgb").is_dir():
                raise PredictionError(f"{cand / TRAIN / 'rgb'}: missing directory (needs rgb/NAME.png for every training frame)")
            _check_kind(cand / TRAIN, "rgb", self.train_frames, required=True)

    def __len__(self) -> int:
        return len(self.names)

    def path(self, index: int, kind: str, frame: str) -> str:
        """Candidate ``index``'s file of ``kind`` for ``frame`` (a plain string: the pass builds
        one per file, and a ``Path`` costs more than reading a small one)."""
        return os.path.join(self.root, self.names[index], kind, frame + SUFFIX[kind])

    def load(self, index: int) -> Candidate:
        """Read and check candidate ``index`` whole (colour, depth, ids decoded and their values
        checked); :class:`PredictionError` names the bad file."""
        rgb = np.stack([self._read(self.path(index, "rgb", f), "rgb") for f in self.frames])
        depth = np.stack([self._read(self.path(index, "depth", f), "depth") for f in self.frames]) if self.has_depth else None
        ids = np.stack([self._read(self.path(index, "ids", f), "ids") for f in self.frames]) if self.has_ids else None
        return Candidate(rgb, depth, ids)

    def load_rgb(self, index: int) -> np.ndarray:
        """Candidate ``index``'s colour ``(V, H, W, 3)``, read and checked, for the candidate pass,
        which needs nothing else. Its depth and ids files are checked up to their headers (a regular
        file of a size such a file can have, whose header declares the scene's image size; an id PNG
        single-channel 8-bit) without being decoded: decoding and checking their values is
        :meth:`load`'s, for the candidates whose full metrics are computed (docs/predictions.md)."""
        rgb = np.stack([self._read(self.path(index, "rgb", f), "rgb") for f in self.frames])
        for kind in ("depth",) * self.has_depth + ("ids",) * self.has_ids:
            for f in self.frames:
                self._read(self.path(index, kind, f), kind, decode=False)
        return rgb

    def load_train(self, index: int) -> np.ndarray:
        """Candidate ``index``'s renders of the training frames ``(T, H, W, 3)``, in time order, checked."""
        folder = self.root / self.names[index] / TRAIN / "rgb"
        return np.stack([self._read(folder / (f + SUFFIX["rgb"]), "rgb") for f in self.train_frames])

    def _read(self, path: str | Path, kind: str, decode: bool = True) -> np.ndarray | None:
        """One view's file, checked. Only a regular file of a size such an image can have is read,
        and its header's size must match the scene's before anything is decoded: a FIFO, a link
        to ``/dev/zero`` or a small file that inflates to gigabytes is one line naming it.
        ``decode=False``: those header checks alone (None)."""
        try:
            if kind == "depth":
                size = D.exr_size(path)
            else:
                data = D.read_regular(path, max_png_bytes(self.scene.height, self.scene.width))
                size = (png_size if kind == "rgb" else ids_png_size)(data)
            if p := D.size_problem(path, size, self.scene):
                raise PredictionError(p)
            if not decode:
                return None
            a = D.read_depth(path) if kind == "depth" else (decode_rgb if kind == "rgb" else decode_ids)(data)
        except PngError as e:
            if data.startswith(JPEG_MAGIC):
                hint = f" ({IMPORT_HINT[kind]})" if kind in IMPORT_HINT else ""
                raise PredictionError(f"{path}: JPEG, expected PNG{hint}") from None
            raise PredictionError(f"{path}: {e}") from None
        except D.DatasetError as e:  # its message already names the file
            raise PredictionError(str(e)) from None
        except OSError as e:
            raise PredictionError(f"{path}: cannot read ({e.strerror or e})") from None
        if p := PROBLEMS[kind](path, a, self.scene):
            raise PredictionError(p)
        return a


class MemorySource:
    """Candidates produced in memory (e.g. rendered by a method), checked like files.

    ``loader(n)`` returns candidate n as a :class:`Candidate` on the evaluated views; it may be
    called twice for a candidate that matches a ground truth (the pass, then the full metrics).
    Only a ``fork_safe`` loader (numpy only: no torch, no GPU) may run in worker processes;
    otherwise score with one worker, so that the loader runs in the calling process.
    ``train_loader(n)``: candidate n's renders of the training frames ``(T, H, W, 3)`` in time
    order (fidelity; optional).
    """

    def __init__(self, names: Sequence[str], loader: Callable[[int], Candidate], scene: D.Scene,
                 num_views: int, has_depth: bool = False, has_ids: bool = False, fork_safe: bool = False,
                 train_loader: Callable[[int], np.ndarray] | None = None) -> None:
        if not names:
            raise PredictionError("no candidates to score")
        self.names, self.loader, self.scene, self.num_views = list(names), loader, scene, num_views
        self.has_depth, self.has_ids, self.fork_safe = has_depth, has_ids, fork_safe
        self.train_loader, self.has_train = train_loader, train_loader is not None

    def __len__(self) -> int:
        return len(self.names)

    def load(self, index: int) -> Candidate:
        c = self.loader(index)
        check_candidate(c, self.names[index], self.scene, self.num_views, self.has_depth, self.has_ids)
        return c

    def load_train(self, index: int) -> np.ndarray:
        if self.train_loader is None:
            raise PredictionError(f"{self.names[index]}: no renders of the training video")
        rgb = np.asarray(self.train_loader(index))
        T = len(self.scene.train_frames)
        if len(rgb) != T:
            raise PredictionError(f"{self.names[index]}: train holds {len(rgb)} views, expected {T}")
        for t in range(T):
            if p := rgb_problem(f"{self.names[index]} train view {t}", rgb[t], self.scene):
                raise PredictionError(p)
        return rgb

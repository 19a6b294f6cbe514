"""``benchgen import-renders``: a folder of renders from nerfstudio's ``ns-render`` or D-NeRF as one
candidate of the prediction format (:mod:`benchgen.score.predictions`, docs/predictions.md).

What it takes (docs/predictions.md, "From nerfstudio or D-NeRF"):

* **Where.** ``DIR`` is a folder of images, ``ns-render dataset``'s ``--output-path`` (its
  ``test/`` split, in which the colour folder is ``rgb_fine`` (``dnerf``, ``vanilla-nerf``) or
  ``rgb`` (other models), the depth folder ``raw-depth_fine`` or ``raw-depth``), or D-NeRF's
  ``renderonly_test_*`` folder (its ``estim/``, not its ``gt/``).
* **Names.** One file per test view, named by the test frame (``v01_t00.jpg``: ns-render keeps
  the dataset's file names) or by its index in ``transforms_test.json``'s order (``00000.png``:
  older ns-render; ``000.png``: D-NeRF's ``--render_test``).
* **Colour.** PNG (8- or 16-bit, RGB or RGBA) or JPEG (ns-render's default), of the dataset's
  size. PNGs without transparent pixels (and 16-bit ones) are copied byte for byte; JPEGs
  (lossy: scores are a bound) and 8-bit PNGs with transparent pixels, composited over white as
  nerfstudio's ``dnerf`` and D-NeRF's ``white_bkgd`` composite, are written as 8-bit RGB PNGs.
* **Depth** (optional). ns-render's raw depth (``.npy.gz``, ``(H, W, 1)`` float32), ``.npy`` or a
  one-channel EXR. ``ray``: distance along the pixel's ray (nerfstudio's NeRF depth), converted
  to planar depth with the dataset's cameras (:func:`scenecore.cameras.planar_from_ray_depth`);
  ``planar``: camera-axis depth, copied.

Every file is matched and checked before the candidate is complete; it is written into a
temporary sibling swapped in whole (:func:`scenecore.atomic.own_dir`), so a failure leaves the
output as it was. An existing output is replaced only if a previous import wrote it.
"""

from __future__ import annotations

import contextlib
import io
import os
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.atomic import atomic_write_bytes, atomic_write_json, own_dir
from scenecore.cameras import planar_from_ray_depth
from benchgen.score.pngread import PNG_SIGNATURE, PngError, decode_rgb, max_png_bytes, png_size
from benchgen.score.predictions import JPEG_MAGIC, SUFFIX, PredictionError, depth_problem, rgb_problem

#: Marks an output directory written by an import, which the next import may replace.
MARKER = ".benchgen-import"
#: Provenance of an import, written into the candidate.
PROVENANCE = "import.json"
_WHAT = "an import of renders (benchgen import-renders)"
RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".npy.gz", ".npy", ".exr")  # longest first: "a.npy.gz" is "a", not "a.npy"
#: Render folders, preferred in this order: ns-render's of NeRF's fine network, then of any
#: model, then D-NeRF's (``render_path`` writes ``estim/`` beside the ground truth's ``gt/``).
RGB_FOLDERS = ("rgb_fine", "rgb", "estim")
DEPTH_FOLDERS = ("raw-depth_fine", "raw-depth")
DEPTH_KINDS = ("ray", "planar")
#: Background that transparent pixels are composited over (nerfstudio's dnerf, D-NeRF's white_bkgd).
BACKGROUND = 255
#: Names shown in a message listing missing or extra files.
_PREVIEW = 4


@dataclass
class ImportSummary:
    """What an import read and wrote (also written to ``import.json`` in the candidate)."""

    out: Path
    views: int
    rgb_folder: Path
    naming: str
    rgb_formats: dict[str, int]
    composited_views: int = 0
    depth_folder: Path | None = None
    depth_naming: str | None = None
    depth_kind: str | None = None
    depth_formats: dict[str, int] = field(default_factory=dict)

    def to_json(self, dataset: Path) -> dict:
        return {
            "written_by": "benchgen import-renders", "dataset": str(dataset.resolve()), "views": self.views,
            "rgb": {"source": str(self.rgb_folder.resolve()), "naming": self.naming, "formats": self.rgb_formats,
                    "composited_over_white": self.composited_views},
            "depth": None if self.depth_folder is None else {
                "source": str(self.depth_folder.resolve()), "naming": self.depth_naming, "kind": self.depth_kind,
                "formats": self.depth_formats},
        }

    def lines(self) -> list[str]:
        fmt = ", ".join(f"{n} {k}" for k, n in sorted(self.rgb_formats.items()))
        out = [f"imported {self.views} test views into {self.out}",
               f"  colour: {self.rgb_folder} ({fmt}; named by {self.naming})"]
        if self.composited_views:
            out.append(f"  {self.composited_views} views had transparent pixels: composited over white")
        if self.depth_folder is not None:
            how = "distance along the ray, converted to planar depth" if self.depth_kind == "ray" else "planar depth, copied"
            out.append(f"  depth: {self.depth_folder} ({', '.join(sorted(self.depth_formats))}; {how})")
        if self.rgb_formats.get("JPEG"):
            out.append("  note: JPEG is lossy, so the scores are lower than the renders deserve; for exact scores "
                       "render PNG (ns-render dataset ... --image-format png)")
        return out


# --------------------------------------------------------------------------------------------
# Finding the renders
# --------------------------------------------------------------------------------------------


def _suffix(name: str, suffixes: Sequence[str]) -> str | None:
    low = name.lower()
    return next((s for s in suffixes if low.endswith(s) and len(name) > len(s)), None)


def _files(folder: Path) -> list[str]:
    """Names of the files in ``folder`` (hidden ones left out)."""
    return sorted(e.name for e in os.scandir(folder) if not e.name.startswith(".") and e.is_file())


def _holds(folder: Path, suffixes: Sequence[str]) -> bool:
    return any(_suffix(n, suffixes) for n in _files(folder))


def _subfolders(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


def _split_folder(root: Path) -> Path:
    """``root/test`` for ns-render's ``--output-path`` (which holds one folder per split), else ``root``."""
    if (root / "test").is_dir():
        return root / "test"
    others = [s for s in ("train", "val") if (root / s).is_dir()]
    if others and not _holds(root, RGB_SUFFIXES + DEPTH_SUFFIXES):
        raise PredictionError(f"{root}: holds ns-render's {' and '.join(others)} split, not test; "
                              "render the test views (ns-render dataset --split test)")
    return root


@dataclass(frozen=True)
class _Kind:
    """What a folder of renders of one kind holds, and how ns-render names its folders."""

    what: str
    suffixes: tuple[str, ...]
    preferred: tuple[str, ...]
    flag: str

    def usable(self, folder: Path) -> bool:
        """Whether an output folder other than the preferred ones may hold this kind: never the
        ground truth (ns-render's ``gt-*``, D-NeRF's ``gt``); colour never from raw, depth or
        accumulation outputs."""
        name = folder.name
        if self is RGB:
            return (name != "gt" and not name.startswith(("gt-", "raw-")) and "depth" not in name
                    and "accumulation" not in name)
        return "depth" in name and not name.startswith(("gt-", "raw-gt-"))


RGB = _Kind("renders", RGB_SUFFIXES, RGB_FOLDERS, "DIR")
DEPTH = _Kind("depth maps", DEPTH_SUFFIXES, DEPTH_FOLDERS, "--depth DIR")


def _find_folder(root: str | Path, kind: _Kind) -> Path:
    """The folder of ``kind`` in ``root``: ``root`` itself, its ``test/`` split, or the preferred
    (else the only usable) folder of ns-render's outputs in it."""
    root = Path(root)
    if not root.is_dir():
        raise PredictionError(f"{root}: not a directory (expected a folder of {kind.what}, or ns-render's --output-path)")
    if _holds(root, kind.suffixes):
        return root
    base = _split_folder(root)
    if base != root and _holds(base, kind.suffixes):
        return base
    folders = [p for p in _subfolders(base) if _holds(p, kind.suffixes)]
    preferred = [base / name for name in kind.preferred if base / name in folders]
    usable = preferred[:1] or [p for p in folders if kind.usable(p)]
    if len(usable) > 1:
        raise PredictionError(f"{base}: several folders of {kind.what} ({', '.join(p.name for p in usable)}); "
                              f"give the one to import as {kind.flag}")
    if usable:
        return usable[0]
    if kind is DEPTH and (mapped := [p for p in (root, *_subfolders(base)) if "depth" in p.name and _holds(p, RGB_SUFFIXES)]):
        raise PredictionError(f"{mapped[0]}: colour-mapped depth images, which hold no depth values; render raw depth "
                              f"(ns-render dataset ... --rendered-output-names {DEPTH_FOLDERS[0]})")
    files = " or ".join(f"NAME{s}" for s in kind.suffixes)
    raise PredictionError(f"{root}: no {kind.what} (expected {files} per test view, or ns-render's "
                          f"{' or '.join(f'test/{n}/' for n in kind.preferred)})")


def find_rgb_folder(root: str | Path) -> Path:
    """The folder of colour renders in ``root`` (see the module docstring)."""
    return _find_folder(root, RGB)


def find_depth_folder(root: str | Path) -> Path:
    """The folder of depth maps in ``root``: ``.npy.gz`` / ``.npy`` / ``.exr`` files, or ns-render's
    ``test/raw-depth_fine`` (``raw-depth``); colour-mapped depth images are refused (they hold no depth)."""
    return _find_folder(root, DEPTH)


def transforms_test_order(dataset: str | Path, scene: D.Scene) -> list[str]:
    """Test frame names in the order of ``transforms_test.json`` (what ns-render and D-NeRF render
    in; the order that writer uses when the dataset has no such file)."""
    path = Path(dataset) / "transforms_test.json"
    test = {f.name for f in scene.test_frames}
    if not path.exists():
        return [f.name for f in D.transforms_splits(scene)["test"][0]]
    try:
        names = [Path(fr["file_path"]).name for fr in D.read_json(path)["frames"]]
    except (TypeError, KeyError) as e:
        raise D.DatasetError(f"{path}: malformed ({type(e).__name__}: {e})") from None
    if sorted(names) != sorted(test):
        raise D.DatasetError(f"{path}: its frames are not the test views of scene.json")
    return names


def _preview(items: Sequence[str]) -> str:
    shown = ", ".join(items[:_PREVIEW])
    return shown + (f", ... ({len(items)} in all)" if len(items) > _PREVIEW else "")


def match_files(folder: Path, suffixes: Sequence[str], order: Sequence[str]) -> tuple[dict[str, Path], str]:
    """``{test frame name: file}`` for the renders in ``folder`` and how they are named (``"test
    frame"`` or ``"index"``); one line naming what is missing or extra when they are not exactly
    one file per test view."""
    by_stem: dict[str, list[str]] = {}
    unknown = []
    for name in _files(folder):
        s = _suffix(name, suffixes)
        if s is None:
            unknown.append(name)
        else:
            by_stem.setdefault(name[: -len(s)], []).append(name)
    if twice := next((v for v in by_stem.values() if len(v) > 1), None):
        raise PredictionError(f"{folder}: one view given twice ({', '.join(twice)})")
    names = set(order)
    by_index = bool(by_stem) and not names & set(by_stem) and all(s.isdigit() for s in by_stem)
    if by_index:
        index = {int(s): v[0] for s, v in by_stem.items()}
        files = {order[i]: folder / f for i, f in index.items() if i < len(order)}
        missing = [f"index {i} ({order[i]})" for i in range(len(order)) if i not in index]
        extra = [index[i] for i in sorted(index) if i >= len(order)] + unknown
    else:
        files = {s: folder / v[0] for s, v in by_stem.items() if s in names}
        missing = [n for n in order if n not in by_stem]
        extra = [v[0] for s, v in sorted(by_stem.items()) if s not in names] + unknown
    if missing or extra:
        parts = [f"{len(missing)} of {len(order)} test views missing ({_preview(missing)})"] * bool(missing)
        parts += [f"{len(extra)} extra file(s) ({_preview(extra)})"] * bool(extra)
        hint = (f"name one file per test view by its frame ({order[0]}{suffixes[0]}) or by its index in "
                f"transforms_test.json's order (00000{suffixes[0]})")
        if by_index and missing:
            hint += "; D-NeRF renders every testskip-th view only: render with --testskip 1"
        raise PredictionError(f"{folder}: {'; '.join(parts)}; {hint}")
    return files, "index in transforms_test.json" if by_index else "test frame"


# --------------------------------------------------------------------------------------------
# Reading one view
# --------------------------------------------------------------------------------------------


def _read_bytes(path: Path, max_bytes: int) -> bytes:
    try:
        return D.read_regular(path, max_bytes)
    except D.DatasetError as e:
        raise PredictionError(str(e)) from None


def _size(path: Path, shape: tuple[int, ...], scene: D.Scene) -> None:
    if p := D.size_problem(path, shape, scene):
        raise PredictionError(f"{p}; render at the dataset's resolution (no --downscale-factor)")


def _composite(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """8-bit ``rgb`` over the white background with 8-bit ``alpha``, rounded to the nearest value."""
    a = alpha.astype(np.int32)[..., None]
    return ((rgb.astype(np.int32) * a + BACKGROUND * (255 - a) + 127) // 255).astype(np.uint8)


def convert_rgb(path: str | Path, scene: D.Scene) -> tuple[bytes, str, bool]:
    """One render as the PNG bytes of the prediction format: ``(png, "PNG" | "JPEG", composited)``.

    An 8-bit PNG without transparent pixels, and any 16-bit PNG (its precision kept, its alpha
    ignored as the scorer ignores it), is returned as it is; a JPEG, or an 8-bit PNG with
    transparent pixels composited over white, is re-encoded as 8-bit RGB.
    Raises :class:`PredictionError` naming ``path`` for anything the scorer would refuse.
    """
    from PIL import Image

    path = Path(path)
    data = _read_bytes(path, max_png_bytes(scene.height, scene.width))
    try:
        if data.startswith(PNG_SIGNATURE):
            _size(path, png_size(data), scene)
            rgb = decode_rgb(data)
            if (p := rgb_problem(path, rgb, scene)):
                raise PredictionError(p)
            if rgb.dtype != np.uint8:
                return data, "PNG", False
            with Image.open(io.BytesIO(data)) as im:
                if im.mode not in ("RGBA", "PA") and "transparency" not in im.info:
                    return data, "PNG", False
                alpha = np.asarray(im.convert("RGBA"))[..., 3]
            if alpha.min() == 255:
                return data, "PNG", False
            return D.encode_png(_composite(rgb, alpha)), "PNG", True
        if data.startswith(JPEG_MAGIC):
            with Image.open(io.BytesIO(data)) as im:
                _size(path, (im.height, im.width), scene)
                if im.mode in ("L", "LA", "I", "I;16", "F", "1"):
                    raise PredictionError(f"{path}: grey JPEG; expected colour renders")
                rgb = np.asarray(im.convert("RGB"))
            return D.encode_png(rgb), "JPEG", False
    except PngError as e:
        raise PredictionError(f"{path}: {e}") from None
    except PredictionError:
        raise
    except Exception as e:  # Pillow raises many types for corrupt data
        raise PredictionError(f"{path}: cannot decode the image ({e})") from None
    raise PredictionError(f"{path}: neither a PNG nor a JPEG file")


def _npy_bytes(scene: D.Scene) -> int:
    """Most bytes of a ``.npy`` depth map of the scene's size: float64 samples and a header."""
    return 8 * scene.height * scene.width + (1 << 16)


def _gunzip(path: Path, data: bytes, limit: int) -> bytes:
    """``data`` inflated, refused past ``limit`` bytes without inflating further."""
    stream = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        raw = stream.decompress(data, limit + 1)
    except zlib.error as e:
        raise PredictionError(f"{path}: not a gzip file ({e})") from None
    if len(raw) > limit:
        raise PredictionError(f"{path}: inflates to more than the {limit} bytes a depth map of the dataset's size takes")
    if not stream.eof:
        raise PredictionError(f"{path}: truncated gzip file")
    return raw


def read_depth_map(path: str | Path, scene: D.Scene) -> np.ndarray:
    """One depth map as ``(H, W)`` float64: ``.npy.gz`` (ns-render's ``raw-depth``), ``.npy``
    (``(H, W)`` or ``(H, W, 1)`` float) or an EXR (channel ``Z`` or the only one); checked."""
    path = Path(path)
    suffix = _suffix(path.name, DEPTH_SUFFIXES)
    if suffix == ".exr":
        try:
            _size(path, D.exr_size(path), scene)
            depth = D.read_depth(path)
        except D.DatasetError as e:
            raise PredictionError(str(e)) from None
    else:
        limit = _npy_bytes(scene)
        data = _read_bytes(path, limit + limit // 100 + (1 << 16) if suffix == ".npy.gz" else limit)
        if suffix == ".npy.gz":
            data = _gunzip(path, data, limit)
        try:
            depth = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise PredictionError(f"{path}: not a NumPy .npy array ({e})") from None
        if depth.ndim == 3 and depth.shape[2] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise PredictionError(f"{path}: expected an (H, W) or (H, W, 1) float depth map, got {depth.shape} {depth.dtype}")
        _size(path, depth.shape, scene)
    return np.asarray(depth, dtype=np.float64)


def convert_depth(path: str | Path, scene: D.Scene, kind: str) -> np.ndarray:
    """One depth map as the prediction format's planar depth ``(H, W)`` float32 (``ray``:
    converted with the dataset's intrinsics; ``planar``: as it is); checked like the scorer does."""
    depth = read_depth_map(path, scene)
    if kind == "ray":
        depth = planar_from_ray_depth(depth, scene.intrinsics.matrix())
    elif kind != "planar":
        raise PredictionError(f"unknown depth kind {kind!r} (expected one of {', '.join(DEPTH_KINDS)})")
    depth = depth.astype(np.float32)
    if p := depth_problem(path, depth, scene):
        raise PredictionError(p)
    return depth


# --------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------


def _inside(a: Path, b: Path) -> bool:
    """Whether ``a`` is ``b`` or lies inside it."""
    return a == b or b in a.parents


def import_renders(renders: str | Path, dataset: str | Path, out: str | Path, depth: str | Path | None = None,
                   depth_kind: str | None = None) -> ImportSummary:
    """Import the renders in ``renders`` (and depth maps in ``depth``) as candidate ``out`` of a
    prediction directory for ``dataset``; see the module docstring.

    Raises:
        PredictionError: the renders do not match the dataset's test views (one line naming the
            file or folder and what is wrong); nothing is written.
        FileExistsError: ``out`` exists, is not empty and was not written by an import.
    """
    dataset, out = Path(dataset), Path(out)
    if (depth is None) != (depth_kind is None):
        raise PredictionError("--depth DIR and --depth-kind ray|planar go together: nerfstudio's NeRF depth is "
                              "the distance along the ray (ray), the prediction format's depth is planar")
    if depth_kind is not None and depth_kind not in DEPTH_KINDS:
        raise PredictionError(f"--depth-kind must be one of {', '.join(DEPTH_KINDS)}, got {depth_kind!r}")
    scene = D.load_scene(dataset)
    order = transforms_test_order(dataset, scene)
    rgb_folder = find_rgb_folder(renders)
    rgb_files, naming = match_files(rgb_folder, RGB_SUFFIXES, order)
    depth_folder = depth_files = depth_naming = None
    if depth is not None:
        depth_folder = find_depth_folder(depth)
        depth_files, depth_naming = match_files(depth_folder, DEPTH_SUFFIXES, order)
    target = out.resolve()
    for src in filter(None, (rgb_folder, depth_folder)):
        if _inside(src.resolve(), target):
            raise PredictionError(f"{out}: holds the renders being imported ({src}); choose another --out")
    summary = ImportSummary(out, len(order), rgb_folder, naming, {}, depth_folder=depth_folder,
                            depth_naming=depth_naming, depth_kind=depth_kind)
    made = [p for p in (target, *target.parents) if not p.exists()]  # folders own_dir creates above out
    try:
        _write(summary, out, scene, order, rgb_files, depth_files, dataset)
    except BaseException:
        for p in made[1:]:  # what a failed import created: nothing is left behind
            with contextlib.suppress(OSError):
                p.rmdir()
        raise
    return summary


def _write(summary: ImportSummary, out: Path, scene: D.Scene, order: Sequence[str], rgb_files: dict[str, Path],
           depth_files: dict[str, Path] | None, dataset: Path) -> None:
    formats: Counter[str] = Counter()
    depth_formats: Counter[str] = Counter()
    with own_dir(out, MARKER, _WHAT) as tmp:
        for name in order:
            png, fmt, composited = convert_rgb(rgb_files[name], scene)
            formats[fmt] += 1
            summary.composited_views += composited
            atomic_write_bytes(tmp / "rgb" / (name + SUFFIX["rgb"]), png)
            if depth_files is not None:
                src = depth_files[name]
                depth_formats[_suffix(src.name, DEPTH_SUFFIXES) or "?"] += 1
                D.write_depth(tmp / "depth" / (name + SUFFIX["depth"]), convert_depth(src, scene, summary.depth_kind))
        summary.rgb_formats, summary.depth_formats = dict(formats), dict(depth_formats)
        atomic_write_json(tmp / PROVENANCE, summary.to_json(dataset))

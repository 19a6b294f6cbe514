"""The OSN export format, read side: numpy only.

This module is shared by the Blender add-on (which may use nothing but Blender's bundled numpy)
and by ``osn`` (``osn.export`` writes the format and reuses the evaluator and sampler from here),
so the format version, the network evaluation and the configuration maths have one owner. The
network and configuration maths are in :mod:`scenecore.scale_space`, re-exported here.

Export directory (format ``osn-export`` version 1, see docs/export-and-addon.md)::

    osn_export.json          manifest: conventions, cameras, objects, files with sizes and sha256
    arrays.npz               poses, cameras, sampled configurations
    scale_net.npz            W0, b0, W1, b1, ... (present when the scene has a scale network)
    objects/<id>.vdb         grids "density" (float) and "color" (vec3, linear RGB); with the
                             object's "field" entry also the field's own grids (below)
    objects/<id>_planes.npz  the field's colour planes (objects whose field has them)
    objects/<id>.ply         surface mesh (training views fused, or marching cubes: mesh_source),
                             binary little-endian, sRGB vertex colours

Conventions:
* Scene frame = the anchor's object frame, in the anchor's unit (the anchor has ``sbar = 1``).
* ``camera_to_scene (T, 4, 4)``: OpenCV camera-to-scene pose of the training camera per frame.
* ``object_to_scene`` of object k at its frames, at ``sbar_k = 1``. A configuration with actual
  scales ``sbar`` places k at ``scale_about(c_t, sbar_k) @ object_to_scene_k[t]`` where ``c_t``
  is the training camera centre: the training video is unchanged, novel views are not.
* An object's optional ``field`` entry names the learned field's parameters in its volume:
  ``density = softplus(density_raw + offset)`` inside the bbox (0 outside) and display colour
  ``sigmoid(color_raw + planes)``, each grid trilinear between its nodes. Rendered emission-
  absorption with display colours composited as they are (no linearisation), this is the field
  OSN renders; ``density`` and ``color`` are its values at the nodes only.
* Eq. 1: a normalised scale ``s`` in [0, 1) maps to ``sbar = lo * (1 - s) + hi * s`` with the
  object's ``scale_range = [lo, hi]``. The scale network takes the normalised scales of the
  non-anchor objects, in manifest order, and returns a validity probability.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .cameras import opengl_from_opencv, scale_about
from .errors import ExportFormatError
from .paths import join_inside
# The scale network and configuration maths live in scale_space; callers (the add-on, osn.export)
# reach them through this module, the one entry point of the export format.
from .scale_space import (
    ACTIVATIONS,
    configured_poses,
    denormalise,
    learned_intervals,
    normalise,
    sample_valid_configurations,
    scale_net_numpy,
    scale_scores,
)

EXPORT_FORMAT = "osn-export"
EXPORT_VERSION = 1
MANIFEST_NAME = "osn_export.json"
#: Grids of an object's ``field`` entry: pre-activation density, pre-sigmoid colour, colour planes.
DENSITY_RAW_GRID = "density_raw"
COLOR_RAW_GRID = "color_raw"
#: The axes each of an object's three colour planes spans (``planes[i]`` spans ``PLANE_AXES[i]``).
PLANE_AXES = ((0, 1), (0, 2), (1, 2))
#: Largest colour plane side a reader accepts.
MAX_PLANE_SIZE = 4096

__all__ = [
    "EXPORT_FORMAT", "EXPORT_VERSION", "MANIFEST_NAME", "ExportFormatError", "ExportObjectData", "ExportData",
    "scale_net_numpy", "denormalise", "normalise", "configured_poses", "blender_camera_matrices",
    "learned_intervals", "scale_scores", "sample_valid_configurations", "read_export", "read_ply", "sha256_file",
    "opengl_from_opencv", "scale_about", "ACTIVATIONS", "names_manifest", "FieldGrids",
    "DENSITY_RAW_GRID", "COLOR_RAW_GRID", "PLANE_AXES",
]


def blender_camera_matrices(camera_to_scene: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-scene poses ``(..., 4, 4)`` as Blender camera ``matrix_world``."""
    return opengl_from_opencv(camera_to_scene)


# --------------------------------------------------------------------------------------------
# Reading an export
# --------------------------------------------------------------------------------------------


@dataclass
class FieldGrids:
    """An object's ``field`` entry: the grids of the learned field inside its volume file.

    Attributes:
        density_grid: pre-activation density grid; ``density = softplus(value + density_offset)``.
        color_grid: pre-sigmoid colour grid; ``colour = sigmoid(value + sum of planes)``.
        planes: ``(3, P, P, 3)`` pre-sigmoid colour planes (``planes[i, v, u]``, bilinear at
            box-normalised ``-1 + 2 (u, v) / (P - 1)`` along :data:`PLANE_AXES` ``[i]``), or None.
    """

    density_grid: str
    density_offset: float
    color_grid: str
    planes: np.ndarray | None = None


@dataclass
class ExportObjectData:
    """One learned object as read from an export (see ``osn.export.ExportObject`` for meanings)."""

    id: int
    name: str
    is_anchor: bool
    bbox: np.ndarray
    grid_shape: tuple[int, int, int]
    scale_range: tuple[float, float]
    valid_interval: tuple[float, float]
    frames: np.ndarray
    object_to_scene: np.ndarray
    volume_path: str
    mesh_path: str | None
    mesh: dict[str, np.ndarray] | None = None
    field: FieldGrids | None = None


@dataclass
class ExportData:
    """A validated export: every array loaded, every file present and matching its checksum."""

    root: str
    manifest: dict[str, Any]
    width: int
    height: int
    K: np.ndarray
    timestamps: np.ndarray
    camera_to_scene: np.ndarray
    test_cameras: np.ndarray | None
    objects: list[ExportObjectData]
    anchor_index: int
    net_layers: list[tuple[np.ndarray, np.ndarray]] | None
    net_hidden: str = "relu"
    net_output: str = "sigmoid"
    net_threshold: float = 0.5
    samples: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.timestamps)

    @property
    def scale_ranges(self) -> np.ndarray:
        return np.array([o.scale_range for o in self.objects], dtype=np.float64)

    @property
    def valid_intervals(self) -> np.ndarray:
        return np.array([o.valid_interval for o in self.objects], dtype=np.float64)

    @property
    def free_indices(self) -> list[int]:
        """Positions of the non-anchor objects: the scale network's inputs, in order."""
        return [i for i in range(len(self.objects)) if i != self.anchor_index]

    def validity(self, sbar: np.ndarray) -> np.ndarray:
        """Scale-network score of actual scales ``(N, K)`` or ``(K,)``."""
        s = scale_scores(self.net_layers, np.asarray(sbar, dtype=np.float64), self.scale_ranges, self.anchor_index,
                         self.net_hidden, self.net_output)
        return s if np.ndim(sbar) > 1 else s[0]

    def sample(self, count: int, seed: int) -> np.ndarray:
        """``count`` valid configurations (actual scales), seeded rejection sampling."""
        return sample_valid_configurations(self.validity, self.valid_intervals, self.net_threshold, count, seed)


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _show(value: Any, limit: int = 60) -> str:
    """A short one-line ``repr`` of a manifest value for an error message."""
    s = " ".join(repr(value).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _get(d: Any, key: str, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise ExportFormatError(f"{where}: missing key {key!r}")
    return d[key]


def _dict(value: Any, where: str, what: str) -> dict:
    if not isinstance(value, dict):
        raise ExportFormatError(f"{where}: {what} must be a JSON object, got {_show(value)}")
    return value


def _list(value: Any, where: str, what: str) -> list:
    if not isinstance(value, list):
        raise ExportFormatError(f"{where}: {what} must be a list, got {_show(value)}")
    return value


def names_manifest(filepath: str, set_in_call: bool) -> bool:
    """Whether an import call names an ``osn_export.json`` itself (then it imports without a file
    browser). ``filepath`` is remembered between runs (the browser reopens in the last export's
    folder), so a value alone does not mean the caller chose it: ``set_in_call`` is Blender's
    ``is_property_set("filepath")``, false for a value carried over from the previous run and true
    only when the caller (drop handler, menu/keymap item, script) set it for this call."""
    return bool(set_in_call) and os.path.basename(filepath) == MANIFEST_NAME


def _str(value: Any, where: str, what: str) -> str:
    if not isinstance(value, str) or not value:
        raise ExportFormatError(f"{where}: {what} must be a non-empty string, got {_show(value)}")
    return value


def _int(value: Any, where: str, what: str, minimum: int | None = None) -> int:
    """A JSON integer (an integral float is accepted), optionally ``>= minimum``; bools are refused."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
        bound = "" if minimum is None else f" >= {minimum}"
        raise ExportFormatError(f"{where}: {what} must be an integer{bound}, got {_show(value)}")
    return value


def _numbers(value: Any, where: str, what: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Finite JSON numbers of exactly ``shape`` (``None`` = any length) as float64."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):  # ragged nesting
        a = None
    if len(shape) == 0:
        want = "a number"
    elif len(shape) == 1:
        want = "a list of numbers" if shape[0] is None else f"a list of {shape[0]} numbers"
    else:
        want = "an array of " + "x".join("N" if n is None else str(n) for n in shape) + " numbers"
    if (a is None or a.dtype.kind not in "iuf" or a.ndim != len(shape)
            or any(n is not None and n != m for n, m in zip(shape, a.shape))):
        raise ExportFormatError(f"{where}: {what} must be {want}, got {_show(value)}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise ExportFormatError(f"{where}: {what} has non-finite values")
    return a


def _array(arrays: dict[str, np.ndarray], key: str, shape: tuple[int | None, ...], where: str) -> np.ndarray:
    if key not in arrays:
        raise ExportFormatError(f"{where}: missing array {key!r}")
    a = np.asarray(arrays[key])
    if a.dtype.kind not in "iuf":
        raise ExportFormatError(f"{where}: array {key!r} has dtype {a.dtype}, expected numbers")
    a = a.astype(np.float64)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise ExportFormatError(f"{where}: array {key!r} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ExportFormatError(f"{where}: array {key!r} has non-finite values")
    return a


#: Most bytes the arrays of one export ``.npz`` may declare together, whatever its manifest says
#: (a manifest can claim any count); a million sampled configurations of thirty objects take a
#: tenth of it.
MAX_NPZ_BYTES = 1 << 28
_NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


def _npz_declared_bytes(path: str) -> int:
    """Bytes the members of ``path`` declare in their ``.npy`` headers, read without loading any
    array; a member that is not a ``.npy`` array of numbers is refused."""
    total = 0
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version not in _NPY_HEADERS:
                    raise ValueError(f"member {info.filename!r} has .npy format version {version}")
                shape, _, dtype = _NPY_HEADERS[version](fh)
            if not info.filename.endswith(".npy") or dtype.hasobject:
                raise ValueError(f"member {info.filename!r} is not a .npy array of numbers")
            total += math.prod(shape) * dtype.itemsize
    return total


def _load_npz(path: str, max_bytes: int) -> dict[str, np.ndarray]:
    """Every array of ``path`` (never unpickling). Their ``.npy`` headers are read first and the
    file is refused, before any array is allocated, when they declare more than ``max_bytes``
    together (what the export's sizes allow): a small compressed member can declare gigabytes."""
    try:
        declared = _npz_declared_bytes(path)
        if declared > max_bytes:
            raise ExportFormatError(
                f"{path}: arrays declare {declared} bytes, more than the {max_bytes} the export's sizes allow")
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except ExportFormatError:
        raise
    except Exception as e:  # noqa: BLE001 - any decoding failure is a corrupt file for the user
        raise ExportFormatError(f"{path}: cannot read ({' '.join(str(e).split())})") from None


def _declared_count(m: dict[str, Any], key: str, mpath: str) -> int:
    """``m[key]["count"]``, the number of test cameras or samples the manifest declares (0 when
    ``m[key]`` is null or absent)."""
    entry = m.get(key)
    if entry is None:
        return 0
    return _int(_get(_dict(entry, mpath, f"{key!r}"), "count", f"{mpath}: {key}"), mpath, f"{key}.count", minimum=0)


def _arrays_bytes(m: dict[str, Any], mpath: str, T: int) -> int:
    """Most bytes ``arrays.npz`` can hold for the manifest's sizes (at most :data:`MAX_NPZ_BYTES`):
    float64 4x4 poses of the camera, of every object and of every declared test camera at each of
    the ``T`` frames, the objects' int64 frame indices and the declared sampled configurations."""
    K = len(_list(_get(m, "objects", mpath), mpath, "'objects'"))
    V, N = _declared_count(m, "test_cameras", mpath), _declared_count(m, "samples", mpath)
    return min(MAX_NPZ_BYTES, 8 * (16 * T * (1 + K + V) + T * K + N * K))


def read_ply(path: str) -> dict[str, np.ndarray]:
    """Read a binary little-endian triangle PLY with uchar RGB(A) vertex colours (as the export writes).

    Returns ``vertices (V, 3) float64``, ``faces (F, 3) int64`` and ``colors (V, 4) uint8`` (sRGB).
    """
    with open(path, "rb") as fh:
        blob = fh.read()
    end = blob.find(b"end_header\n")
    if not blob.startswith(b"ply\n") or end < 0:
        raise ExportFormatError(f"{path}: not a PLY file")
    header = blob[: end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ExportFormatError(f"{path}: only binary little-endian PLY is supported")
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    off = end + len(b"end_header\n")
    out: dict[str, np.ndarray] = {}
    try:
        for line in header:
            w = line.split()
            if w[:1] == ["element"]:
                elements.append((w[1], int(w[2]), []))
            elif w[:1] == ["property"] and elements:
                elements[-1][2].append((w[-1], " ".join(w[1:-1])))
        for name, count, props in elements:
            if name == "vertex":
                dt = np.dtype([(p, types[t]) for p, t in props])
                v = np.frombuffer(blob, dtype=dt, count=count, offset=off)
                off += dt.itemsize * count
                out["vertices"] = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
                names = v.dtype.names or ()
                rgb = [v[c] for c in ("red", "green", "blue")] if "red" in names else [np.full(count, 255, np.uint8)] * 3
                alpha = v["alpha"] if "alpha" in names else np.full(count, 255, np.uint8)
                out["colors"] = np.stack(rgb + [alpha], axis=1).astype(np.uint8)
            elif name == "face":
                if len(props) != 1 or props[0][1] not in ("list uchar int", "list uchar uint"):
                    raise ExportFormatError(f"{path}: unsupported face layout {props}")
                dt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
                f = np.frombuffer(blob, dtype=dt, count=count, offset=off)
                off += dt.itemsize * count
                if count and not np.all(f["n"] == 3):
                    raise ExportFormatError(f"{path}: only triangle faces are supported")
                out["faces"] = f["i"].astype(np.int64)
            else:
                raise ExportFormatError(f"{path}: unexpected PLY element {name!r}")
    except (ValueError, KeyError, IndexError, TypeError) as e:
        if isinstance(e, ExportFormatError):
            raise
        raise ExportFormatError(f"{path}: truncated or malformed PLY ({' '.join(str(e).split())})") from None
    if "vertices" not in out or "faces" not in out:
        raise ExportFormatError(f"{path}: PLY lacks vertices or faces")
    if len(out["faces"]) and (out["faces"].min() < 0 or out["faces"].max() >= len(out["vertices"])):
        raise ExportFormatError(f"{path}: face indices out of range")
    return out


def read_export(path: str, load_meshes: bool = True) -> ExportData:
    """Read and validate an export directory (or its manifest file).

    Checks the format and version, that every file the manifest names exists with the recorded
    size and sha256, every manifest field's type and shape, and every array's shape and
    finiteness, before anything is returned: a caller that builds a scene from the result never
    sees a half-valid export. Every problem raises ``ExportFormatError`` (or ``OSError`` for an
    unreadable file) with a one-line message naming the file and the field.
    """
    root = os.path.dirname(path) if os.path.isfile(path) else path
    mpath = os.path.join(root, MANIFEST_NAME)
    if not os.path.isfile(mpath):
        raise ExportFormatError(f"{mpath}: missing manifest (not an OSN export directory)")
    try:
        with open(mpath, encoding="utf-8") as fh:
            m = json.load(fh)
    except (OSError, ValueError) as e:
        raise ExportFormatError(f"{mpath}: cannot read JSON ({e})") from None
    if not isinstance(m, dict) or m.get("format") != EXPORT_FORMAT:
        raise ExportFormatError(f"{mpath}: not an {EXPORT_FORMAT} manifest")
    if m.get("version") != EXPORT_VERSION:
        raise ExportFormatError(
            f"{mpath}: export version {m.get('version')!r}, this reader supports version {EXPORT_VERSION}; "
            "re-export with a matching osn or update the add-on"
        )
    try:
        return _read_manifest(root, mpath, m, load_meshes)
    except (TypeError, ValueError, KeyError, IndexError) as e:
        # The checks above and below name the field; this only keeps a case they missed from
        # reaching the user as a traceback.
        if isinstance(e, ExportFormatError):
            raise
        raise ExportFormatError(f"{mpath}: malformed export ({type(e).__name__}: {' '.join(str(e).split())})") from None


def _check_listed_files(root: str, mpath: str, m: dict[str, Any]) -> set[str]:
    """The manifest's ``files``: each inside the export, present, of the recorded size and sha256."""
    listed: set[str] = set()
    for j, entry in enumerate(_list(_get(m, "files", mpath), mpath, "'files'")):
        what = f"files[{j}]"
        _dict(entry, mpath, what)
        rel = _str(_get(entry, "path", f"{mpath}: {what}"), mpath, f"{what}.path")
        size = _int(_get(entry, "bytes", f"{mpath}: {what}"), mpath, f"{what}.bytes", minimum=0)
        digest = _str(_get(entry, "sha256", f"{mpath}: {what}"), mpath, f"{what}.sha256")
        # Absolute names, '..' and symbolic links leading out of the export are refused.
        p = os.fspath(join_inside(root, rel, f"{what}.path", ExportFormatError, source=mpath, resolve=True))
        if not os.path.isfile(p):
            raise ExportFormatError(f"{p}: missing file named in the manifest")
        if os.path.getsize(p) != size or sha256_file(p) != digest:
            raise ExportFormatError(f"{p}: corrupt file (size or sha256 differs from the manifest)")
        listed.add(rel)
    return listed


def _file_namer(root: str, mpath: str, listed: set[str]) -> Callable[[Any, str], str]:
    """``named(rel, what)``: the path of a file the manifest refers to, which must be among ``listed``."""

    def named(rel: Any, what: str) -> str:
        if not isinstance(rel, str) or rel not in listed:
            raise ExportFormatError(f"{mpath}: {what} {_show(rel)} is not among the manifest's files")
        return os.path.join(root, rel)

    return named


def _read_object(
    o: Any, i: int, mpath: str, arrays: dict[str, np.ndarray], T: int, named: Callable[[Any, str], str],
    used_ids: set[int],
) -> ExportObjectData:
    """Manifest entry ``i`` of ``objects`` with its arrays (mesh not loaded); its id not in ``used_ids``."""
    where = f"{mpath}: object {i}"
    _dict(o, mpath, f"object {i}")
    oid = _int(_get(o, "id", where), where, "id", minimum=0)
    if oid in used_ids:
        raise ExportFormatError(f"{where}: id {oid} is used by another object")
    frames = np.asarray(arrays.get(f"obj{oid}_frames", np.zeros(0, np.int64)))
    if frames.dtype.kind not in "iu" or frames.ndim != 1 or not len(frames) or frames.min() < 0 or frames.max() >= T:
        raise ExportFormatError(f"{where}: frames must be a non-empty integer subset of 0..{T - 1}")
    frames = frames.astype(np.int64)
    lo, hi = _numbers(_get(o, "scale_range", where), where, "scale_range", (2,))
    vlo, vhi = _numbers(_get(o, "valid_interval", where), where, "valid_interval", (2,))
    if not (0 < lo < hi and 0 < vlo <= vhi):
        raise ExportFormatError(f"{where}: scale_range [{lo}, {hi}] or valid_interval [{vlo}, {vhi}] is empty or inverted")
    grid_shape = _list(_get(o, "grid_shape", where), where, "grid_shape")
    if len(grid_shape) != 3:
        raise ExportFormatError(f"{where}: grid_shape must be 3 integers [D, H, W], got {_show(grid_shape)}")
    mesh_rel = o.get("mesh")
    is_anchor = _get(o, "is_anchor", where)
    if not isinstance(is_anchor, bool):
        raise ExportFormatError(f"{where}: is_anchor must be true or false, got {_show(is_anchor)}")
    return ExportObjectData(
        id=oid,
        name=_str(_get(o, "name", where), where, "name"),
        is_anchor=is_anchor,
        bbox=_numbers(_get(o, "bbox", where), where, "bbox", (2, 3)),
        grid_shape=tuple(_int(n, where, "grid_shape", minimum=1) for n in grid_shape),  # type: ignore[arg-type]
        scale_range=(float(lo), float(hi)),
        valid_interval=(float(vlo), float(vhi)),
        frames=frames,
        object_to_scene=_array(arrays, f"obj{oid}_object_to_scene", (len(frames), 4, 4), where),
        volume_path=named(_get(o, "volume", where), "volume"),
        mesh_path=named(mesh_rel, "mesh") if mesh_rel is not None else None,
        field=_read_field(o.get("field"), where, named),
    )


def _read_field(f: Any, where: str, named: Callable[[Any, str], str]) -> FieldGrids | None:
    """An object's optional ``field`` entry (absent or null: an export made before it existed)."""
    if f is None:
        return None
    where = f"{where}: field"
    _dict(f, where, "entry")
    dens, col = _dict(_get(f, "density", where), where, "density"), _dict(_get(f, "color", where), where, "color")
    if _get(dens, "activation", where) != "softplus" or _get(col, "activation", where) != "sigmoid":
        raise ExportFormatError(f"{where}: activations {_show(dens.get('activation'))} / {_show(col.get('activation'))}, "
                                "this reader supports softplus density and sigmoid colour")
    offset = _numbers(_get(dens, "offset", where), where, "density offset", ())
    planes = None
    entry = col.get("planes")
    if entry is not None:
        pw = f"{where}: color planes"
        _dict(entry, pw, "entry")
        P = _int(_get(entry, "size", pw), pw, "size", minimum=2)
        if P > MAX_PLANE_SIZE:
            raise ExportFormatError(f"{pw}: size {P} exceeds {MAX_PLANE_SIZE}")
        if [list(x) for x in _list(_get(entry, "axes", pw), pw, "axes")] != [list(x) for x in PLANE_AXES]:
            raise ExportFormatError(f"{pw}: axes {_show(entry.get('axes'))}, this reader supports {[list(x) for x in PLANE_AXES]}")
        z = _load_npz(named(_get(entry, "file", pw), "colour planes file"), 4 * 9 * P * P + 4096)
        planes = _array(z, _str(_get(entry, "array", pw), pw, "array"), (3, P, P, 3), pw)
    return FieldGrids(_str(_get(dens, "grid", where), where, "density grid"), float(offset),
                      _str(_get(col, "grid", where), where, "colour grid"), planes)


def _read_objects(
    m: dict[str, Any], mpath: str, arrays: dict[str, np.ndarray], T: int, named: Callable[[Any, str], str], load_meshes: bool
) -> tuple[list[ExportObjectData], int]:
    """Every object (ids unique, meshes loaded if asked) and the index of the one anchor."""
    objects: list[ExportObjectData] = []
    for i, o in enumerate(_list(_get(m, "objects", mpath), mpath, "'objects'")):
        obj = _read_object(o, i, mpath, arrays, T, named, {prev.id for prev in objects})
        if load_meshes and obj.mesh_path:
            obj.mesh = read_ply(obj.mesh_path)
        objects.append(obj)
    anchors = [i for i, o in enumerate(objects) if o.is_anchor]
    if len(anchors) != 1:
        raise ExportFormatError(f"{mpath}: expected exactly one anchor object, found {len(anchors)}")
    return objects, anchors[0]


def _read_scale_network(
    net: Any, mpath: str, named: Callable[[Any, str], str], num_objects: int
) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, Any]]:
    """The network's layers ``[(W (out, in), b (out,)), ...]`` (input width ``num_objects - 1``,
    output width 1) and its ``ExportData`` fields (activations, threshold)."""
    where = f"{mpath}: scale_network"
    _dict(net, mpath, "'scale_network'")
    z = _load_npz(named(_get(net, "file", where), "scale network file"), MAX_NPZ_BYTES)
    n = _int(_get(net, "layers", where), where, "layers", minimum=1)
    width_in, layers = num_objects - 1, []
    for i in range(n):  # each layer's input width is the previous layer's output width
        W = _array(z, f"W{i}", (None, width_in), where)
        layers.append((W, _array(z, f"b{i}", (W.shape[0],), where)))
        width_in = W.shape[0]
    if width_in != 1:
        raise ExportFormatError(f"{mpath}: scale network output width {width_in}, expected 1")
    net_kw = {
        "net_hidden": _str(_get(net, "hidden_activation", where), where, "hidden_activation"),
        "net_output": _str(_get(net, "output_activation", where), where, "output_activation"),
        "net_threshold": float(_numbers(_get(net, "threshold", where), where, "threshold", ())),
    }
    for key in ("net_hidden", "net_output"):
        if net_kw[key] not in ACTIVATIONS:
            raise ExportFormatError(f"{where}: unknown activation {net_kw[key]!r} (expected one of {ACTIVATIONS})")
    return layers, net_kw


def _read_manifest(root: str, mpath: str, m: dict[str, Any], load_meshes: bool) -> ExportData:
    named = _file_namer(root, mpath, _check_listed_files(root, mpath, m))
    timestamps = _numbers(_get(m, "timestamps", mpath), mpath, "'timestamps'", (None,))
    T = len(timestamps)
    if T == 0:
        raise ExportFormatError(f"{mpath}: 'timestamps' is empty")
    arrays = _load_npz(named(_get(m, "arrays", mpath), "arrays file"), _arrays_bytes(m, mpath, T))
    cam = _dict(_get(m, "camera", mpath), mpath, "'camera'")
    width = _int(_get(cam, "width", f"{mpath}: camera"), mpath, "camera.width", minimum=1)
    height = _int(_get(cam, "height", f"{mpath}: camera"), mpath, "camera.height", minimum=1)
    K = _numbers(_get(cam, "K", f"{mpath}: camera"), mpath, "camera.K", (3, 3))
    c2s = _array(arrays, "camera_to_scene", (T, 4, 4), mpath)
    test = _array(arrays, "test_cameras", (None, T, 4, 4), mpath) if "test_cameras" in arrays else None
    objects, anchor = _read_objects(m, mpath, arrays, T, named, load_meshes)
    net = m.get("scale_network")
    layers, net_kw = _read_scale_network(net, mpath, named, len(objects)) if net is not None else (None, {})
    samples = _array(arrays, "samples_sbar", (None, len(objects)), mpath) if "samples_sbar" in arrays else None
    return ExportData(
        root=root,
        manifest=m,
        width=width,
        height=height,
        K=K,
        timestamps=timestamps,
        camera_to_scene=c2s,
        test_cameras=test,
        objects=objects,
        anchor_index=anchor,
        net_layers=layers,
        samples=samples,
        **net_kw,
    )

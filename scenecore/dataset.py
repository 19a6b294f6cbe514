"""Dataset format v1: reading, writing and validating (numpy only; never imports bpy or torch).

This module is the single owner of the on-disk layout specified in ``docs/dataset-format.md``.
benchgen writes through it, osn reads through it, and ``validate`` checks a directory against it.

Layout::

    DATASET/
      scene.json                       manifest (format, version, camera, frames, objects)
      train/{rgb,depth,ids}/NAME.*     the monocular training video (shared by every configuration)
      configs/GGG/config.json          scale vector of ground-truth configuration GGG
      configs/GGG/{rgb,depth,ids}/NAME.*   its test views
      valid_region.json                exact valid-scale region
      verification.json                invariance statistics (optional until generation ends)
      transforms_train.json / transforms_test.json   D-NeRF/NVFi-style views (optional)

Every write is atomic: a temporary file in the same directory, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from .cameras import fov_from_intrinsics, intrinsics_matrix, opengl_from_opencv, scale_about
from .validity import ValidRegion

FORMAT_NAME = "osn-dataset"
FORMAT_VERSION = 1
#: Instance-id value of pixels where no object is hit.
NO_OBJECT = 255
MAX_OBJECTS = 255
SPLITS = ("train", "test")
ROLES = ("anchor", "object")


class DatasetError(ValueError):
    """A dataset file is missing or malformed. The message names the file and the problem."""


# --------------------------------------------------------------------------------------------
# Typed objects
# --------------------------------------------------------------------------------------------


@dataclass
class Intrinsics:
    """Pixel-unit pinhole intrinsics (pixel centres at ``.5``, see :mod:`scenecore.cameras`)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    @classmethod
    def from_matrix(cls, K: np.ndarray) -> "Intrinsics":
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


@dataclass
class Frame:
    """One image of the rig: viewpoint ``view`` at timestamp index ``time_index``.

    ``camera_to_world`` is a 4x4 OpenCV pose (x right, y down, z forward) in world units.
    """

    name: str
    view: int
    time_index: int
    split: str
    camera_to_world: np.ndarray


@dataclass
class SceneObject:
    """A rigid object. ``poses[t]`` is its 4x4 object-to-world pose in the base configuration."""

    id: int
    name: str
    role: str
    poses: np.ndarray


@dataclass
class Scene:
    """The manifest ``scene.json``."""

    width: int
    height: int
    intrinsics: Intrinsics
    timestamps: np.ndarray
    num_views: int
    frames: list[Frame]
    objects: list[SceneObject]
    num_configurations: int
    units: str = "meters"
    generator: dict[str, Any] = field(default_factory=dict)

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def anchor_id(self) -> int:
        return next(o.id for o in self.objects if o.role == "anchor")

    def split(self, split: str) -> list[Frame]:
        return [f for f in self.frames if f.split == split]

    @property
    def train_frames(self) -> list[Frame]:
        return self.split("train")

    @property
    def test_frames(self) -> list[Frame]:
        return self.split("test")

    def training_camera_centers(self) -> np.ndarray:
        """``(T, 3)`` training camera centre per timestamp: the centre each configuration scales about."""
        centers = np.full((len(self.timestamps), 3), np.nan)
        for f in self.train_frames:
            centers[f.time_index] = f.camera_to_world[:3, 3]
        return centers

    def configured_pose(self, object_id: int, time_index: int, scale: float) -> np.ndarray:
        """Object-to-world pose of an object scaled by ``scale`` about the training camera centre."""
        c = self.training_camera_centers()[time_index]
        return scale_about(c, scale) @ self.objects[object_id].poses[time_index]


@dataclass
class Configuration:
    """Ground-truth configuration ``index``: one scale per object (the anchor's is 1)."""

    index: int
    scales: np.ndarray

    @property
    def dirname(self) -> str:
        return config_dirname(self.index)


@dataclass
class FramePaths:
    rgb: Path
    depth: Path
    ids: Path

    def all(self) -> tuple[Path, Path, Path]:
        return (self.rgb, self.depth, self.ids)

    def exist(self) -> bool:
        return all(p.exists() for p in self.all())


# --------------------------------------------------------------------------------------------
# Paths
# --------------------------------------------------------------------------------------------


def config_dirname(index: int) -> str:
    return f"{index:03d}"


def frame_paths(root: str | Path, frame_name: str, config: int | None = None) -> FramePaths:
    """Paths of a frame's files: the training video when ``config`` is None, else a config's view."""
    base = Path(root) / ("train" if config is None else Path("configs") / config_dirname(config))
    return FramePaths(
        rgb=base / "rgb" / f"{frame_name}.png",
        depth=base / "depth" / f"{frame_name}.exr",
        ids=base / "ids" / f"{frame_name}.png",
    )


# --------------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``, else delete it.

    For writers that need a file name (OpenEXR, OpenVDB): the final file appears complete or not at all.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
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


def _finite_or_none(x: np.ndarray) -> list:
    """JSON has no infinity: +inf is stored as null."""
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in np.atleast_2d(x)]


def atomic_write_json(path: str | Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1, default=_json_default) + "\n").encode())


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: missing file")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------


def encode_png(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", np.ascontiguousarray(image), extension=".png")


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write an ``(H, W, 3)`` uint8 RGB PNG atomically."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: RGB must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    atomic_write_bytes(path, encode_png(rgb))


def write_ids(path: str | Path, ids: np.ndarray) -> None:
    """Write an ``(H, W)`` uint8 instance-id PNG atomically (``NO_OBJECT`` = nothing hit)."""
    ids = np.asarray(ids)
    if ids.dtype != np.uint8 or ids.ndim != 2:
        raise ValueError(f"{path}: instance ids must be (H, W) uint8, got {ids.shape} {ids.dtype}")
    atomic_write_bytes(path, encode_png(ids))


def write_depth(path: str | Path, depth: np.ndarray) -> None:
    """Write ``(H, W)`` planar depth as a float32 single-channel ("Z") EXR, atomically.

    The array is converted to a C-contiguous float32 copy first: OpenEXR writes strided or
    transposed arrays wrong without raising.
    """
    import OpenEXR

    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"{path}: depth must be (H, W), got {depth.shape}")
    data = np.ascontiguousarray(depth, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        OpenEXR.File(header, {"Z": data}).write(str(tmp))


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise DatasetError(f"{path}: missing file")


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an 8-bit RGB image (PNG, or JPEG for ``osn preprocess``) as ``(H, W, 3)`` uint8
    (alpha dropped, grey expanded)."""
    import imageio.v3 as iio

    path = Path(path)
    _check_exists(path)
    try:
        img = iio.imread(path)
    except Exception as e:  # imageio raises many types for corrupt files
        raise DatasetError(f"{path}: cannot read the image ({e})") from None
    if img.dtype != np.uint8:
        raise DatasetError(f"{path}: expected 8-bit RGB, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise DatasetError(f"{path}: expected an RGB image, got shape {img.shape}")
    return np.ascontiguousarray(img[..., :3])


def read_ids(path: str | Path) -> np.ndarray:
    """Read an instance-id PNG as ``(H, W)`` uint8."""
    import imageio.v3 as iio

    path = Path(path)
    _check_exists(path)
    try:
        img = iio.imread(path)
    except Exception as e:
        raise DatasetError(f"{path}: cannot read the image ({e})") from None
    if img.ndim != 2 or img.dtype != np.uint8:
        raise DatasetError(f"{path}: instance ids must be a single-channel 8-bit PNG, got {img.shape} {img.dtype}")
    return img


def read_depth(path: str | Path) -> np.ndarray:
    """Read a planar-depth EXR (channel "Z", or the only channel) as ``(H, W)`` float32."""
    import OpenEXR

    path = Path(path)
    _check_exists(path)
    try:
        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "Z" in channels:
                px = channels["Z"].pixels
            elif len(channels) == 1:
                px = next(iter(channels.values())).pixels
            else:
                raise DatasetError(f"{path}: no 'Z' channel (found {sorted(channels)})")
            px = np.array(px)
    except DatasetError:
        raise
    except Exception as e:
        raise DatasetError(f"{path}: cannot read EXR ({e})") from None
    if px.ndim != 2:
        raise DatasetError(f"{path}: depth must be a single channel, got shape {px.shape}")
    return px.astype(np.float32, copy=False)


# --------------------------------------------------------------------------------------------
# Manifest (de)serialisation
# --------------------------------------------------------------------------------------------


def scene_to_json(scene: Scene) -> dict[str, Any]:
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "units": scene.units,
        "camera_convention": "opencv",
        "depth": "planar",
        "no_object_id": NO_OBJECT,
        "image": {"width": scene.width, "height": scene.height},
        "intrinsics": {
            "fx": scene.intrinsics.fx,
            "fy": scene.intrinsics.fy,
            "cx": scene.intrinsics.cx,
            "cy": scene.intrinsics.cy,
        },
        "timestamps": [float(t) for t in scene.timestamps],
        "num_views": scene.num_views,
        "num_configurations": scene.num_configurations,
        "objects": [
            {"id": o.id, "name": o.name, "role": o.role, "poses": np.asarray(o.poses).tolist()}
            for o in scene.objects
        ],
        "frames": [
            {
                "name": f.name,
                "view": f.view,
                "time_index": f.time_index,
                "split": f.split,
                "camera_to_world": np.asarray(f.camera_to_world).tolist(),
            }
            for f in scene.frames
        ],
        "generator": scene.generator,
    }


def _req(d: dict, key: str, where: str, path: Path) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise DatasetError(f"{path}: {where} is missing '{key}'")
    return d[key]


def _matrix(x: Any, shape: tuple[int, ...], what: str, path: Path) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {what} is not a numeric array") from None
    if a.shape != shape:
        raise DatasetError(f"{path}: {what} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{path}: {what} contains non-finite values")
    return a


def scene_from_json(d: dict[str, Any], path: Path) -> Scene:
    """Parse and check a manifest dict; raise ``DatasetError`` naming ``path`` and the problem."""
    try:
        return _scene_from_json(d, path)
    except DatasetError as e:
        raise DatasetError(str(e) if str(path) in str(e) else f"{path}: {e}") from None
    except (TypeError, ValueError, KeyError, AttributeError, IndexError) as e:  # a field of the wrong type
        raise DatasetError(f"{path}: malformed manifest ({type(e).__name__}: {e})") from None


def _scene_from_json(d: dict[str, Any], path: Path) -> Scene:
    fmt = d.get("format") if isinstance(d, dict) else None
    if fmt != FORMAT_NAME:
        raise DatasetError(f"{path}: not an {FORMAT_NAME} manifest (format={fmt!r})")
    version = d.get("version")
    if version != FORMAT_VERSION:
        raise DatasetError(
            f"{path}: unknown format version {version!r} (this toolkit reads version {FORMAT_VERSION})"
        )
    image = _req(d, "image", "manifest", path)
    width, height = int(_req(image, "width", "image", path)), int(_req(image, "height", "image", path))
    if width <= 0 or height <= 0:
        raise DatasetError(f"{path}: image size {width}x{height} is not positive")
    intr = _req(d, "intrinsics", "manifest", path)
    vals = [float(_req(intr, k, "intrinsics", path)) for k in ("fx", "fy", "cx", "cy")]
    if not all(math.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
        raise DatasetError(f"{path}: intrinsics {vals} must be finite with positive focal lengths")
    timestamps = np.array(_req(d, "timestamps", "manifest", path), dtype=np.float64)
    T = len(timestamps)
    if T == 0 or not np.all(np.isfinite(timestamps)):
        raise DatasetError(f"{path}: timestamps must be a non-empty list of finite numbers")
    objects = []
    for k, o in enumerate(_req(d, "objects", "manifest", path)):
        oid = int(_req(o, "id", f"object {k}", path))
        if oid != k:
            raise DatasetError(f"{path}: object {k} has id {oid}; ids must be 0..K-1 in order")
        role = _req(o, "role", f"object {k}", path)
        if role not in ROLES:
            raise DatasetError(f"{path}: object {k} has unknown role {role!r} (expected one of {ROLES})")
        poses = _matrix(_req(o, "poses", f"object {k}", path), (T, 4, 4), f"object {k} poses", path)
        objects.append(SceneObject(oid, str(_req(o, "name", f"object {k}", path)), role, poses))
    if not objects:
        raise DatasetError(f"{path}: no objects")
    if len(objects) > MAX_OBJECTS:
        raise DatasetError(f"{path}: {len(objects)} objects; at most {MAX_OBJECTS} fit in 8-bit ids")
    anchors = [o.id for o in objects if o.role == "anchor"]
    if len(anchors) != 1:
        raise DatasetError(f"{path}: exactly one object must have role 'anchor', found {len(anchors)}")
    num_views = int(_req(d, "num_views", "manifest", path))
    frames = []
    names = set()
    for i, f in enumerate(_req(d, "frames", "manifest", path)):
        name = str(_req(f, "name", f"frame {i}", path))
        if name in names:
            raise DatasetError(f"{path}: duplicate frame name {name!r}")
        names.add(name)
        split = _req(f, "split", f"frame {name}", path)
        if split not in SPLITS:
            raise DatasetError(f"{path}: frame {name} has unknown split {split!r}")
        ti = int(_req(f, "time_index", f"frame {name}", path))
        if not 0 <= ti < T:
            raise DatasetError(f"{path}: frame {name} has time_index {ti} outside 0..{T - 1}")
        view = int(_req(f, "view", f"frame {name}", path))
        if not 0 <= view < num_views:
            raise DatasetError(f"{path}: frame {name} has view {view} outside 0..{num_views - 1}")
        c2w = _matrix(_req(f, "camera_to_world", f"frame {name}", path), (4, 4), f"frame {name} camera_to_world", path)
        frames.append(Frame(name, view, ti, split, c2w))
    train_times = sorted(f.time_index for f in frames if f.split == "train")
    if train_times != list(range(T)):
        raise DatasetError(f"{path}: the training video must have exactly one frame per timestamp")
    return Scene(
        width=width,
        height=height,
        intrinsics=Intrinsics(*vals),
        timestamps=timestamps,
        num_views=num_views,
        frames=frames,
        objects=objects,
        num_configurations=int(d.get("num_configurations", 0)),
        units=str(d.get("units", "meters")),
        generator=dict(d.get("generator", {})),
    )


# --------------------------------------------------------------------------------------------
# Public read / write API
# --------------------------------------------------------------------------------------------


def write_scene(root: str | Path, scene: Scene) -> None:
    atomic_write_json(Path(root) / "scene.json", scene_to_json(scene))


def load_scene(root: str | Path) -> Scene:
    path = Path(root) / "scene.json"
    return scene_from_json(read_json(path), path)


def write_frame(
    root: str | Path,
    frame_name: str,
    rgb: np.ndarray,
    depth: np.ndarray,
    ids: np.ndarray,
    config: int | None = None,
) -> FramePaths:
    """Write one frame's RGB, depth and instance ids (training video if ``config`` is None)."""
    paths = frame_paths(root, frame_name, config)
    # Depth and ids first, RGB last: a frame counts as present once all three exist.
    write_depth(paths.depth, depth)
    write_ids(paths.ids, ids)
    write_rgb(paths.rgb, rgb)
    return paths


def read_training_video(root: str | Path, scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The training video in time order, checked against ``scene``: ``rgb (T,H,W,3)``,
    ``depth (T,H,W)`` and ``ids (T,H,W)`` (see :func:`read_frame`)."""
    frames = [read_frame(root, f.name, scene=scene) for f in sorted(scene.train_frames, key=lambda f: f.time_index)]
    return tuple(np.stack(a) for a in zip(*frames))  # type: ignore[return-value]


def read_frame(
    root: str | Path, frame_name: str, config: int | None = None, scene: Scene | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``(rgb uint8 (H,W,3), depth float32 (H,W), ids uint8 (H,W))`` of a frame.

    With ``scene``, also check every image against the manifest (size, instance ids in range)
    and raise ``DatasetError`` naming the first bad file: readers that stack frames or index
    objects by id would otherwise fail later with a message that names no file.
    """
    p = frame_paths(root, frame_name, config)
    rgb, depth, ids = read_rgb(p.rgb), read_depth(p.depth), read_ids(p.ids)
    if scene is not None:
        for problem in (
            size_problem(p.rgb, rgb.shape[:2], scene),
            size_problem(p.depth, depth.shape, scene),
            size_problem(p.ids, ids.shape, scene) or ids_problem(p.ids, ids, scene.num_objects),
        ):
            if problem:
                raise DatasetError(problem)
    return rgb, depth, ids


def size_problem(path: Path, shape: tuple[int, ...], scene: Scene) -> str | None:
    """One line naming ``path`` when an image of ``shape (H, W)`` does not match the manifest."""
    if tuple(shape) == (scene.height, scene.width):
        return None
    return f"{path}: size {shape[1]}x{shape[0]}, expected {scene.width}x{scene.height} (scene.json)"


def ids_problem(path: Path, ids: np.ndarray, num_objects: int) -> str | None:
    """One line naming ``path`` when instance ids name no object of the manifest."""
    bad = (ids >= num_objects) & (ids != NO_OBJECT)
    if not bad.any():
        return None
    return (
        f"{path}: {int(bad.sum())} pixels have ids out of range "
        f"(found {sorted(set(np.unique(ids[bad]).tolist()))}, objects are 0..{num_objects - 1}, {NO_OBJECT} = none)"
    )


def write_configuration(root: str | Path, config: Configuration) -> None:
    atomic_write_json(
        Path(root) / "configs" / config.dirname / "config.json",
        {"index": config.index, "scales": np.asarray(config.scales, dtype=np.float64).tolist()},
    )


def load_configuration(root: str | Path, index: int, num_objects: int | None = None) -> Configuration:
    path = Path(root) / "configs" / config_dirname(index) / "config.json"
    d = read_json(path)
    scales = np.array(_req(d, "scales", "configuration", path), dtype=np.float64)
    if scales.ndim != 1 or (num_objects is not None and len(scales) != num_objects):
        raise DatasetError(f"{path}: scales has shape {scales.shape}, expected ({num_objects},)")
    if not np.all(np.isfinite(scales)) or np.any(scales <= 0):
        raise DatasetError(f"{path}: scales must be finite and positive, got {scales.tolist()}")
    return Configuration(int(d.get("index", index)), scales)


def load_configurations(root: str | Path, scene: Scene | None = None) -> list[Configuration]:
    scene = scene or load_scene(root)
    return [load_configuration(root, g, scene.num_objects) for g in range(scene.num_configurations)]


def write_valid_region(root: str | Path, region: ValidRegion) -> None:
    atomic_write_json(
        Path(root) / "valid_region.json",
        {
            "anchor": region.anchor,
            "constraint": "s_i / s_j < ratio_bounds[i][j] for all i != j; null = unbounded",
            "ratio_bounds": _finite_or_none(region.ratio_bounds),
            "intervals": _finite_or_none(region.intervals),
        },
    )


def _inf_array(x: Any, shape: tuple[int, ...], what: str, path: Path) -> np.ndarray:
    try:
        a = np.array([[np.inf if v is None else v for v in row] for row in x], dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {what} is not a numeric matrix") from None
    if a.shape != shape:
        raise DatasetError(f"{path}: {what} has shape {a.shape}, expected {shape}")
    if np.any(np.isnan(a)):
        raise DatasetError(f"{path}: {what} contains NaN")
    return a


def load_valid_region(root: str | Path, num_objects: int | None = None) -> ValidRegion:
    path = Path(root) / "valid_region.json"
    d = read_json(path)
    B = _req(d, "ratio_bounds", "valid region", path)
    K = num_objects if num_objects is not None else len(B)
    bounds = _inf_array(B, (K, K), "ratio_bounds", path)
    intervals = _inf_array(_req(d, "intervals", "valid region", path), (K, 2), "intervals", path)
    if np.any(intervals[:, 0] > intervals[:, 1]):
        raise DatasetError(f"{path}: an interval has lo > hi")
    return ValidRegion(anchor=int(_req(d, "anchor", "valid region", path)), ratio_bounds=bounds, intervals=intervals)


def write_verification(root: str | Path, stats: dict[str, Any]) -> None:
    atomic_write_json(Path(root) / "verification.json", stats)


def load_verification(root: str | Path) -> dict[str, Any]:
    return read_json(Path(root) / "verification.json")


def write_transforms_json(root: str | Path, scene: Scene, test_config: int = 0) -> None:
    """D-NeRF/NVFi-style ``transforms_{train,test}.json`` (OpenGL/Blender camera-to-world).

    ``file_path`` has no extension, as in D-NeRF. Test views point at configuration
    ``test_config``; times are the normalised timestamps.
    """
    root = Path(root)
    fov_x = math.radians(fov_from_intrinsics(scene.intrinsics.matrix(), scene.width))
    for split, config in (("train", None), ("test", test_config)):
        frames = []
        for f in scene.split(split):
            rel = frame_paths(".", f.name, config).rgb.with_suffix("")
            frames.append(
                {
                    "file_path": "./" + rel.as_posix(),
                    "time": float(scene.timestamps[f.time_index]),
                    "transform_matrix": opengl_from_opencv(f.camera_to_world).tolist(),
                }
            )
        atomic_write_json(root / f"transforms_{split}.json", {"camera_angle_x": fov_x, "frames": frames})


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def _check_frame_files(paths: FramePaths, scene: Scene, problems: list[str]) -> None:
    try:
        rgb = read_rgb(paths.rgb)
        if p := size_problem(paths.rgb, rgb.shape[:2], scene):
            problems.append(p)
    except DatasetError as e:
        problems.append(str(e))
    ids = depth = None
    try:
        ids = read_ids(paths.ids)
        if p := size_problem(paths.ids, ids.shape, scene):
            problems.append(p)
            ids = None
        elif p := ids_problem(paths.ids, ids, scene.num_objects):
            problems.append(p)
    except DatasetError as e:
        problems.append(str(e))
    try:
        depth = read_depth(paths.depth)
        if p := size_problem(paths.depth, depth.shape, scene):
            problems.append(p)
            depth = None
        elif np.isnan(depth).any():
            problems.append(f"{paths.depth}: {int(np.isnan(depth).sum())} NaN depths")
    except DatasetError as e:
        problems.append(str(e))
    if ids is not None and depth is not None:
        hit = ids != NO_OBJECT
        bad = hit & ~(np.isfinite(depth) & (depth > 0))
        if bad.any():
            problems.append(f"{paths.depth}: {int(bad.sum())} pixels with an object have non-finite or non-positive depth")


def validate(root: str | Path, check_images: bool = True) -> list[str]:
    """Check a dataset directory against format v1; return every problem found (empty = valid).

    Each problem names the file and what is wrong: missing file, unreadable file, wrong shape or
    dtype, unknown version, ids out of range, non-finite pose, inconsistent configuration, ...
    """
    root = Path(root)
    problems: list[str] = []
    if not root.is_dir():
        return [f"{root}: not a directory"]
    try:
        scene = load_scene(root)
    except DatasetError as e:
        return [str(e)]
    K = scene.num_objects
    region = None
    try:
        region = load_valid_region(root, K)
        if region.anchor != scene.anchor_id:
            problems.append(f"{root / 'valid_region.json'}: anchor {region.anchor} differs from the manifest's {scene.anchor_id}")
    except DatasetError as e:
        problems.append(str(e))
    if check_images:
        for f in scene.train_frames:
            _check_frame_files(frame_paths(root, f.name), scene, problems)
    for g in range(scene.num_configurations):
        try:
            cfg = load_configuration(root, g, K)
        except DatasetError as e:
            problems.append(str(e))
            continue
        cfg_path = root / "configs" / config_dirname(g) / "config.json"
        if abs(cfg.scales[scene.anchor_id] - 1.0) > 1e-12:
            problems.append(f"{cfg_path}: the anchor's scale is {cfg.scales[scene.anchor_id]}, must be 1")
        if region is not None and not region.contains(cfg.scales):
            problems.append(f"{cfg_path}: scales {cfg.scales.tolist()} lie outside the valid region")
        if check_images:
            for f in scene.test_frames:
                _check_frame_files(frame_paths(root, f.name, g), scene, problems)
    return problems


def iter_frame_files(root: str | Path, scene: Scene) -> Iterable[tuple[Frame, int | None, FramePaths]]:
    """Every (frame, configuration or None, paths) the dataset should contain."""
    for f in scene.train_frames:
        yield f, None, frame_paths(root, f.name)
    for g in range(scene.num_configurations):
        for f in scene.test_frames:
            yield f, g, frame_paths(root, f.name, g)

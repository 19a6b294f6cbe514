"""Dataset JSON files and frame I/O: ``scene.json``, ``configs/GGG/config.json``,
``valid_region.json``, ``verification.json``, and whole frames (RGB + depth + ids)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write_json, read_json
from ..paths import join_inside
from ..validity import ValidRegion
from .images import read_depth, read_ids, read_rgb, write_depth, write_ids, write_rgb
from .model import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MAX_OBJECTS,
    NO_OBJECT,
    ROLES,
    SPLITS,
    Configuration,
    DatasetError,
    Frame,
    FramePaths,
    Intrinsics,
    Scene,
    SceneObject,
    config_dirname,
    frame_paths,
)

__all__ = [
    "scene_to_json", "scene_from_json", "write_scene", "load_scene", "write_frame", "read_frame",
    "read_training_video", "size_problem", "ids_problem", "write_configuration", "load_configuration",
    "load_configurations", "write_valid_region", "load_valid_region", "write_verification", "load_verification",
]


# --------------------------------------------------------------------------------------------
# scene.json
# --------------------------------------------------------------------------------------------


def scene_to_json(scene: Scene) -> dict[str, Any]:
    """The manifest as a JSON-ready dict (see docs/dataset-format.md)."""
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
        **({} if scene.near is None else {"near": scene.near, "far": scene.far}),
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


def _check_format(d: Any, path: Path) -> None:
    fmt = d.get("format") if isinstance(d, dict) else None
    if fmt != FORMAT_NAME:
        raise DatasetError(f"{path}: not an {FORMAT_NAME} manifest (format={fmt!r})")
    version = d.get("version")
    if version != FORMAT_VERSION:
        raise DatasetError(
            f"{path}: unknown format version {version!r} (this toolkit reads version {FORMAT_VERSION})"
        )


def _parse_camera(d: dict[str, Any], path: Path) -> tuple[int, int, Intrinsics]:
    image = _req(d, "image", "manifest", path)
    width, height = int(_req(image, "width", "image", path)), int(_req(image, "height", "image", path))
    if width <= 0 or height <= 0:
        raise DatasetError(f"{path}: image size {width}x{height} is not positive")
    intr = _req(d, "intrinsics", "manifest", path)
    vals = [float(_req(intr, k, "intrinsics", path)) for k in ("fx", "fy", "cx", "cy")]
    if not all(math.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
        raise DatasetError(f"{path}: intrinsics {vals} must be finite with positive focal lengths")
    return width, height, Intrinsics(*vals)


def _parse_objects(d: dict[str, Any], T: int, path: Path) -> list[SceneObject]:
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
    return objects


def _parse_frames(d: dict[str, Any], T: int, num_views: int, path: Path) -> list[Frame]:
    frames = []
    names = set()
    for i, f in enumerate(_req(d, "frames", "manifest", path)):
        name = str(_req(f, "name", f"frame {i}", path))
        join_inside(path.parent, name, f"frame {i} name", DatasetError, source=path)  # names become file names
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
    return frames


def _scene_from_json(d: dict[str, Any], path: Path) -> Scene:
    _check_format(d, path)
    width, height, intrinsics = _parse_camera(d, path)
    timestamps = np.array(_req(d, "timestamps", "manifest", path), dtype=np.float64)
    T = len(timestamps)
    if T == 0 or not np.all(np.isfinite(timestamps)):
        raise DatasetError(f"{path}: timestamps must be a non-empty list of finite numbers")
    objects = _parse_objects(d, T, path)
    num_views = int(_req(d, "num_views", "manifest", path))
    return Scene(
        width=width,
        height=height,
        intrinsics=intrinsics,
        timestamps=timestamps,
        num_views=num_views,
        frames=_parse_frames(d, T, num_views, path),
        objects=objects,
        num_configurations=int(d.get("num_configurations", 0)),
        units=str(d.get("units", "meters")),
        generator=dict(d.get("generator", {})),
        **_parse_near_far(d, path),
    )


def _parse_near_far(d: dict[str, Any], path: Path) -> dict[str, float]:
    """``near`` and ``far`` (both or neither; absent in datasets written before they existed)."""
    if "near" not in d and "far" not in d:
        return {}
    near, far = float(_req(d, "near", "manifest", path)), float(_req(d, "far", "manifest", path))
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        raise DatasetError(f"{path}: near {near} and far {far} must be finite with 0 < near < far")
    return {"near": near, "far": far}


def write_scene(root: str | Path, scene: Scene) -> None:
    """Write ``scene.json`` atomically."""
    atomic_write_json(Path(root) / "scene.json", scene_to_json(scene))


def load_scene(root: str | Path) -> Scene:
    """Read and check ``scene.json``; raise ``DatasetError`` naming the file and the problem."""
    path = Path(root) / "scene.json"
    return scene_from_json(read_json(path), path)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def write_frame(
    root: str | Path,
    frame_name: str,
    rgb: np.ndarray,
    depth: np.ndarray,
    ids: np.ndarray,
    config: int | None = None,
) -> FramePaths:
    """Write one frame's RGB ``(H,W,3)`` uint8, depth ``(H,W)`` and instance ids ``(H,W)`` uint8
    (training video if ``config`` is None)."""
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
    """One line naming ``path`` when instance ids ``(H, W)`` name no object of the manifest."""
    bad = (ids >= num_objects) & (ids != NO_OBJECT)
    if not bad.any():
        return None
    return (
        f"{path}: {int(bad.sum())} pixels have ids out of range "
        f"(found {sorted(set(np.unique(ids[bad]).tolist()))}, objects are 0..{num_objects - 1}, {NO_OBJECT} = none)"
    )


# --------------------------------------------------------------------------------------------
# Configurations, valid region, verification
# --------------------------------------------------------------------------------------------


def write_configuration(root: str | Path, config: Configuration) -> None:
    """Write ``configs/GGG/config.json`` atomically."""
    atomic_write_json(
        Path(root) / "configs" / config.dirname / "config.json",
        {"index": config.index, "scales": np.asarray(config.scales, dtype=np.float64).tolist()},
    )


def load_configuration(root: str | Path, index: int, num_objects: int | None = None) -> Configuration:
    """Read and check configuration ``index`` (``num_objects`` scales, finite and positive)."""
    path = Path(root) / "configs" / config_dirname(index) / "config.json"
    d = read_json(path)
    scales = np.array(_req(d, "scales", "configuration", path), dtype=np.float64)
    if scales.ndim != 1 or (num_objects is not None and len(scales) != num_objects):
        raise DatasetError(f"{path}: scales has shape {scales.shape}, expected ({num_objects},)")
    if not np.all(np.isfinite(scales)) or np.any(scales <= 0):
        raise DatasetError(f"{path}: scales must be finite and positive, got {scales.tolist()}")
    return Configuration(int(d.get("index", index)), scales)


def load_configurations(root: str | Path, scene: Scene | None = None) -> list[Configuration]:
    """Every configuration of the dataset, in order."""
    scene = scene or load_scene(root)
    return [load_configuration(root, g, scene.num_objects) for g in range(scene.num_configurations)]


def _finite_or_none(x: np.ndarray) -> list:
    """JSON has no infinity: +inf is stored as null."""
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in np.atleast_2d(x)]


def write_valid_region(root: str | Path, region: ValidRegion) -> None:
    """Write ``valid_region.json`` atomically (``+inf`` stored as ``null``)."""
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
    """Read and check ``valid_region.json`` (``ratio_bounds (K, K)``, ``intervals (K, 2)``)."""
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
    """Write ``verification.json`` atomically."""
    atomic_write_json(Path(root) / "verification.json", stats)


def load_verification(root: str | Path) -> dict[str, Any]:
    """Read ``verification.json``."""
    return read_json(Path(root) / "verification.json")

"""D-NeRF / nerfstudio (``dnerf-data``) interop: ``transforms_{train,val,test}.json``.

The files follow the contract both loaders read (see docs/dataset-format.md, "D-NeRF and
nerfstudio"): all three splits exist; ``file_path`` is relative, starts with ``./`` and has no
extension (the loaders append ``.png``); ``time`` is in [0, 1] and every split starts at time 0,
the training video ending at exactly 1; ``transform_matrix`` is an OpenGL camera-to-world pose;
one ``camera_angle_x`` (radians) stands for square pixels and a centred principal point;
``near`` / ``far`` repeat scene.json's depth range when it has one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write_json
from ..cameras import fov_from_intrinsics, opengl_from_opencv
from .model import DatasetError, Frame, Scene, frame_paths

__all__ = ["TRANSFORMS_SPLITS", "MAX_VAL_VIEWS", "camera_angle_x", "val_frames", "transforms_splits", "write_transforms_json"]

TRANSFORMS_SPLITS = ("train", "val", "test")
#: ``transforms_val.json`` holds at most this many test views: D-NeRF logs one of them now and
#: then and nerfstudio evaluates on them during training, so a few suffice and keep that cheap.
MAX_VAL_VIEWS = 10
#: Relative tolerance of the intrinsics that ``camera_angle_x`` can express.
_INTRINSICS_RTOL = 1e-6


def camera_angle_x(scene: Scene, root: str | Path = ".") -> float:
    """Horizontal field of view in radians, the only intrinsics D-NeRF and nerfstudio read.

    Raises ``DatasetError`` unless ``fx == fy`` and the principal point is the image centre
    (relative tolerance 1e-6): any other camera would be read silently wrong.
    """
    k, W, H = scene.intrinsics, scene.width, scene.height
    problems = []
    if abs(k.fx - k.fy) > _INTRINSICS_RTOL * k.fx:
        problems.append(f"fx = {k.fx} differs from fy = {k.fy}")
    if abs(k.cx - W / 2) > _INTRINSICS_RTOL * W or abs(k.cy - H / 2) > _INTRINSICS_RTOL * H:
        problems.append(f"principal point ({k.cx}, {k.cy}) is not the image centre ({W / 2}, {H / 2})")
    if problems:
        raise DatasetError(
            f"{Path(root) / 'transforms_*.json'}: {'; '.join(problems)}; D-NeRF and nerfstudio know only "
            "camera_angle_x (square pixels, principal point at the image centre)"
        )
    return math.radians(fov_from_intrinsics(k.matrix(), W))


def _video_order(frames: list[Frame]) -> list[Frame]:
    return sorted(frames, key=lambda f: (f.time_index, f.view))


def val_frames(test_frames: list[Frame]) -> list[Frame]:
    """Up to :data:`MAX_VAL_VIEWS` test frames evenly spaced in (time, view) order, the first kept.

    The first test frame in that order is the earliest one (time 0 in a valid export), which
    D-NeRF requires of every split.
    """
    ordered = _video_order(test_frames)
    if not ordered:
        return []
    picks = np.unique(np.linspace(0, len(ordered) - 1, min(MAX_VAL_VIEWS, len(ordered))).round().astype(int))
    return [ordered[i] for i in picks]


def transforms_splits(scene: Scene, test_config: int = 0) -> dict[str, tuple[list[Frame], int | None]]:
    """Frames (in time, view order) and the configuration their images come from, per split:
    ``train`` from the training video, ``test`` every test view of ``test_config``, ``val`` a
    subset of ``test`` (:func:`val_frames`)."""
    test = _video_order(scene.test_frames)
    return {"train": (_video_order(scene.train_frames), None), "val": (val_frames(test), test_config), "test": (test, test_config)}


def _frame_entry(scene: Scene, f: Frame, config: int | None) -> dict[str, Any]:
    rel = frame_paths(".", f.name, config).rgb.with_suffix("").as_posix()
    # nerfstudio strips every "./" from the path, D-NeRF joins it as is: only a plain path means the same to both.
    if "./" in rel or ".." in rel.split("/"):
        raise DatasetError(f"frame {f.name!r}: its path {rel!r} would be read differently by D-NeRF and nerfstudio")
    return {
        "file_path": "./" + rel,
        "time": float(scene.timestamps[f.time_index]),
        "transform_matrix": opengl_from_opencv(f.camera_to_world).tolist(),
    }


def _check_times(path: Path, split: str, times: list[float], num_timestamps: int) -> None:
    """D-NeRF asserts that every split starts at time 0 and that training runs from 0 to exactly 1."""
    if not times:
        raise DatasetError(f"{path}: no frames; D-NeRF and nerfstudio need train, val and test")
    if not all(0.0 <= t <= 1.0 for t in times):
        raise DatasetError(f"{path}: times must lie in [0, 1], got {min(times)}..{max(times)}")
    if times[0] != 0.0:
        raise DatasetError(f"{path}: the first frame is at time {times[0]}; D-NeRF requires every split to start at 0")
    if split != "train":
        return
    if any(b < a for a, b in zip(times, times[1:])):
        raise DatasetError(f"{path}: training times decrease; the training video must be in time order")
    if times[-1] != 1.0:
        raise DatasetError(
            f"{path}: the training video ends at time {times[-1]}; D-NeRF requires it to end at exactly 1 "
            f"(the scene has {num_timestamps} timestamp(s); at least 2 are needed)"
        )


def write_transforms_json(root: str | Path, scene: Scene, test_config: int = 0) -> None:
    """Write ``transforms_{train,val,test}.json`` for D-NeRF and nerfstudio's ``dnerf-data``.

    Test and val views point at configuration ``test_config``. Every split is built and checked
    (:func:`camera_angle_x`, times) before any file is written; a scene the loaders would reject
    or misread (one timestamp, off-centre principal point, ...) raises ``DatasetError``.
    """
    root = Path(root)
    fov_x = camera_angle_x(scene, root)
    # Neither D-NeRF nor nerfstudio reads near / far from here: they are for the user to pass on
    # (docs/predictions.md); datasets written before they existed have none.
    near_far = {} if scene.near is None else {"near": scene.near, "far": scene.far}
    docs = {}
    for split, (frames, config) in transforms_splits(scene, test_config).items():
        entries = [_frame_entry(scene, f, config) for f in frames]
        path = root / f"transforms_{split}.json"
        _check_times(path, split, [e["time"] for e in entries], len(scene.timestamps))
        docs[path] = {"camera_angle_x": fov_x, **near_far, "frames": entries}
    for path, doc in docs.items():
        atomic_write_json(path, doc)

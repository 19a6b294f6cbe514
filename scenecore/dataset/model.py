"""Dataset format v1: constants, typed objects and the file layout (numpy only)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import intrinsics_matrix, scale_about
from ..errors import DatasetError
from ..paths import join_inside

__all__ = [
    "FORMAT_NAME", "FORMAT_VERSION", "NO_OBJECT", "MAX_OBJECTS", "SPLITS", "ROLES", "DatasetError",
    "Intrinsics", "Frame", "SceneObject", "Scene", "Configuration", "FramePaths", "config_dirname", "frame_paths",
]

FORMAT_NAME = "osn-dataset"
FORMAT_VERSION = 1
#: Instance-id value of pixels where no object is hit.
NO_OBJECT = 255
MAX_OBJECTS = 255
SPLITS = ("train", "test")
ROLES = ("anchor", "object")


@dataclass
class Intrinsics:
    """Pixel-unit pinhole intrinsics (pixel centres at ``.5``, see :mod:`scenecore.cameras`)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        """The ``(3, 3)`` intrinsics matrix."""
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    @classmethod
    def from_matrix(cls, K: np.ndarray) -> "Intrinsics":
        """From a ``(3, 3)`` intrinsics matrix."""
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
    #: Depth range of every ground-truth frame with a margin (``depth_range``), for methods that
    #: sample rays between near and far planes; None in datasets written before it existed.
    near: float | None = None
    far: float | None = None

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def anchor_id(self) -> int:
        return next(o.id for o in self.objects if o.role == "anchor")

    def split(self, split: str) -> list[Frame]:
        """The frames of one split (``train`` or ``test``), in manifest order."""
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
    """The three files of one frame."""

    rgb: Path
    depth: Path
    ids: Path

    def all(self) -> tuple[Path, Path, Path]:
        return (self.rgb, self.depth, self.ids)

    def exist(self) -> bool:
        return all(p.exists() for p in self.all())


def config_dirname(index: int) -> str:
    """Directory name of configuration ``index`` under ``configs/`` (``000``, ``001``, ...)."""
    return f"{index:03d}"


def frame_paths(root: str | Path, frame_name: str, config: int | None = None) -> FramePaths:
    """Paths of a frame's files: the training video when ``config`` is None, else a config's view.

    Raises ``DatasetError`` for a frame name that would lead outside the dataset (absolute, ``..``):
    every read and write of a frame goes through here."""
    base = Path(root) / ("train" if config is None else Path("configs") / config_dirname(config))
    join_inside(base, frame_name, "frame name", DatasetError)
    return FramePaths(
        rgb=base / "rgb" / f"{frame_name}.png",
        depth=base / "depth" / f"{frame_name}.exr",
        ids=base / "ids" / f"{frame_name}.png",
    )

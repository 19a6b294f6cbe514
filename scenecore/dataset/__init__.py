"""Dataset format v1: reading, writing and validating (numpy only; never imports bpy or torch).

This package is the single owner of the on-disk layout specified in ``docs/dataset-format.md``.
benchgen writes through it, osn reads through it, and ``validate`` checks a directory against it.
``from scenecore import dataset as D`` gives the whole API; the modules are:

* ``model``: constants, ``DatasetError``, the typed ``Scene`` / ``Frame`` / ``Configuration``, file paths;
* ``images``: RGBA / instance-id PNGs and planar-depth EXRs;
* ``manifest``: ``scene.json``, configurations, valid region, verification, whole frames;
* ``transforms``: D-NeRF / nerfstudio ``transforms_{train,val,test}.json``;
* ``depth_range``: the scene's ``near`` / ``far`` (every ground-truth depth, with a margin);
* ``covisibility``: each configuration's stored co-visibility masks (``covisibility.npz``);
* ``validation``: ``validate``, the format checker;
* atomic writes come from :mod:`scenecore.atomic` (re-exported here).

Layout::

    DATASET/
      scene.json                       manifest (format, version, camera, frames, objects)
      train/{rgb,depth,ids}/NAME.*     the monocular training video (shared by every configuration)
      configs/GGG/config.json          scale vector of ground-truth configuration GGG
      configs/GGG/{rgb,depth,ids}/NAME.*   its test views
      configs/GGG/covisibility.npz     its test views' co-visibility masks, bit-packed (optional)
      valid_region.json                exact valid-scale region
      verification.json                invariance statistics (optional until generation ends)
      transforms_{train,val,test}.json D-NeRF / nerfstudio views (written at the end of generation)

Every write is atomic: a temporary file in the same directory, then ``os.replace``.
"""

from ..atomic import atomic_path, atomic_write_bytes, atomic_write_json, publish_mode, read_json
from .images import (
    MAX_IMAGE_PIXELS, encode_png, exr_size, read_depth, read_ids, read_image, read_regular, read_rgb, rgb_from_image,
    write_depth, write_ids, write_rgb,
)
from .manifest import (
    ids_problem, load_configuration, load_configurations, load_scene, load_valid_region, load_verification, read_frame,
    read_training_video, scene_from_json, scene_to_json, size_problem, write_configuration, write_frame, write_scene,
    write_valid_region, write_verification,
)
from .model import (
    FORMAT_NAME, FORMAT_VERSION, MAX_OBJECTS, NO_OBJECT, ROLES, SPLITS, Configuration, DatasetError, Frame, FramePaths,
    Intrinsics, Scene, SceneObject, config_dirname, frame_paths,
)
from .transforms import MAX_VAL_VIEWS, TRANSFORMS_SPLITS, camera_angle_x, transforms_splits, val_frames, write_transforms_json
from .validation import iter_frame_files, validate
from .covisibility import (
    COVISIBILITY_FILE, CovisibilityMasks, covisibility_frames, covisibility_path, read_covisibility, write_covisibility,
)
from .depth_range import depth_range, with_depth_range

__all__ = [
    "atomic_path", "atomic_write_bytes", "atomic_write_json", "publish_mode", "read_json",
    "MAX_IMAGE_PIXELS", "encode_png", "exr_size", "read_depth", "read_ids", "read_image", "read_regular", "read_rgb",
    "rgb_from_image", "write_depth", "write_ids", "write_rgb",
    "ids_problem", "load_configuration", "load_configurations", "load_scene", "load_valid_region", "load_verification",
    "read_frame", "read_training_video", "scene_from_json", "scene_to_json", "size_problem", "write_configuration",
    "write_frame", "write_scene", "write_valid_region", "write_verification",
    "FORMAT_NAME", "FORMAT_VERSION", "MAX_OBJECTS", "NO_OBJECT", "ROLES", "SPLITS", "Configuration", "DatasetError",
    "Frame", "FramePaths", "Intrinsics", "Scene", "SceneObject", "config_dirname", "frame_paths",
    "MAX_VAL_VIEWS", "TRANSFORMS_SPLITS", "camera_angle_x", "transforms_splits", "val_frames", "write_transforms_json",
    "iter_frame_files", "validate",
    "COVISIBILITY_FILE", "CovisibilityMasks", "covisibility_frames", "covisibility_path", "read_covisibility",
    "write_covisibility", "depth_range", "with_depth_range",
]

"""``osn oracle``: per-object inputs from a benchgen dataset's ground truth (what perfect SfM would give).

The oracle reads the dataset's camera and object poses, planar depths and instance masks, and
writes exactly the quantities per-object SfM would estimate (poses and sparse depths in each
object's own unit, :mod:`osn.preprocess.inputs`), normalised by the same
:func:`~osn.preprocess.inputs.object_inputs_from_observations`. Training on it separates learning
errors from SfM errors. Unlike SfM it knows every object's unit (``unit_to_world``) and the
world-to-anchor similarity, which evaluation needs to place test cameras.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenecore import dataset as D
from scenecore.cameras import invert_pose
from scenecore.config import integer, validate
from osn.preprocess.inputs import (
    BOX_PADDING,
    NORMALISATION_RULES,
    SCENE_FAR_FACTOR,
    SCENE_NEAR_FACTOR,
    InputsError,
    ObjectInputs,
    SceneInputs,
    auto_points_per_frame,
    check_inputs,
    object_inputs_from_observations,
    scene_volume,
)


@dataclass
class OracleConfig:
    """Options of the oracle preprocessing.

    Attributes:
        points_per_frame: sparse depths kept per object and frame; 0 = :func:`auto_points_per_frame`
            (grows with the frame's pixels, as SfM's features do).
        min_pixels: an object is used in a frame only if it covers at least this many pixels.
        scene_near_factor, scene_far_factor: the scene volume is
            ``[factor_near * min_k near_k, factor_far * max_k far_k]`` in object units (Eq. 1);
            ``0 < near < 1 <= far``.
        box_padding: relative padding of each object's canonical box around its points.
        seed: random seed of the sparse subsampling.
    """

    points_per_frame: int = 0
    min_pixels: int = 16
    scene_near_factor: float = SCENE_NEAR_FACTOR
    scene_far_factor: float = SCENE_FAR_FACTOR
    box_padding: float = BOX_PADDING
    seed: int = 0

    def __post_init__(self) -> None:
        validate(self, "oracle", {
            "points_per_frame": integer(0),
            "min_pixels": integer(1),
            **NORMALISATION_RULES,
            "seed": integer(0),
        })


def oracle_inputs(
    dataset_root: str | Path,
    cfg: OracleConfig | None = None,
    video: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> SceneInputs:
    """Derive per-object inputs from a benchgen dataset's ground truth (see module docstring).

    ``video``: the dataset's :func:`scenecore.dataset.read_training_video`, when the caller has
    read it already (it is read here otherwise).
    """
    cfg = cfg or OracleConfig()
    root = Path(dataset_root)
    scene = D.load_scene(root)
    rng = np.random.default_rng(cfg.seed)
    train = sorted(scene.train_frames, key=lambda f: f.time_index)
    images_a, depths_a, masks_a = video if video is not None else D.read_training_video(root, scene)  # names bad files
    K = scene.intrinsics.matrix()
    c2w = np.stack([f.camera_to_world for f in train])
    # One generator over the objects in order: each object's subsample depends on those before.
    objects = [_oracle_object(root, scene, obj, depths_a, masks_a, c2w, K, cfg, rng) for obj in scene.objects]
    scene_near, scene_far = scene_volume(objects, cfg.scene_near_factor, cfg.scene_far_factor)
    inputs = SceneInputs(
        width=scene.width,
        height=scene.height,
        K=K,
        timestamps=scene.timestamps.copy(),
        images=images_a,
        masks=masks_a,
        objects=objects,
        anchor=scene.anchor_id,
        scene_near=scene_near,
        scene_far=scene_far,
        world_to_anchor=_world_to_anchor(scene, objects[scene.anchor_id], c2w),
        source="oracle",
        meta={"dataset": str(root), "oracle": cfg.__dict__},
    )
    check_inputs(inputs, root)
    return inputs


def _oracle_object(
    root: Path, scene: D.Scene, obj: D.SceneObject, depths: np.ndarray, masks: np.ndarray, c2w: np.ndarray,
    K: np.ndarray, cfg: OracleConfig, rng: np.random.Generator,
) -> ObjectInputs:
    """One object's inputs from ground truth: ``depths (T, H, W)`` metres, ``masks (T, H, W)`` ids,
    ``c2w (T, 4, 4)`` training cameras; ``cfg.points_per_frame`` random pixels per frame."""
    T = len(scene.timestamps)
    frames = [t for t in range(T) if (masks[t] == obj.id).sum() >= cfg.min_pixels]
    if not frames:
        raise InputsError(f"{root}: object {obj.id} ({obj.name}) covers fewer than {cfg.min_pixels} pixels in every training frame")
    pix_l, dep_l = [], []
    for t in frames:
        v, u = np.nonzero(masks[t] == obj.id)
        n = min(cfg.points_per_frame or auto_points_per_frame(scene.width, scene.height), len(u))
        pick = np.sort(rng.choice(len(u), size=n, replace=False))
        pix_l.append(np.stack([u[pick], v[pick]], axis=1).astype(np.int64))
        dep_l.append(depths[t][v[pick], u[pick]].astype(np.float64))
    # Object frame = camera of the first frame (the object's body frame seen from there).
    obj_from_world = [invert_pose(obj.poses[t]) for t in frames]
    cam_to_body = np.stack([ofw @ c2w[t] for t, ofw in zip(frames, obj_from_world)])
    return object_inputs_from_observations(
        obj.id, obj.name, np.array(frames), cam_to_body, pix_l, dep_l, [np.ones(len(d)) for d in dep_l],
        K, scene.width, scene.height, cfg.box_padding, metres_per_unit=1.0,
    )


def _world_to_anchor(scene: D.Scene, anchor: ObjectInputs, c2w: np.ndarray) -> np.ndarray:
    """``(4, 4)`` similarity from dataset world to anchor coordinates (the anchor is static in
    benchgen scenes): world -> the anchor's body -> the camera of its first frame, in its unit."""
    a_obj = scene.objects[scene.anchor_id]
    t0 = int(anchor.frames[0])
    w2a = invert_pose(invert_pose(a_obj.poses[t0]) @ c2w[t0]) @ invert_pose(a_obj.poses[t0])
    S = np.diag([1 / anchor.unit_to_world] * 3 + [1.0])
    return S @ w2a

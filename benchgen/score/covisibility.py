"""Co-visibility of test pixels with the training video (docs/metrics.md, "Co-visibility mask").

A test pixel is evaluated only when a training frame of the same configuration saw its surface
point; objects move between frames, so each point moves with its object. Pure numpy geometry on
the dataset's conventions (:mod:`scenecore.cameras`); :mod:`benchgen.score.truth` builds every
ground truth's masks with it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from scenecore import dataset as D
from scenecore.cameras import invert_pose, pixel_rays, project
from scenecore.dataset import NO_OBJECT, Scene

#: Relative depth tolerance of the occlusion test (:func:`covisibility_mask`'s ``rtol``).
DEPTH_RTOL = 0.03
#: Version of the mask rule: stored masks (``configs/GGG/covisibility.npz``) computed under
#: another version or tolerance are not used by ``benchgen score``. Bump it when the rule changes.
RULE_VERSION = 1


def covisibility_mask(
    depth: np.ndarray,
    K: np.ndarray,
    c2w: np.ndarray,
    train_depths: Sequence[np.ndarray] | np.ndarray,
    train_K: np.ndarray,
    train_c2w: np.ndarray,
    object_ids: np.ndarray | None = None,
    object_transforms: np.ndarray | None = None,
    rtol: float = DEPTH_RTOL,
) -> np.ndarray:
    """Boolean ``(H, W)``: test pixels whose surface point some training frame saw.

    A test pixel's 3D point (from its ground-truth planar ``depth``, intrinsics ``K`` and OpenCV
    pose ``c2w``) is co-visible when, for some training frame i, it projects in front of the camera
    inside the image and its depth agrees with that frame's depth at the nearest pixel within
    ``rtol`` (relative), i.e. it is not occluded there. Pixels with no finite depth are not
    co-visible (nothing shows that they were observed).

    Moving objects: with ``object_ids`` ``(H, W)`` (the test view's ids) and ``object_transforms``
    ``(T, K_obj, 4, 4)`` mapping each object's points from the test time's world into training
    frame i's world (:func:`covisibility_transforms`), each point moves with its object. Without
    them the scene is taken as static. ``train_depths`` ``(T, H', W')`` must be the training depth
    *of the same configuration* as the test view (:func:`configured_depth`); ``train_K`` is
    ``(3, 3)`` or ``(T, 3, 3)``, ``train_c2w`` is ``(T, 4, 4)``.
    """
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    train_c2w = np.asarray(train_c2w, dtype=np.float64).reshape(-1, 4, 4)
    T = len(train_c2w)
    train_K = np.broadcast_to(np.asarray(train_K, dtype=np.float64), (T, 3, 3))
    if len(train_depths) != T:
        raise ValueError(f"{len(train_depths)} training depth maps for {T} training cameras")
    if (object_ids is None) != (object_transforms is None):
        raise ValueError("object_ids and object_transforms go together (both or neither)")
    origins, dirs = pixel_rays(K, c2w, W, H)
    z = depth.reshape(-1)
    hit = np.isfinite(z) & (z > 0)
    points = origins[hit] + z[hit, None] * dirs[hit]
    if object_ids is not None:
        ids = np.asarray(object_ids).reshape(-1)[hit].astype(np.int64)
        object_transforms = np.asarray(object_transforms, dtype=np.float64)
        if object_transforms.shape[:1] != (T,) or object_transforms.shape[2:] != (4, 4):
            raise ValueError(f"object_transforms must be ({T}, K, 4, 4), got {object_transforms.shape}")
        if ids.size and (ids.min() < 0 or ids.max() >= object_transforms.shape[1]):
            raise ValueError("a pixel with finite depth has no valid object id")
    # A point is co-visible when any frame saw it, so each frame checks only the points no frame
    # before it saw (most points are seen in the first frames); each object's points move with
    # one matrix per frame.
    seen = np.zeros(points.shape[0], dtype=bool)
    todo = np.arange(points.shape[0])
    for i in range(T):
        if todo.size == 0:
            break
        p = points[todo]
        if object_ids is not None:
            p = move_with_objects(p, ids[todo], object_transforms[i])
        _, ok = seen_in_frame(p, train_K[i], train_c2w[i], train_depths[i], rtol)
        seen[todo[ok]] = True
        todo = todo[~ok]
    out = np.zeros(H * W, dtype=bool)
    out[hit] = seen
    return out.reshape(H, W)


def move_with_objects(points: np.ndarray, ids: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """World points ``(N, 3)`` of objects ``ids (N,)`` moved by their object's ``transforms[k]``
    ``(K, 4, 4)`` (one frame of :func:`covisibility_transforms`); a new array."""
    out = np.array(points, dtype=np.float64, copy=True)
    for k in np.unique(ids):
        rows = np.flatnonzero(ids == k)
        A = transforms[k]
        out[rows] = out[rows] @ A[:3, :3].T + A[:3, 3]
    return out


def seen_in_frame(
    points: np.ndarray, K: np.ndarray, c2w: np.ndarray, depth: np.ndarray, rtol: float = DEPTH_RTOL
) -> tuple[np.ndarray, np.ndarray]:
    """Where a frame sees world ``points (N, 3)``: their pixel coordinates ``uv (N, 2)`` (centres at
    .5) and ``seen (N,)``, True where a point projects in front of the camera inside the image and
    agrees within ``rtol`` (relative) with the frame's planar ``depth (H, W)`` at the nearest pixel
    (it is not occluded there)."""
    uv, z = project(points, K, c2w)
    dmap = np.asarray(depth, dtype=np.float64)
    h, w = dmap.shape
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    u = np.clip(np.floor(uv[:, 0]), 0, w - 1).astype(np.int64)
    v = np.clip(np.floor(uv[:, 1]), 0, h - 1).astype(np.int64)
    d = dmap[v, u]
    with np.errstate(invalid="ignore"):  # inf - inf where the frame's pixel hit nothing
        seen = inside & np.isfinite(d) & (np.abs(z - d) <= rtol * d)
    return uv, seen


def configured_depth(base_depth: np.ndarray, ids: np.ndarray, scales: Sequence[float]) -> np.ndarray:
    """Training depth of a configuration from the stored base (all scales 1) training depth.

    Scaling object k by ``s_k`` about the training camera centre multiplies its depth along
    every training ray by ``s_k``; pixels with id ``NO_OBJECT`` keep their (infinite) depth.
    """
    ids = np.asarray(ids)
    factor = np.ones(ids.shape)
    hit = ids != NO_OBJECT
    factor[hit] = np.asarray(scales, dtype=np.float64)[ids[hit]]
    return np.asarray(base_depth, dtype=np.float64) * factor


def covisibility_transforms(scene: Scene, scales: Sequence[float], test_time: int, poses: np.ndarray | None = None) -> np.ndarray:
    """``(T, K, 4, 4)``: object k's map from the test time's world to training time t's world.

    In a configuration, object k at time t has pose ``P_k(t) = scene.configured_pose(k, t, s_k)``
    (scaled about the training camera centre of t), so a point x on k at the test time is at
    ``P_k(t) P_k(test_time)^-1 x`` at time t. Index t is the time index, so pass the training
    frames to :func:`covisibility_mask` sorted by time. ``poses``: :func:`configuration_poses` of
    the same configuration, when it is already at hand.
    """
    poses = configuration_poses(scene, scales) if poses is None else poses
    T, K = poses.shape[:2]
    out = np.empty((T, K, 4, 4))
    for k in range(K):
        inv_test = invert_pose(poses[test_time, k])
        for t in range(T):
            out[t, k] = poses[t, k] @ inv_test
    return out


def configuration_poses(scene: Scene, scales: Sequence[float]) -> np.ndarray:
    """``(T, K, 4, 4)``: every object's pose at every time index in a configuration
    (``scene.configured_pose``), for :func:`covisibility_transforms` of many test times."""
    T, K = len(scene.timestamps), scene.num_objects
    return np.array([[scene.configured_pose(k, t, scales[k]) for k in range(K)] for t in range(T)]).reshape(T, K, 4, 4)


def configuration_masks(
    scene: Scene, scales: np.ndarray, frames: Sequence[D.Frame], depth: np.ndarray, ids: np.ndarray,
    train_depth: np.ndarray, train_ids: np.ndarray,
) -> np.ndarray:
    """Co-visibility masks ``(V, H, W)`` bool of one configuration's views ``frames``.

    ``depth``/``ids`` ``(V, H, W)`` are the configuration's ground truth on those views;
    ``train_depth``/``train_ids`` ``(T, H, W)`` the stored (base) training video in time order.
    Each test pixel's surface point moves with its object to every training time and is
    co-visible when a training frame of this configuration saw it (:func:`covisibility_mask`).
    """
    K = scene.intrinsics.matrix()
    t_c2w = np.stack([f.camera_to_world for f in sorted(scene.train_frames, key=lambda f: f.time_index)])
    t_depths = [configured_depth(d, i, scales) for d, i in zip(train_depth, train_ids)]
    transforms: dict[int, np.ndarray] = {}  # per test time: they depend on the time only
    poses = configuration_poses(scene, scales)
    out = np.zeros(depth.shape, bool)
    for v, f in enumerate(frames):
        if f.time_index not in transforms:
            transforms[f.time_index] = covisibility_transforms(scene, scales, f.time_index, poses)
        out[v] = covisibility_mask(
            depth[v], K, f.camera_to_world, t_depths, K, t_c2w,
            object_ids=np.where(ids[v] == NO_OBJECT, 0, ids[v]), object_transforms=transforms[f.time_index],
        )
    return out

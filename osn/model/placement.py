"""Placing objects for a configuration seen from any camera at a training timestamp.

A configuration with de-normalised scales ``sbar`` scales object k about the training camera
centre of each timestamp. Seen from a *novel* camera at timestamp t, a point ``x`` in that
camera's frame (scene units = the anchor's unit) lies in object k at

    cam_to_obj_k[t] @ ( (traincam_t <- novel) x / sbar_k )

where ``traincam_t <- novel`` is the rigid transform from the novel camera to the training camera
of time t, both in scene units. Test cameras given in dataset world coordinates reach the anchor's
frame through ``SceneInputs.world_to_anchor`` (a similarity fitted on the training cameras, or the
oracle's exact one); the anchor's training poses then give ``traincam_t <- novel``.
"""

from __future__ import annotations

import numpy as np

from scenecore.cameras import invert_pose
from osn.preprocess.inputs import InputsError, SceneInputs


def split_similarity(S: np.ndarray) -> tuple[float, np.ndarray]:
    """Split a ``(4, 4)`` similarity ``[s R | t]`` into ``s`` and the ``(4, 4)`` rigid ``[R | t]``."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    if not np.isfinite(s) or s <= 0:
        raise InputsError(f"not a proper similarity (det = {np.linalg.det(S[:3, :3]):.3g})")
    R = np.eye(4)
    R[:3, :3] = S[:3, :3] / s
    R[:3, 3] = S[:3, 3]
    return s, R


def novel_to_training_camera(inputs: SceneInputs, camera_to_world: np.ndarray, time_index: int) -> np.ndarray:
    """Rigid ``(4, 4)`` transform (scene units) from a world-space OpenCV camera ``camera_to_world
    (4, 4)`` to the training camera at ``time_index``.

    Camera coordinates in metres become scene units by the similarity's scale; the result maps
    scene-unit novel-camera coordinates to scene-unit training-camera coordinates.
    """
    if inputs.world_to_anchor is None:
        raise InputsError("these inputs have no world-to-anchor alignment; novel cameras cannot be placed")
    anchor = inputs.object(inputs.anchor)
    slot = anchor.frame_slot(time_index)
    if slot is None:
        raise InputsError(f"the anchor has no pose at timestamp {time_index}")
    scale, _ = split_similarity(inputs.world_to_anchor)
    # novel camera (metres) -> anchor frame (anchor units); rescale the camera side to scene units.
    A = inputs.world_to_anchor @ np.asarray(camera_to_world, dtype=np.float64)
    A[:3, :3] /= scale
    return invert_pose(anchor.cam_to_obj[slot]) @ A


def object_transforms(
    inputs: SceneInputs, cam_to_traincam: np.ndarray, time_index: int, sbar: np.ndarray
) -> dict[int, np.ndarray]:
    """``(4, 4)`` similarity per object present at ``time_index``: camera point (scene units) -> object.

    ``cam_to_traincam (4, 4)`` is :func:`novel_to_training_camera`'s result; ``sbar (K,)``.

    ``sbar`` and the returned keys index objects by *position* in ``inputs.objects`` (as every
    scale vector in osn does; positions equal ids unless preprocessing dropped an object).
    Scaling is about the training camera centre, so the division by ``sbar_k`` happens in
    training-camera coordinates: ``cam_to_obj_k[t] @ diag(1/sbar_k) @ cam_to_traincam``.
    Objects without a pose at ``time_index`` are absent from the result (they are not seen then).
    """
    out: dict[int, np.ndarray] = {}
    for k, o in enumerate(inputs.objects):
        slot = o.frame_slot(time_index)
        if slot is None:
            continue
        s = float(sbar[k])
        if not (np.isfinite(s) and s > 0):
            raise InputsError(f"scale of object {o.id} ({o.name}) must be finite and positive, got {s}")
        out[k] = o.cam_to_obj[slot] @ np.diag([1.0 / s] * 3 + [1.0]) @ cam_to_traincam
    return out

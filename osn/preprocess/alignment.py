"""SfM against a benchgen dataset's ground truth: accuracy figures, object units, test-view alignment.

This is the only preprocessing code that reads ground truth (object poses, rendered depth), and
only *after* SfM, for two purposes: to report how accurate the reconstruction is (rotation and
camera-centre errors per object), and to give each object's SfM unit a size in metres
(:func:`depth_unit`) and the anchor a world-to-anchor similarity, which scoring needs (relative
scale error, valid-set accuracy, placing test cameras). Training never uses either.
"""

from __future__ import annotations

import logging

import numpy as np

from scenecore import dataset as D
from scenecore.cameras import fit_pose_similarity, invert_pose, rotation_angle_deg
from osn.preprocess.inputs import ObjectInputs, SceneInputs
from osn.preprocess.sfm import PreprocessReport

log = logging.getLogger(__name__)


def align_to_ground_truth(
    inputs: SceneInputs, report: PreprocessReport, scene: D.Scene, depths: np.ndarray, masks: np.ndarray
) -> None:
    """Fill units, world-to-anchor and accuracy figures from ground truth.

    ``depths (T, H, W)`` is the rendered ground-truth planar depth and ``masks (T, H, W)`` the
    instance ids of the training video. Each object's metres per SfM unit is the median of the
    depth over SfM depth at its sparse points (:func:`depth_unit`). A similarity per object maps
    the SfM camera poses (object frame) onto the ground-truth ones
    (:func:`scenecore.cameras.fit_pose_similarity`); rotation and camera-centre errors are
    measured after it. Its scale is not used as the unit: least squares on noisy camera centres
    shrinks it (on the tests' 128 px scene the block's came out well under half the truth, which
    skews every scale-based evaluation figure); its ratio to the depth unit is reported
    (``similarity_unit_ratio``). An object whose similarity cannot be fitted still gets its unit.
    """
    bridged = inputs.meta.get("bridged_frames", {})
    for o, rep in zip(inputs.objects, [r for r in report.objects if "error" not in r]):
        o.unit_to_world = depth_unit(o, depths)
        if o.unit_to_world is None:
            rep["unit"] = "not measurable: no sparse point has a finite ground-truth depth"
        else:
            rep["sparse_depths_off_10pct"] = sparse_depth_outliers(o, depths)
        try:
            rep.update(pose_accuracy(o, *true_camera_poses(scene, masks, o.id), bridged.get(str(o.id), ())))
        except ValueError as e:
            rep["alignment"] = f"not measurable: {e}"
    _align_test_views(inputs, report, scene)


def true_camera_poses(scene: D.Scene, masks: np.ndarray, object_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth of one object: the time indices ``(F,)`` where it covers a pixel of
    ``masks (T, H, W)``, and the training cameras' poses in its body frame ``(F, 4, 4)``, metres."""
    obj = next(o for o in scene.objects if o.id == object_id)
    c2w = {f.time_index: f.camera_to_world for f in scene.train_frames}
    frames = np.array([t for t in range(len(masks)) if np.any(masks[t] == object_id)], dtype=np.int64)
    poses = [invert_pose(obj.poses[t]) @ c2w[int(t)] for t in frames]
    return frames, np.stack(poses) if poses else np.zeros((0, 4, 4))


def pose_accuracy(o: ObjectInputs, gt_frames: np.ndarray, gt_cam_to_obj: np.ndarray,
                  bridged: list[int] | tuple = ()) -> dict[str, float]:
    """Errors of the SfM poses of ``o`` after the similarity that best maps them onto the ground
    truth ``gt_cam_to_obj (F, 4, 4)`` (metres) at ``gt_frames (F,)``; raises ``ValueError`` when
    that similarity cannot be fitted. The frames ``bridged`` (:mod:`osn.preprocess.bridge`) are
    left out of the fit and of the registered frames' figures, and measured apart
    (``bridged_*``) under the same similarity."""
    slot = {int(t): i for i, t in enumerate(gt_frames)}
    extra = {int(t) for t in bridged}
    keep = [i for i, t in enumerate(o.frames) if int(t) in slot and int(t) not in extra]
    gt_poses = gt_cam_to_obj[[slot[int(o.frames[i])] for i in keep]]
    S = fit_pose_similarity(o.cam_to_obj[keep], gt_poses)
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R = S[:3, :3] / scale

    def errors(idx: list[int]) -> tuple[list[float], np.ndarray]:
        gt = gt_cam_to_obj[[slot[int(o.frames[i])] for i in idx]]
        rot = [rotation_angle_deg(R @ o.cam_to_obj[i, :3, :3], g[:3, :3]) for i, g in zip(idx, gt)]
        aligned = o.cam_to_obj[idx, :3, 3] @ S[:3, :3].T + S[:3, 3]
        return rot, np.linalg.norm(aligned - gt[:, :3, 3], axis=1)  # metres

    out = {}
    if o.unit_to_world is not None:
        out["similarity_unit_ratio"] = scale / o.unit_to_world
    rot, err = errors(keep)
    out.update(
        gt_visible_frames=len(gt_frames),
        registered_fraction=(len(o.frames) - len(extra)) / max(len(gt_frames), 1),
        rotation_error_deg_max=float(max(rot)),
        rotation_error_deg_mean=float(np.mean(rot)),
        center_error_m_mean=float(err.mean()),
        center_error_m_max=float(err.max()),
    )
    extra_idx = [i for i, t in enumerate(o.frames) if int(t) in slot and int(t) in extra]
    if extra_idx:
        rot, err = errors(extra_idx)
        out.update(bridged_rotation_error_deg_max=float(max(rot)), bridged_rotation_error_deg_mean=float(np.mean(rot)),
                   bridged_center_error_m_mean=float(err.mean()), bridged_center_error_m_max=float(err.max()))
    return out


def _align_test_views(inputs: SceneInputs, report: PreprocessReport, scene: D.Scene) -> None:
    """Set ``inputs.world_to_anchor``: the similarity taking the ground-truth training cameras
    (world) onto the anchor's SfM cameras, so evaluation can bring test cameras into the anchor's
    frame. On failure it stays None and the anchor's report entry says why."""
    anchor = inputs.object(inputs.anchor)
    c2w = {f.time_index: f.camera_to_world for f in scene.train_frames}
    try:
        inputs.world_to_anchor = fit_pose_similarity(np.stack([c2w[int(t)] for t in anchor.frames]), anchor.cam_to_obj)
    except ValueError as e:  # the inputs still train; evaluation says why it cannot place test views
        log.warning("test-view alignment failed for the anchor %s: %s", anchor.name, e)
        inputs.world_to_anchor = None
        for rep in report.objects:
            if rep.get("id") == anchor.id:
                rep["test_view_alignment"] = f"failed: {e}"


def _truth_over_sparse(obj: ObjectInputs, depths: np.ndarray) -> np.ndarray:
    """Ground-truth planar depth over the object's sparse depth at each sparse pixel (usable ones)."""
    ratio = np.concatenate([
        depths[int(t)][pix[:, 1], pix[:, 0]] / dep for t, pix, dep in zip(obj.frames, obj.sparse_pix, obj.sparse_depth)
    ] or [np.zeros(0)])
    return ratio[np.isfinite(ratio) & (ratio > 0)]


def depth_unit(obj: ObjectInputs, depths: np.ndarray) -> float | None:
    """Metres per unit of ``obj``: the median of ground-truth planar depth ``depths (T, H, W)``
    over the object's sparse depths at the same pixels (None without a usable point)."""
    ratio = _truth_over_sparse(obj, depths)
    return float(np.median(ratio)) if len(ratio) else None


def sparse_depth_outliers(obj: ObjectInputs, depths: np.ndarray, tolerance: float = 0.1) -> float | None:
    """Share of the object's sparse depths more than ``tolerance`` (relative) off the ground truth
    once in metres (``obj.unit_to_world``): SfM's phantom points, e.g. on the gnome-house room's
    checker floor (docs/preprocess.md). None without a unit or a point."""
    ratio = _truth_over_sparse(obj, depths)
    if obj.unit_to_world is None or not len(ratio):
        return None
    return float(np.mean(np.abs(obj.unit_to_world / ratio - 1.0) > tolerance))

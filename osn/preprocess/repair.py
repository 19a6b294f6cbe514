"""Registered frames whose SfM pose contradicts their own verified matches: find, re-pose or drop.

COLMAP's mapper can leave a frame at a pose that almost none of its two-view-verified matches
agree with (seen on gnome-house at 1024 px: one of the room's frames far off, almost none of
its verified matches near the model's epipolar geometry while every other frame kept most of
its own). One such pose is worse than a missing one: it also tilts every similarity fitted to
the trajectory, so evaluation reads the object's other frames off too.

The check needs no ground truth: for every pair of registered frames with verified matches, the
Sampson distance of each match under the *model's* relative pose. A frame whose matches mostly
disagree is re-posed by RANSAC PnP from the 3D points its verified matches reach through frames
that pass the check, its observations replaced by the PnP inliers and the model bundle-adjusted;
if that fails too, the frame is dropped. Frames that pass are only bundle-adjusted again.

What it cannot see: an error that moves points along their epipolar lines (a camera moving
sideways, turned about its vertical axis; in the tests a turn about the optical axis drops a
frame's consistency nearly to zero, the same turn about the vertical axis far less), and a whole model
that is consistently wrong (a reversed twin, :mod:`osn.preprocess.twin`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric distance (pixels) of matches ``x1 (N,2)`` <-> ``x2 (N,2)`` to ``x2' F x1 = 0``."""
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    num = np.sum(h2 * Fx1, axis=1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


class _Matches:
    """Keypoints and verified inlier matches of a COLMAP database, per image id."""

    def __init__(self, db_path: Path):
        import pycolmap

        db = pycolmap.Database.open(str(db_path))
        try:
            ids = [im.image_id for im in db.read_all_images()]
            self.keypoints = {i: np.asarray(db.read_keypoints(i))[:, :2] for i in ids}
            pair_ids, geoms = db.read_two_view_geometries()
        finally:
            db.close()
        #: image id -> list of (other image id, (N, 2) [keypoint here, keypoint there])
        self.pairs: dict[int, list[tuple[int, np.ndarray]]] = {i: [] for i in ids}
        for pid, g in zip(pair_ids, geoms):
            m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            if len(m) == 0:
                continue
            a, b = pycolmap.pair_id_to_image_pair(pid)
            self.pairs[a].append((b, m))
            self.pairs[b].append((a, m[:, ::-1]))


def _cam_from_world(rec, image_id: int) -> np.ndarray:
    return np.asarray(rec.images[image_id].cam_from_world().matrix())


def epipolar_consistency(rec, matches: _Matches, K: np.ndarray, threshold_px: float) -> dict[int, tuple[int, int]]:
    """Per registered image id: ``(verified matches with other registered images, how many lie
    within threshold_px of the model's epipolar geometry)``."""
    reg = {i for i, im in rec.images.items() if im.has_pose}
    Kinv = np.linalg.inv(K)
    out = {i: [0, 0] for i in reg}
    for a in reg:
        Ma = _cam_from_world(rec, a)
        for b, m in matches.pairs.get(a, []):
            if b not in reg or b < a:
                continue
            Mb = _cam_from_world(rec, b)
            R = Mb[:, :3] @ Ma[:, :3].T
            t = Mb[:, 3] - R @ Ma[:, 3]
            F = Kinv.T @ _skew(t) @ R @ Kinv
            d = sampson_distance(F, matches.keypoints[a][m[:, 0]], matches.keypoints[b][m[:, 1]])
            good = int(np.sum(d <= threshold_px))
            for i in (a, b):
                out[i][0] += len(m)
                out[i][1] += good
    return {i: (n, g) for i, (n, g) in out.items()}


def _repose(rec, image_id: int, matches: _Matches, trusted: set[int], max_error: float, min_inliers: int, seed: int) -> int:
    """RANSAC PnP of one frame from 3D points reached through verified matches to ``trusted``
    frames; on success the frame's observations become the inliers. Returns the inlier count."""
    import pycolmap

    p2, p3, ref = [], [], []
    kp = matches.keypoints[image_id]
    for other, m in matches.pairs.get(image_id, []):
        if other not in trusted:
            continue
        pts = rec.images[other].points2D
        for k_here, k_there in m:
            p = pts[int(k_there)]
            if p.has_point3D():
                p2.append(kp[k_here])
                p3.append(rec.point3D(p.point3D_id).xyz)
                ref.append((int(k_here), int(p.point3D_id)))
    if len(p2) < min_inliers:
        return 0
    im = rec.images[image_id]
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = max_error
    est.ransac.random_seed = seed
    est.ransac.num_threads = 1
    res = pycolmap.estimate_and_refine_absolute_pose(np.asarray(p2), np.asarray(p3), im.camera, est)
    if res is None or int(res["num_inliers"]) < min_inliers:
        return 0
    rec.frames[im.frame_id].set_cam_from_world(im.camera_id, res["cam_from_world"])
    for idx, p in enumerate(im.points2D):
        if p.has_point3D():
            rec.delete_observation(image_id, idx)
    used_kp, used_pt = set(), set()
    for (k, pid), inlier in zip(ref, res["inlier_mask"]):
        if not inlier or k in used_kp or pid in used_pt or not rec.exists_point3D(pid):
            continue
        rec.add_observation(pid, pycolmap.TrackElement(image_id, k))
        used_kp.add(k)
        used_pt.add(pid)
    return int(res["num_inliers"])


def bundle_adjust(rec, cauchy_px: float | None = None) -> None:
    """Global bundle adjustment of poses and points with the intrinsics fixed; squared loss, or
    Cauchy with scale ``cauchy_px`` (pixels of the SfM images)."""
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    if cauchy_px is not None:
        opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        opts.ceres.loss_function_scale = cauchy_px
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = 1  # threads change the result's last digits
    config = pycolmap.BundleAdjustmentConfig()
    for i, im in rec.images.items():
        if im.has_pose:
            config.add_image(i)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    # The adjuster itself, not pycolmap.bundle_adjustment: that one logs past minloglevel.
    pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()


def drop_points_behind(rec) -> int:
    """Delete the 3D points of ``rec`` that lie behind a camera observing them (an adjustment can
    push a weakly seen point through a camera); returns how many went."""
    cam_from_world = {i: np.asarray(im.cam_from_world().matrix()) for i, im in rec.images.items() if im.has_pose}
    behind = [pid for pid in rec.point3D_ids()
              if any(cam_from_world[el.image_id][2, :3] @ rec.point3D(pid).xyz + cam_from_world[el.image_id][2, 3] <= 0
                     for el in rec.point3D(pid).track.elements)]
    for pid in behind:
        rec.delete_point3D(pid)
    return len(behind)


def settle_points(rec) -> int:
    """Make an adjusted ``rec`` safe to read points from: delete the points behind a camera that
    observes them, then recompute every point's error. COLMAP stores a point's error when it last
    triangulates or filters it, and a bundle adjustment moves the model without updating it.
    Returns how many points went."""
    dropped = drop_points_behind(rec)
    rec.update_point_3d_errors()
    return dropped


def repair_registrations(
    rec, db_path: Path, K: np.ndarray, threshold_px: float, min_consistency: float, min_inliers: int, seed: int,
) -> list[dict]:
    """Re-pose or drop the registered frames of ``rec`` whose verified matches mostly contradict
    their pose (``K``, ``threshold_px`` in the SfM images' pixels). Modifies ``rec``; returns one
    entry per suspect frame: its name, consistency before (and after), and what was done."""
    matches = _Matches(db_path)
    cons = epipolar_consistency(rec, matches, K, threshold_px)
    frac = {i: (g / n if n else 1.0) for i, (n, g) in cons.items()}
    if log.isEnabledFor(logging.DEBUG):
        log.debug("epipolar consistency per frame: %s", " ".join(
            f"{Path(rec.images[i].name).stem}:{f:.2f}" for i, f in sorted(frac.items(), key=lambda x: rec.images[x[0]].name)))
    suspects = sorted(i for i, f in frac.items() if f < min_consistency)
    if not suspects:
        return []
    trusted = set(frac) - set(suspects)
    report = []
    for i in suspects:
        inliers = _repose(rec, i, matches, trusted, threshold_px, min_inliers, seed)
        report.append({"frame": Path(rec.images[i].name).stem, "consistency": frac[i], "pnp_inliers": inliers})
    if any(r["pnp_inliers"] for r in report):
        bundle_adjust(rec)
    after = epipolar_consistency(rec, matches, K, threshold_px)
    for i, r in zip(suspects, report):
        n, g = after.get(i, (0, 0))
        r["consistency_after"] = g / n if n else 0.0
        if r["pnp_inliers"] and r["consistency_after"] >= min_consistency:
            r["action"] = "re-posed"
        else:
            rec.deregister_frame(rec.images[i].frame_id)
            r["action"] = "dropped"
        log.warning(
            "frame %s: %.1f%% of its verified matches fit its SfM pose; %s (PnP inliers %d, %.1f%% fit after)",
            r["frame"], 100 * r["consistency"], r["action"], r["pnp_inliers"], 100 * r["consistency_after"],
        )
    return report

"""The depth-reversed twin of a reconstruction, fitted and compared with the model SfM kept.

A small object seen nearly in weak perspective has two reconstructions that fit its images
almost equally: the true one and its depth-reversed twin (the Necker reversal), whose relief is
inverted and whose rotations turn the wrong way, by an error that grows along the video. The
twin projects every point onto the object's masks, so no mask or depth check can tell them apart
(:mod:`osn.preprocess.consistency`), and the mapper's restarts, which differ only in their random
seeds, may all settle in it. Under full perspective only one of the two fits the matches exactly.

So the kept model's twin is built explicitly (:func:`reversed_twin`), bundle-adjusted and compared
point by point over the 3D points both models hold (:func:`compare_with_twin`): the twin *fits
better* when its reprojection error is lower at significantly more than half of them (a one-sided
sign test at :data:`TWIN_SIGNIFICANCE`). On a model of few points seen in few pixels the two fits
differ by noise, about half the points either way. A model that fills the frame (the anchor) has a
twin far worse than itself.

A twin that fits better is reported, not trained: on the development scenes where it applies it
is nearer the truth than SfM's model, yet the valid sets trained from it came out no better, on
one scene empty (docs/preprocess.md, step 8). So it says which models to distrust, like the
consistency check's orientation kinks.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import binomtest

from osn.preprocess.repair import bundle_adjust, drop_points_behind

#: Bundle adjustments of the twin before the comparison: it starts pixels off its own optimum (the
#: reversal is exact only under affine projection).
TWIN_ADJUSTMENTS = 3

#: Significance of the sign test that the twin fits more points better than the kept model.
TWIN_SIGNIFICANCE = 0.01


def reversed_twin(rec):
    """A copy of ``rec`` (a ``pycolmap.Reconstruction``) with its depth relief reversed.

    Every registered camera keeps the points' centroid (the median of the 3D points) where it
    saw it and sees the offsets from it mirrored along its optical axis: camera-from-world rotation
    ``R -> diag(-1, -1, 1) R``, translation so that the centroid's camera coordinates stay. Under
    affine projection this reproduces every image exactly; under perspective it is the start of
    the twin's basin. Each track is triangulated anew (linear, from all its observations) from
    these cameras; points that land behind one of them are deleted.
    """
    import pycolmap

    twin = pycolmap.Reconstruction(rec)
    centre = np.median(np.stack([p.xyz for p in twin.points3D.values()]), axis=0)
    mirror = np.diag([-1.0, -1.0, 1.0])
    projection = {}
    for im in twin.images.values():
        if not im.has_pose:
            continue
        M = np.asarray(im.cam_from_world().matrix())
        R = mirror @ M[:, :3]
        t = M[:, :3] @ centre + M[:, 3] - R @ centre
        twin.frames[im.frame_id].set_cam_from_world(im.camera_id, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        projection[im.image_id] = twin.cameras[im.camera_id].calibration_matrix() @ np.c_[R, t]
    for pid in list(twin.point3D_ids()):
        track = [(projection[el.image_id], twin.images[el.image_id].points2D[el.point2D_idx].xy)
                 for el in twin.point3D(pid).track.elements]
        X = _triangulate(track)
        if X is None:
            twin.delete_point3D(pid)
        else:
            twin.point3D(pid).xyz = X
    drop_points_behind(twin)
    return twin


def _triangulate(track: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """Linear (DLT) triangulation of one track of ``(P (3, 4), xy (2,))``; None when the point is
    at infinity."""
    rows = []
    for P, (x, y) in track:
        rows += [x * P[2] - P[0], y * P[2] - P[1]]
    Xh = np.linalg.svd(np.asarray(rows))[2][-1]
    if abs(Xh[3]) < 1e-12 * np.abs(Xh[:3]).max():
        return None
    return Xh[:3] / Xh[3]


def point_errors(rec) -> dict[int, float]:
    """``point3D_id -> `` mean reprojection error of the point over its track (SfM-image pixels),
    recomputed from the model's poses (``rec``'s stored errors are updated)."""
    rec.update_point_3d_errors()
    return {int(pid): float(p.error) for pid, p in rec.points3D.items()}


def compare_with_twin(rec, cauchy_px: float | None, pixel_scale: float = 1.0) -> dict:
    """How ``rec`` fits its matches against its bundle-adjusted depth-reversed twin; ``rec`` is
    left untouched (its stored point errors too).

    ``cauchy_px``: the Cauchy scale of the twin's bundle adjustments (SfM-image pixels; None for
    squared loss), as the kept model's last one. Returns (``pixel_scale``: SfM-image pixels per
    input pixel) both models' median errors in input pixels over the points both hold, the share
    of those points the twin fits better, their count and the sign test's verdict:
    ``{"median_error_px", "twin_median_error_px", "twin_better_share", "points", "fits_better"}``;
    empty when the model has no points or fewer than two frames.
    """
    import pycolmap

    if rec.num_points3D() == 0 or rec.num_reg_images() < 2:
        return {}
    twin = reversed_twin(rec)
    for _ in range(TWIN_ADJUSTMENTS):
        bundle_adjust(twin, cauchy_px)
    drop_points_behind(twin)  # adjustment can push a weakly seen point through a camera
    kept, other = point_errors(pycolmap.Reconstruction(rec)), point_errors(twin)
    common = sorted(kept.keys() & other.keys())
    if not common:
        return {}
    better = int(sum(other[i] < kept[i] for i in common))
    return {
        "median_error_px": float(np.median([kept[i] for i in common])) / pixel_scale,
        "twin_median_error_px": float(np.median([other[i] for i in common])) / pixel_scale,
        "twin_better_share": better / len(common),
        "points": len(common),
        "fits_better": bool(binomtest(better, len(common), 0.5, alternative="greater").pvalue < TWIN_SIGNIFICANCE),
    }

"""Poses for the frames SfM left an object unposed in, bridged from its posed neighbours.

Per-object SfM may register a mover in only some of the frames its mask shows it in (too few
matches there; often every frame after some point, as the mover turns), and the consistency check
may drop frames. Training draws no ray from the object's pixels in those frames, so every depth
order seen only there (an object passing in front of another) is lost to the scale network.

All objects are filmed by one camera, and the anchor's SfM usually registers that camera in every
frame. In the anchor's frame the object moves as a similarity ``x_a = s W(t) y + p(t)`` (object
point ``y`` in the object's own unit, ``s`` the unknown anchor units per object unit), with
``W = R_anchor R_k^T`` and ``p = c_anchor - s W c_k`` from the two cameras' rotations ``R`` and
centres ``c`` (:func:`object_in_anchor`). Between two registered frames the object's orientation
is interpolated by slerp and its position linearly, by timestamp, and the camera-to-object pose
rebuilt from the anchor's camera there (:func:`bridged_pose`). Past the registered span the two
nearest posed frames extrapolate, one frame at a time outward, each bridged frame a neighbour of
the next. The position depends on ``s`` only through the curvature of the camera's path between
the neighbours, so ``s`` is chosen from a log-spaced range by how well the object's points then
fit its silhouette in that frame.

A bridged pose is kept only when it fits the frame's mask no worse than the object's own
registered poses fit theirs (:func:`osn.preprocess.consistency.silhouette_agreement`, both
measured with the other frames' points): no more of its points off the mask than the worst
registered frame, and no less of the mask covered by them. A predicted pose that fails is first
shifted across the view onto the silhouette (:func:`refine_to_silhouette`: a mover whose pace
changed), its depth and orientation kept; one that still fails stays unposed and ends its chain.
Bridged frames carry no sparse depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from scenecore.cameras import invert_pose, project_pixels

from osn.preprocess.consistency import silhouette_agreement, silhouette_masks, thinned

#: Candidate scales, as factors of the scale at which the object's median sparse depth equals the
#: anchor's (objects stand in front of the anchor, so mostly below it): 2^(k/2), k = -12 .. 2.
SCALE_FACTORS = 2.0 ** (np.arange(-12, 3) / 2.0)


def object_in_anchor(cam_to_obj: np.ndarray, cam_to_anchor: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(W (3, 3), p (3,))``: the object-to-anchor similarity ``x_a = s W y + p`` of one frame,
    from the camera-to-object and camera-to-anchor poses ``(4, 4)`` of that frame and the scale
    ``s`` (anchor units per object unit)."""
    W = cam_to_anchor[:3, :3] @ cam_to_obj[:3, :3].T
    return W, cam_to_anchor[:3, 3] - s * W @ cam_to_obj[:3, 3]


def bridged_pose(alpha: float, obj0: np.ndarray, obj1: np.ndarray, anc0: np.ndarray, anc1: np.ndarray,
                 anc_t: np.ndarray, s: float) -> np.ndarray:
    """The camera-to-object pose ``(4, 4)`` at a frame a fraction ``alpha`` of the way from frame 0
    to frame 1 (outside [0, 1]: extrapolated), given both frames' camera-to-object poses
    ``obj0, obj1``, the anchor's ``anc0, anc1`` and the anchor's at the frame ``anc_t`` (all
    ``(4, 4)``), and the scale ``s`` (anchor units per object unit; ``inf``: the camera's path
    between the frames taken as straight)."""
    s_eff = 1.0 if np.isinf(s) else s
    W0, p0 = object_in_anchor(obj0, anc0, s_eff)
    W1, p1 = object_in_anchor(obj1, anc1, s_eff)
    step = Rotation.from_matrix(W0.T @ W1).as_rotvec()
    W = W0 @ Rotation.from_rotvec(alpha * step).as_matrix()
    if np.isinf(s):  # p / s -> c_anchor / s vanishes: interpolate W c_k directly
        c = W.T @ ((1 - alpha) * W0 @ obj0[:3, 3] + alpha * W1 @ obj1[:3, 3])
    else:
        p = (1 - alpha) * p0 + alpha * p1
        c = W.T @ (anc_t[:3, 3] - p) / s
    out = np.eye(4)
    out[:3, :3] = W.T @ anc_t[:3, :3]
    out[:3, 3] = c
    return out


@dataclass
class Bridged:
    """The frames bridged for one object and why the others were not."""

    frames: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    #: Per candidate frame (time index as a string): the chosen pose's miss and cover shares,
    #: the scale factor, and whether it was kept.
    record: dict = field(default_factory=dict)
    #: The acceptance thresholds: the worst registered frame's miss and cover shares.
    max_miss: float = float("nan")
    min_cover: float = float("nan")


def registered_fit(frames: np.ndarray, cam_to_obj: np.ndarray, points: list[np.ndarray], masks: np.ndarray,
                   object_id: int, anchor: int, K: np.ndarray, tol_px: float) -> tuple[float, float] | None:
    """The acceptance thresholds of a bridged pose: the worst ``(miss, cover)``
    (:func:`~osn.preprocess.consistency.silhouette_agreement`) over the registered frames, each
    measured with the other frames' ``points``; None where no frame could be measured."""
    own = []
    for n, t in enumerate(frames):
        others = [p for m, p in enumerate(points) if m != n and len(p)]
        if others:
            own.append(silhouette_agreement(np.concatenate(others), cam_to_obj[n], masks[int(t)], object_id, anchor,
                                            K, tol_px))
    own = np.array([x for x in own if np.isfinite(x).all()])
    return (float(own[:, 0].max()), float(own[:, 1].min())) if len(own) else None


def _neighbours(t: int, posed: dict[int, np.ndarray], registered: np.ndarray, ts: np.ndarray,
                chained: bool) -> tuple[int, int]:
    """The two frames a pose at ``t`` is bridged from: past the registered span (``chained``) the
    two posed frames nearest ``t``, in time order; inside it the registered frames around ``t``."""
    if chained:
        known = np.array(sorted(posed), dtype=np.int64)
        near = known[np.argsort(np.abs(known - t), kind="stable")[:2]]
        ta, tb = (int(x) for x in sorted(near, key=lambda x: ts[x]))
        return ta, tb
    return int(registered[registered < t].max()), int(registered[registered > t].min())


def bridge_object(
    frames: np.ndarray, cam_to_obj: np.ndarray, points: list[np.ndarray], depth_median: float,
    anchor_frames: np.ndarray, anchor_cam_to_obj: np.ndarray, anchor_depth_median: float,
    masks: np.ndarray, timestamps: np.ndarray, object_id: int, anchor: int, K: np.ndarray, tol_px: float,
    min_pixels: int = 1,
) -> Bridged:
    """Bridge object ``object_id`` into the frames where ``masks (T, H, W)`` shows it but it has no
    pose (module docstring). ``frames (F,)``, ``cam_to_obj (F, 4, 4)``: its registered frames and
    poses; ``points``: per registered frame its sparse depths back-projected into the object
    (:func:`osn.preprocess.consistency.frame_points`); ``depth_median``, ``anchor_depth_median``: the
    object's and the anchor's median sparse depth in their own units; the anchor's registered
    frames and poses; ``tol_px``: the object's mask tolerance (as the consistency checks set it);
    ``min_pixels``: frames where its mask has fewer pixels are left (as SfM leaves them). Only
    frames where the anchor is registered are bridged, from neighbours where it is too."""
    out = Bridged()
    slot = {int(t): n for n, t in enumerate(anchor_frames)}
    both = [n for n, t in enumerate(frames) if int(t) in slot]
    shown = [t for t in range(len(masks)) if t not in set(map(int, frames)) and t in slot
             and int(np.count_nonzero(masks[t] == object_id)) >= max(min_pixels, 1)]
    if len(both) < 2 or not shown or not (depth_median > 0 and anchor_depth_median > 0):
        return out
    thin = thinned(points)
    fit = registered_fit(frames, cam_to_obj, thin, masks, object_id, anchor, K, tol_px)
    if fit is None:
        return out
    out.max_miss, out.min_cover = fit
    pts = np.concatenate([p for p in thin if len(p)])
    ts = np.asarray(timestamps, dtype=np.float64)
    s0 = anchor_depth_median / depth_median
    # Posed frames (registered, then bridged) where the anchor is posed too: time index -> pose.
    posed = {int(frames[n]): cam_to_obj[n] for n in both}
    registered = np.array(sorted(posed), dtype=np.int64)
    first, last = int(registered[0]), int(registered[-1])
    # Outward from the registered span, one frame at a time: each bridged frame is a neighbour of
    # the next, and the first one refused ends the chain on that side.
    groups = [([t for t in shown if first < t < last], False), (sorted(t for t in shown if t > last), True),
              (sorted((t for t in shown if t < first), reverse=True), True)]
    fits = lambda M, t: silhouette_agreement(pts, M, masks[t], object_id, anchor, K, tol_px)  # noqa: E731
    for group, chained in groups:
        for t in group:
            ta, tb = _neighbours(t, posed, registered, ts, chained)
            span = ts[tb] - ts[ta]
            alpha = (ts[t] - ts[ta]) / span if span > 0 else 0.5
            best = None  # the scale whose pose fits the silhouette best
            for sc in [*(s0 * SCALE_FACTORS), np.inf]:
                M = bridged_pose(alpha, posed[ta], posed[tb], anchor_cam_to_obj[slot[ta]], anchor_cam_to_obj[slot[tb]],
                                 anchor_cam_to_obj[slot[t]], sc)
                miss, cover = fits(M, t)
                if np.isfinite(miss) and np.isfinite(cover) and (best is None or miss - cover < best[0]):
                    best = (miss - cover, sc, M, miss, cover)
            if best is None:
                out.record[str(t)] = {"kept": False, "why": "no point of the object lands in the frame"}
                if chained:
                    break
                continue
            _, sc, M, miss, cover = best
            refined = not (miss <= out.max_miss and cover >= out.min_cover)
            if refined:  # the motion changed pace: shift the object across the view onto its silhouette
                M = refine_to_silhouette(pts, M, masks[t], object_id, anchor, K, depth_median)
                miss, cover = fits(M, t)
            kept = bool(miss <= out.max_miss and cover >= out.min_cover)
            out.record[str(t)] = {"kept": kept, "miss": miss, "cover": cover, "from": [ta, tb], "alpha": float(alpha),
                                  "refined": refined, "scale_factor": None if np.isinf(sc) else float(sc / s0)}
            if kept:
                posed[t] = M
                out.frames.append(int(t))
                out.poses.append(M)
            elif chained:
                break
    order = np.argsort(out.frames, kind="stable")
    out.frames, out.poses = [out.frames[i] for i in order], [out.poses[i] for i in order]
    return out


#: Mask pixels the silhouette fit measures per frame (evenly spaced; the fit is a mean distance).
MAX_MASK_PIXELS = 2000


def silhouette_distance(points: np.ndarray, cam_to_obj: np.ndarray, K: np.ndarray, outside: np.ndarray,
                        hide: np.ndarray, pixels: np.ndarray) -> float:
    """Two-sided mean distance (pixels) between the object's projected points and its visible
    mask in one ``(H, W)`` frame: points to the mask (``outside``: the distance transform of the
    mask's complement; points where ``hide`` says an object may hide it not counted) plus the
    mask's ``pixels (P, 2)`` to the nearest projected point; ``inf`` with fewer than three points
    in the frame."""
    H, W = outside.shape
    uv, _, pix, inside = project_pixels(points, K, cam_to_obj, W, H)
    if int(inside.sum()) < 3:
        return float("inf")
    u, v = pix[inside, 0], pix[inside, 1]
    free = ~hide[v, u]
    to_mask = (ndimage.map_coordinates(outside, [uv[inside][free, 1] - 0.5, uv[inside][free, 0] - 0.5], order=1,
                                       mode="nearest").mean() if free.any() else 0.0)
    to_points = cKDTree(uv[inside]).query(pixels)[0].mean()
    return float(to_mask + to_points)


def refine_to_silhouette(points: np.ndarray, cam_to_obj: np.ndarray, mask: np.ndarray, object_id: int, anchor: int,
                         K: np.ndarray, depth: float) -> np.ndarray:
    """``cam_to_obj (4, 4)`` shifted across the camera's view (its x and y, the depth kept) to
    minimise :func:`silhouette_distance` in one frame's instance ids ``mask (H, W)``; ``depth``:
    the object's typical depth, the shift's unit. Depth and orientation are kept as the
    neighbours' motion gives them: a silhouette fixes neither well (its size changes little with
    depth; a round object turns freely inside its own). Returned unchanged when the object is not
    visible, no point lands in the frame, or no shift fits better."""
    visible = mask == object_id
    if not visible.any():
        return cam_to_obj
    outside = ndimage.distance_transform_edt(~visible)
    hide = silhouette_masks(mask, object_id, anchor, 0.0)[1]
    pixels = np.argwhere(visible)[:, ::-1] + 0.5
    if len(pixels) > MAX_MASK_PIXELS:
        pixels = pixels[np.linspace(0, len(pixels) - 1, MAX_MASK_PIXELS).astype(np.int64)]

    def moved(x: np.ndarray) -> np.ndarray:
        E = np.eye(4)  # the object moved by depth * (x, y, 0) in the camera's frame
        E[:2, 3] = depth * x
        return cam_to_obj @ invert_pose(E)

    def cost(x: np.ndarray) -> float:
        d = silhouette_distance(points, moved(x), K, outside, hide, pixels)
        return d if np.isfinite(d) else 1e6  # the line search needs finite values

    start = cost(np.zeros(2))
    if start >= 1e6:
        return cam_to_obj
    res = minimize(cost, np.zeros(2), method="Powell", options={"xtol": 1e-4, "ftol": 1e-4, "maxfev": 600})
    return moved(res.x) if res.fun < start else cam_to_obj

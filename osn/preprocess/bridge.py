"""Poses for the frames SfM left an object unposed in, bridged from its registered neighbours.

Per-object SfM may register a mover in only some of the frames its mask shows it in (too few
matches there). Training draws no ray from the object's pixels in those frames, so every depth
order seen only there (an object passing in front of another) is lost to the scale network.

All objects are filmed by one camera, and the anchor's SfM usually registers that camera in every
frame. In the anchor's frame the object moves as a similarity ``x_a = s W(t) y + p(t)`` (object
point ``y`` in the object's own unit, ``s`` the unknown anchor units per object unit), with
``W = R_anchor R_k^T`` and ``p = c_anchor - s W c_k`` from the two cameras' rotations ``R`` and
centres ``c`` (:func:`object_in_anchor`). Between two registered frames the object's orientation
is interpolated by slerp and its position linearly, by timestamp, and the camera-to-object pose
rebuilt from the anchor's camera there (:func:`bridged_pose`); past the last registered frame
the last two extrapolate. The position depends on ``s`` only through the curvature of the
camera's path between the neighbours, so ``s`` is chosen from a log-spaced range by how well
the object's points then fit its silhouette in that frame.

A bridged pose is kept only when it fits the frame's mask no worse than the object's own
registered poses fit theirs (:func:`osn.preprocess.consistency.silhouette_agreement`, both
measured with the other frames' points): no more of its points off the mask than the worst
registered frame, and no less of the mask covered by them. Bridged frames carry no sparse depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from osn.preprocess.consistency import silhouette_agreement, thinned

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


def _neighbours(t: float, ts: np.ndarray) -> tuple[int, int] | None:
    """Indices of the two registered timestamps ``ts`` (sorted) that bracket ``t``, or the two
    nearest on its side when it lies outside them; None with fewer than two."""
    if len(ts) < 2:
        return None
    i = int(np.searchsorted(ts, t))
    i = min(max(i, 1), len(ts) - 1)
    return i - 1, i


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
    registered = set(map(int, frames))
    shown = [t for t in range(len(masks)) if t not in registered and t in slot
             and int(np.count_nonzero(masks[t] == object_id)) >= max(min_pixels, 1)]
    if len(both) < 2 or not shown or not (depth_median > 0 and anchor_depth_median > 0):
        return out
    thin = thinned(points)
    # The registered frames' own fit, each measured with the other frames' points.
    own = []
    for n, t in enumerate(frames):
        others = [p for m, p in enumerate(thin) if m != n and len(p)]
        if others:
            own.append(silhouette_agreement(np.concatenate(others), cam_to_obj[n], masks[int(t)], object_id, anchor,
                                            K, tol_px))
    own = np.array([x for x in own if np.isfinite(x).all()])
    if not len(own):
        return out
    out.max_miss, out.min_cover = float(own[:, 0].max()), float(own[:, 1].min())
    pts = np.concatenate([p for p in thin if len(p)])
    ts = np.asarray(timestamps, dtype=np.float64)
    reg_t = ts[[int(frames[n]) for n in both]]
    order = np.argsort(reg_t, kind="stable")
    both, reg_t = [both[i] for i in order], reg_t[order]
    s0 = anchor_depth_median / depth_median
    candidates = [*(s0 * SCALE_FACTORS), np.inf]
    for t in shown:
        a, b = _neighbours(ts[t], reg_t)
        na, nb = both[a], both[b]
        span = reg_t[b] - reg_t[a]
        alpha = (ts[t] - reg_t[a]) / span if span > 0 else 0.5
        anc = [anchor_cam_to_obj[slot[int(frames[n])]] for n in (na, nb)]
        best = None
        for s in candidates:
            M = bridged_pose(alpha, cam_to_obj[na], cam_to_obj[nb], anc[0], anc[1], anchor_cam_to_obj[slot[t]], s)
            miss, cover = silhouette_agreement(pts, M, masks[t], object_id, anchor, K, tol_px)
            if not (np.isfinite(miss) and np.isfinite(cover)):
                continue
            score = miss + (1.0 - cover)
            if best is None or score < best[0]:
                best = (score, miss, cover, s, M)
        if best is None:
            out.record[str(t)] = {"kept": False, "why": "no point of the object lands in the frame"}
            continue
        _, miss, cover, s, M = best
        kept = bool(miss <= out.max_miss and cover >= out.min_cover)
        out.record[str(t)] = {"kept": kept, "miss": miss, "cover": cover, "alpha": float(alpha),
                              "scale_factor": None if np.isinf(s) else float(s / s0)}
        if kept:
            out.frames.append(int(t))
            out.poses.append(M)
    return out

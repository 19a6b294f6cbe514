"""SfM depths that would hide what the other frames saw: a phantom count that needs no ground truth.

Repeated texture lets SfM triangulate points one period off (on gnome-house's checker floor many
of the room's depths lie on a phantom floor well in front of the true one). Such a point fits the
frames it was matched in, but projected into the object's other frames it lands *in front of*
the depths those frames observed there: were it real, it would hide what SfM saw. ``osn
preprocess`` reports per object how many depths do so in at least half of the frames that can
test them (:func:`occluding_flags`, ``occluding_depths`` in ``preprocess_report.json``): the
only phantom figure a video without ground truth has. On gnome-house it flags most of the
room's gross phantoms (below half the true depth) and almost none of its good depths
(measurements in docs/experiments/). ``osn preprocess`` keeps the flagged depths out of training
(``drop_occluding: training``): an object's are dropped before normalising it (a small object's
few phantoms would set its near plane and box), the anchor's after (its near plane sets the
scene volume, and normalising the room without them makes the valid set worse; docs/preprocess.md).

Pure numpy on one object's observations in its own frame and unit; nothing here reads ground truth.
"""

from __future__ import annotations

import numpy as np

from scenecore.cameras import pixel_rays, project_pixels

#: Relative depth by which a point must lie in front of a frame's observed depths, and the share
#: of the testing frames that must see it so, for :func:`occluding_flags`.
MARGIN = 0.15
VOTE = 0.5

#: Side of the pixel blocks whose median observed depth a projection is compared with, as a
#: fraction of the frame's larger side: SfM's depths cover well under 1% of the pixels, so smaller
#: blocks often hold no observed depth and leave many of the room's gross phantoms uncounted.
CELL_FRACTION = 0.03


def occlusion_tests(
    cam_to_obj: np.ndarray,
    sparse_pix: list[np.ndarray],
    sparse_depth: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
    margin: float,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, how often each sparse depth was tested against the other frames and how often
    it would have hidden what they saw.

    Args:
        cam_to_obj: ``(F, 4, 4)`` camera-to-object poses of the object's frames (depths' unit).
        sparse_pix: per frame ``(M, 2)`` integer pixels ``(u, v)``; sparse_depth: ``(M,)`` planar depths.
        K: ``(3, 3)`` intrinsics; width, height: the frames' size in pixels.
        margin: relative depth by which a point must lie in front of the observed surface.

    Returns:
        Per frame ``(tested, hides)``, each ``(M,)`` counts of other frames: those where the point
        projects in front of the camera into a block of pixels (side ``CELL_FRACTION`` of the
        frame) holding observed depths, and among them those where its depth is below
        ``(1 - margin)`` times their median.
    """
    cell = max(1, int(round(CELL_FRACTION * max(width, height))))
    gh, gw = -(-height // cell), -(-width // cell)
    observed = [_cell_medians(pix, dep, cell, gh, gw) for pix, dep in zip(sparse_pix, sparse_depth)]
    out = []
    for i, (pix, dep) in enumerate(zip(sparse_pix, sparse_depth)):
        dep = np.asarray(dep, dtype=np.float64)
        tested = np.zeros(len(dep))
        hides = np.zeros(len(dep))
        if len(dep):
            o, d = pixel_rays(K, cam_to_obj[i], width, height, pixels=np.asarray(pix))
            pts = o + dep[:, None] * d  # object frame
            for j in range(len(cam_to_obj)):
                if j == i:
                    continue
                _, z, uv, inside = project_pixels(pts, K, cam_to_obj[j], width, height)
                seen = np.zeros(len(z))
                seen[inside] = observed[j][uv[inside, 1] // cell, uv[inside, 0] // cell]
                test = seen > 0
                tested += test
                hides += test & (z < (1.0 - margin) * seen)
        out.append((tested, hides))
    return out


def occluding_share(
    cam_to_obj: np.ndarray,
    sparse_pix: list[np.ndarray],
    sparse_depth: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
    margin: float,
) -> list[np.ndarray]:
    """Per frame ``(M,)`` in [0, 1]: the share of the other frames that could test a sparse depth
    (:func:`occlusion_tests`, the same arguments) in which it would occlude; 0 when none could."""
    return [np.divide(h, t, out=np.zeros_like(h), where=t > 0)
            for t, h in occlusion_tests(cam_to_obj, sparse_pix, sparse_depth, K, width, height, margin)]


def contradicted_share(counts: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """The share of all of an object's depth-against-frame tests (``counts``: what
    :func:`occlusion_tests` returns) in which a depth lies in front of what the other frame saw
    there: 0 on exact depths but for blocks straddling a depth edge, more where SfM's poses or
    points are off. 0 when nothing could be tested."""
    tested = sum(float(t.sum()) for t, _ in counts)
    return sum(float(h.sum()) for _, h in counts) / tested if tested > 0 else 0.0


def _cell_medians(pix: np.ndarray, dep: np.ndarray, cell: int, gh: int, gw: int) -> np.ndarray:
    """``(gh, gw)`` median of the depths observed in each ``cell`` x ``cell`` pixel block (0 where none)."""
    out = np.zeros((gh, gw))
    if len(dep) == 0:
        return out
    pix = np.asarray(pix)
    key = (pix[:, 1] // cell) * gw + pix[:, 0] // cell
    order = np.lexsort((np.asarray(dep), key))
    key, dep = key[order], np.asarray(dep, dtype=np.float64)[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    out.flat[key[starts]] = 0.5 * (dep[lo] + dep[hi])
    return out


def occluding_flags(
    cam_to_obj: np.ndarray, sparse_pix: list[np.ndarray], sparse_depth: list[np.ndarray], K: np.ndarray, width: int,
    height: int, margin: float = MARGIN, vote: float = VOTE,
) -> list[np.ndarray]:
    """Per frame ``(M,)`` bool: the sparse depths that lie more than ``margin`` in front of what the
    other frames saw in at least a share ``vote`` of those that could test them (:func:`occluding_share`)."""
    return [s >= vote for s in occluding_share(cam_to_obj, sparse_pix, sparse_depth, K, width, height, margin)]


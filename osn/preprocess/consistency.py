"""Reconstructions that contradict the video: per-object checks of SfM that need no ground truth.

Per-object SfM can be wrong while fitting its own matches well: a frame posed degrees off, a
model whose depths disagree from frame to frame. Training on it unflagged teaches the fields
wrong geometry. Every signal here is measured on what the method has: the object's own poses and
sparse depths (any unit: every figure is scale-free), the instance masks and the anchor's poses.

Signals, per object:

* **Mask agreement** (:func:`mask_misses`, :func:`frame_medians`): every frame's sparse
  depths, back-projected with that frame's pose, are the object's points; projected with another
  frame's pose they must land on the object's mask there (dilated by the reconstruction's own
  reprojection noise), unless another object hides them. A frame whose pose is off sends the
  object's points off its mask in that frame, and its own points off the masks of the others.
  Per frame: the median, over the other frames, of the share of points that miss (both
  directions), so a few wrong frames do not condemn the right ones. *Detects* rotations and
  translations that move the object across its silhouette (a few degrees on an object a tenth of
  the frame wide), and depths so wrong that parallax moves them off the silhouette. *Cannot
  detect* errors that keep the silhouette: a depth-reversed twin (it reproduces the image
  positions; SfM compares the kept model with it, :mod:`osn.preprocess.twin`), a turn about the
  line of sight to a round object, scale; nor anything about the anchor (its mask is the whole
  frame but the objects, which may hide it).
* **Depth agreement** (:func:`depth_disagreement`, :func:`consistent_core`): a point of frame i
  projected into frame j lands next to the depths SfM observed there; where one lies within the
  mask tolerance, the relative difference of the two depths (median per frame pair). In a
  consistent model the same track is observed in both frames and the difference is its
  reprojection noise (a tenth of a percent on the tests' scene). A frame posed wrong disagrees
  with every right frame; removing the worst frame one at a time until the rest agree
  (:func:`consistent_core`) names it. When no half of the frames agrees, the depths themselves
  are wrong (scrambled, a wrong scale per frame). *Detects* rotations of a degree or two that the
  masks cannot see, on objects and on the anchor alike; *cannot detect* an error every frame
  shares (a model distorted as a whole, consistently; SfM's own bundle adjustment makes its
  depths agree with its poses whatever they are).
* **Orientation against the anchor** (:func:`orientation_kinks`): all objects are filmed by one
  camera, so object k's orientation in the anchor's frame is ``W_k(t) = R_anchor(t) R_k(t)^T``
  (camera-to-anchor rotation times object-to-camera rotation, up to one constant rotation on the
  right). Objects rotate, so ``W_k`` may change; but a rigid object's orientation cannot jump and
  come back between two frames. Per interior frame: the angle between ``W_k(t)`` and the
  interpolation (slerp, by timestamp) of its neighbours. *Detects* a single frame's rotation
  error (and an anchor frame's, seen by every object at once); *cannot detect* smooth drifts (a
  reversed twin's rotations, which grow along the video) or errors in translation, and a genuine
  sudden turn between two frames looks the same, and a wrong frame also raises its neighbours'
  figure. So a frame's figure is reported (``frame_orientation_kink_deg``), not acted on. Its
  *median* over the frames is another matter: a few real turns raise a few frames, a
  reconstruction wrong as a whole raises them all (``orientation_kink_deg``). It *detects* a
  model that keeps the silhouettes and agrees with its own depths while its orientation jitters
  against the anchor's cameras (the spin of a round object, a model assembled from misregistered
  parts); it *cannot detect* a model wrong smoothly (a drift) or in translation only, and it
  *cannot tell* a harmless spin about a round object's axis from a turn that moves its surface.

Thresholds (none is a per-scene constant):

* mask tolerance: ``1 + 3 *`` the reconstruction's mean reprojection error (input pixels): its
  sparse pixels are rounded to whole pixels and lie up to a pixel inside the eroded mask, and a
  good point reprojects within a few times the mean error;
* a frame contradicts its masks when **most** of the object's points miss there
  (:data:`FRAME_MISS`): a right pose puts most of them on the silhouette whatever the occlusions
  (points hidden by other objects are not counted), a pose 10 degrees off almost none;
* depths disagree above :data:`DEPTH_RATIO` times the median of the scene's other objects'
  figures (the same measurement on the same video, mostly right: it holds the frames' rounding,
  the poses' noise and the surfaces' slope within the tolerance), and at least :data:`DEPTH_FLOOR`
  (a scene of near-perfect objects must not flag the one that is merely good: depths 2% apart
  are well inside what the sparse-depth loss's robust scale tolerates);
* an object misses its masks as a whole (its typical frame's share, once its contradicting frames
  are removed) above :data:`MASK_RATIO` times the other objects' median, and at least
  :data:`MASK_FLOOR` (a segmenter's borders and the anchor's occlusions stay below it);
* an object's orientation jitters against the anchor (its median kink, once its contradicting
  frames are removed) above :data:`KINK_RATIO` times the other movers' median, and at least
  :data:`KINK_FLOOR` (the jitter of well-posed movers); alone among the movers, above the floor.

Actions (:func:`assess_scene`): contradicting frames (masks or depth core) are dropped from the
object (``repair``) when more than half of its frames, and ``min_frames``, remain; otherwise, or
when what remains still misses its masks as a whole, its SfM is dropped (``drop``, a one-line
warning; the anchor cannot be, and the caller stops); an object whose depths disagree with no
half of its frames agreeing trains without its sparse depths (``no_depth``: its poses, range and
box are kept; the depths still measure its unit against ground truth when there is one); an
object whose orientation jitters against the anchor is named (reason ``orientation``, a one-line
warning) and trained as found: the kink cannot tell a turn that moves the object's surface from a
spin about a round object's own axis, which leaves its shape and contacts right, and dropping the
flagged movers did not gain on the development split.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from scenecore.cameras import pixel_rays, project_pixels

#: A frame contradicts its masks when more than this share of the object's points miss there.
FRAME_MISS = 0.5
#: Points per frame the checks project (evenly spaced in SfM's order; the figures are shares and
#: medians, which this many points fix to a few percent), and partner frames per frame (evenly
#: spaced over the video): the checks cost frames x partners x points, not frames squared.
MAX_POINTS = 500
MAX_PARTNERS = 40
#: An object's points miss its masks in its typical frame at this multiple of the other objects' ...
MASK_RATIO = 3.0
#: ... and more often than this (below it: a segmenter's mask borders and the anchor's occlusions).
MASK_FLOOR = 0.1
#: An object's depths disagree at this multiple of the scene's other objects' disagreement ...
DEPTH_RATIO = 3.0
#: ... and at least this relative disagreement.
DEPTH_FLOOR = 0.02
#: A mover's orientation jitters against the anchor's cameras (its median kink, degrees) at this
#: multiple of the scene's other movers' ...
KINK_RATIO = 3.0
#: ... and above this many degrees (well-posed movers of the development split stay below it).
KINK_FLOOR = 0.5


def frame_points(cam_to_obj: np.ndarray, sparse_pix: list[np.ndarray], sparse_depth: list[np.ndarray],
                 K: np.ndarray) -> list[np.ndarray]:
    """Per frame ``(M, 3)``: its sparse depths back-projected into the object's frame (any unit)."""
    out = []
    for M, pix, dep in zip(cam_to_obj, sparse_pix, sparse_depth):
        pix = np.asarray(pix, dtype=np.int64).reshape(-1, 2)
        o, d = pixel_rays(K, M, 1, 1, pixels=pix)
        out.append(o + np.asarray(dep, dtype=np.float64).reshape(-1)[:, None] * d)
    return out


def partners(F: int, most: int = MAX_PARTNERS) -> np.ndarray:
    """``(F, F)`` bool: the frame pairs the checks compare: all of them up to ``most + 1`` frames,
    else those whose distance in the object's frame order is a multiple of ``ceil(F / most)``."""
    step = max(1, -(-F // most))
    i, j = np.mgrid[0:F, 0:F]
    return (i != j) & (np.abs(i - j) % step == 0)


def thinned(points: list[np.ndarray], most: int = MAX_POINTS) -> list[np.ndarray]:
    """At most ``most`` of each frame's points, evenly spaced."""
    return [p if len(p) <= most else p[np.linspace(0, len(p) - 1, most).astype(np.int64)] for p in points]


def mask_misses(frames: np.ndarray, cam_to_obj: np.ndarray, points: list[np.ndarray], masks: np.ndarray,
                object_id: int, anchor: int, K: np.ndarray, tol_px: float) -> np.ndarray:
    """``(F, F)``: entry ``[i, j]`` is the share of frame i's points that, projected into frame j,
    miss the object's mask there (dilated by ``tol_px``); NaN on the diagonal, for pairs
    :func:`partners` skips, and where no point could be tested (at most :data:`MAX_POINTS` points
    of frame i are projected).

    Points behind the camera or outside the image are not tested, nor those landing on another
    object that may hide them (:func:`silhouette_masks`).
    """
    F = len(frames)
    H, W = masks.shape[1:]
    out = np.full((F, F), np.nan)
    pairs = partners(F)
    points = thinned(points)
    for j, t in enumerate(frames):
        own, hide = silhouette_masks(masks[int(t)], object_id, anchor, tol_px)
        for i in np.flatnonzero(pairs[:, j]):
            if not len(points[i]):
                continue
            _, _, pix, inside = project_pixels(points[i], K, cam_to_obj[j], W, H)
            u, v = pix[inside, 0], pix[inside, 1]
            tested = ~hide[v, u]
            if tested.any():
                out[i, j] = float(np.mean(~own[v, u][tested]))
    return out


def _disk(radius: float) -> np.ndarray:
    r = max(0, int(np.ceil(radius)))
    return np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= radius + 1e-9


def silhouette_masks(mask: np.ndarray, object_id: int, anchor: int, tol_px: float) -> tuple[np.ndarray, np.ndarray]:
    """``(own, hide)`` of one frame's instance ids ``mask (H, W)``: the object's mask dilated by
    ``tol_px``, and where another object may hide it (any other object for the anchor; any but
    the anchor, which lies behind the objects it holds, for the others; never the no-object id)."""
    own = mask == object_id
    if tol_px >= 1:
        own = ndimage.binary_dilation(own, structure=_disk(tol_px))
    hide = (mask != object_id) & (mask != 255)
    if object_id != anchor:
        hide &= mask != anchor
    return own, hide


def silhouette_agreement(points: np.ndarray, cam_to_obj: np.ndarray, mask: np.ndarray, object_id: int, anchor: int,
                         K: np.ndarray, tol_px: float) -> tuple[float, float]:
    """How well the object's points ``(N, 3)`` seen with pose ``cam_to_obj (4, 4)`` fit its
    silhouette in one frame's instance ids ``mask (H, W)``: ``(miss, cover)``, the share of the
    tested points off the mask dilated by ``tol_px`` (as :func:`mask_misses`), and the share of the
    object's visible mask pixels within ``tol_px`` of a point that lands on it. A pose off the
    silhouette raises the first; one that shrinks the object inside it (too far away) lowers the
    second. NaN where nothing could be tested."""
    H, W = mask.shape
    own, hide = silhouette_masks(mask, object_id, anchor, tol_px)
    _, _, pix, inside = project_pixels(points, K, cam_to_obj, W, H)
    u, v = pix[inside, 0], pix[inside, 1]
    tested = ~hide[v, u]
    miss = float(np.mean(~own[v, u][tested])) if tested.any() else float("nan")
    visible = mask == object_id
    hit = np.zeros_like(visible)
    on = visible[v, u]
    hit[v[on], u[on]] = True
    if tol_px >= 1:
        hit = ndimage.binary_dilation(hit, structure=_disk(tol_px))
    cover = float(np.mean(hit[visible])) if visible.any() else float("nan")
    return miss, cover


def frame_medians(pairs: np.ndarray) -> np.ndarray:
    """``(F,)``: per frame the median over the other frames of the mean of ``pairs[i, j]`` and
    ``pairs[j, i]`` (:func:`mask_misses`, :func:`depth_disagreement`; NaN entries skipped); NaN for
    a frame no pair could test."""
    F = len(pairs)
    both = np.stack([pairs, pairs.T])
    n = np.isfinite(both).sum(axis=0)
    sym = np.divide(np.nansum(both, axis=0), n, out=np.full(pairs.shape, np.nan), where=n > 0)
    out = np.full(F, np.nan)
    for i in range(F):
        row = np.delete(sym[i], i)
        row = row[np.isfinite(row)]
        if len(row):
            out[i] = float(np.median(row))
    return out


def depth_disagreement(cam_to_obj: np.ndarray, sparse_pix: list[np.ndarray], sparse_depth: list[np.ndarray],
                       points: list[np.ndarray], K: np.ndarray, width: int, height: int, tol_px: float) -> np.ndarray:
    """``(F, F)``: entry ``[i, j]`` is the median relative difference between the depth of frame
    i's points projected into frame j and the depth SfM observed at the nearest of frame j's sparse
    pixels within ``tol_px``; NaN on the diagonal, for pairs :func:`partners` skips, and where no
    point has such a neighbour (at most :data:`MAX_POINTS` points of frame i are projected)."""
    F = len(cam_to_obj)
    out = np.full((F, F), np.nan)
    pairs = partners(F)
    points = thinned(points)
    for j in range(F):
        pix_j = np.asarray(sparse_pix[j], dtype=np.float64).reshape(-1, 2) + 0.5
        if not len(pix_j):
            continue
        tree = cKDTree(pix_j)
        dep_j = np.asarray(sparse_depth[j], dtype=np.float64).reshape(-1)
        for i in np.flatnonzero(pairs[:, j]):
            if not len(points[i]):
                continue
            uv, z, _, inside = project_pixels(points[i], K, cam_to_obj[j], width, height)
            if not inside.any():
                continue
            dist, idx = tree.query(uv[inside], distance_upper_bound=max(tol_px, 0.5))
            near = np.isfinite(dist)
            if near.any():
                out[i, j] = float(np.median(np.abs(z[inside][near] / dep_j[idx[near]] - 1.0)))
    return out


def consistent_core(pairs: np.ndarray, threshold: float) -> np.ndarray:
    """``(F,)`` bool: the frames left after removing, one at a time, the frame whose median
    disagreement with the remaining ones (:func:`frame_medians` of ``pairs``) is the largest, until
    none exceeds ``threshold`` (or two are left). Frames posed wrong disagree with every right
    frame, so they go first; a right frame disagrees only with the wrong ones, which are gone by
    then. Depths wrong in every frame leave no core."""
    keep = np.ones(len(pairs), dtype=bool)
    while keep.sum() > 2:
        idx = np.flatnonzero(keep)
        med = frame_medians(pairs[np.ix_(idx, idx)])
        if not np.isfinite(med).any() or not np.nanmax(med) > threshold:
            break
        keep[idx[int(np.nanargmax(med))]] = False
    return keep


def orientation_kinks(frames: np.ndarray, cam_to_obj: np.ndarray, timestamps: np.ndarray, anchor_frames: np.ndarray,
                      anchor_cam_to_obj: np.ndarray) -> np.ndarray:
    """``(F,)`` degrees: per frame, how far the object's orientation in the anchor's frame
    (``R_anchor(t) R_k(t)^T``) lies from the slerp of its neighbours' at its timestamp; NaN at the
    ends and where the anchor has no pose (the neighbours are the nearest frames both registered)."""
    slot = {int(t): n for n, t in enumerate(anchor_frames)}
    both = [n for n, t in enumerate(frames) if int(t) in slot]
    out = np.full(len(frames), np.nan)
    if len(both) < 3:
        return out
    Wk = [anchor_cam_to_obj[slot[int(frames[n])], :3, :3] @ cam_to_obj[n, :3, :3].T for n in both]
    ts = np.asarray(timestamps, dtype=np.float64)[[int(frames[n]) for n in both]]
    for a in range(1, len(both) - 1):
        span = ts[a + 1] - ts[a - 1]
        alpha = (ts[a] - ts[a - 1]) / span if span > 0 else 0.5
        step = Rotation.from_matrix(Wk[a - 1].T @ Wk[a + 1]).as_rotvec() * alpha
        pred = Wk[a - 1] @ Rotation.from_rotvec(step).as_matrix()
        out[both[a]] = float(np.degrees(Rotation.from_matrix(pred.T @ Wk[a]).magnitude()))
    return out


@dataclass
class ObjectObservations:
    """What the checks read of one object's reconstruction (its own frame and unit).

    ``reprojection_error_px``: the reconstruction's mean reprojection error in the input frames'
    pixels, which sets the mask tolerance."""

    id: int
    frames: np.ndarray
    cam_to_obj: np.ndarray
    sparse_pix: list[np.ndarray]
    sparse_depth: list[np.ndarray]
    reprojection_error_px: float


@dataclass
class Verdict:
    """The checks' outcome for one object: its figures, what is wrong and what is done."""

    id: int
    figures: dict = field(default_factory=dict)
    #: ``masks``: frames whose pose sends the object's points off its masks; ``depth_frames``: a
    #: minority of frames whose depths disagree with the others'; ``object_masks``: the rest still
    #: misses its masks (poses wrong as a whole); ``depths``: the rest's depths disagree;
    #: ``orientation``: the rest's orientation jitters against the anchor's cameras (named, kept).
    reasons: list[str] = field(default_factory=list)
    #: Frames dropped from the object (``masks`` and ``depth_frames``).
    bad_frames: list[int] = field(default_factory=list)
    #: Whether training keeps the object's sparse depths; whether its SfM is dropped.
    use_depths: bool = True
    drop: bool = False
    message: str = ""

    @property
    def action(self) -> str:
        """``keep``, ``drop``, or ``repair`` (frames dropped) and/or ``no_depth``, joined by ``+``."""
        if self.drop:
            return "drop"
        parts = (["repair"] if self.bad_frames else []) + ([] if self.use_depths else ["no_depth"])
        return "+".join(parts) or "keep"

    def record(self) -> dict:
        """The verdict as ``preprocess_report.json`` and ``inputs.json`` hold it."""
        return {"verdict": "inconsistent" if self.reasons else "consistent", "reasons": self.reasons,
                "action": self.action, "bad_frames": self.bad_frames, "message": self.message, **self.figures}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _per_frame(frames: np.ndarray, values: np.ndarray) -> dict[str, float | None]:
    return {str(int(t)): _finite(v) for t, v in zip(frames, values)}


@dataclass
class _Measured:
    """The raw figures of one object (:func:`_measure`)."""

    tol: float
    miss: np.ndarray  # (F,) frame_medians of mask_misses
    depth_pairs: np.ndarray  # (F, F) depth_disagreement
    kinks: np.ndarray  # (F,) orientation_kinks

    @property
    def mask_figure(self) -> float:
        return float(np.nanmedian(self.miss)) if np.isfinite(self.miss).any() else float("nan")

    @property
    def depth_figure(self) -> float:
        return float(np.nanmedian(self.depth_pairs)) if np.isfinite(self.depth_pairs).any() else float("nan")

    @property
    def kink_figure(self) -> float:
        return float(np.nanmedian(self.kinks)) if np.isfinite(self.kinks).any() else float("nan")


def _measure(o: ObjectObservations, masks: np.ndarray, K: np.ndarray, timestamps: np.ndarray, anchor: int,
             anchor_obs: ObjectObservations | None) -> _Measured:
    H, W = masks.shape[1:]
    err = o.reprojection_error_px if np.isfinite(o.reprojection_error_px) else 0.0
    tol = 1.0 + 3.0 * err
    pts = frame_points(o.cam_to_obj, o.sparse_pix, o.sparse_depth, K)
    miss = frame_medians(mask_misses(o.frames, o.cam_to_obj, pts, masks, o.id, anchor, K, tol))
    depth = depth_disagreement(o.cam_to_obj, o.sparse_pix, o.sparse_depth, pts, K, W, H, tol)
    kinks = (orientation_kinks(o.frames, o.cam_to_obj, timestamps, anchor_obs.frames, anchor_obs.cam_to_obj)
             if anchor_obs is not None and o.id != anchor else np.full(len(o.frames), np.nan))
    return _Measured(tol, miss, depth, kinks)


def _subset(o: ObjectObservations, keep: np.ndarray) -> ObjectObservations:
    """``o`` on the frames ``keep`` (a boolean mask over its frames)."""
    idx = np.flatnonzero(keep)
    return ObjectObservations(o.id, o.frames[idx], o.cam_to_obj[idx], [o.sparse_pix[i] for i in idx],
                              [o.sparse_depth[i] for i in idx], o.reprojection_error_px)


def _threshold(figures: dict[int, float], oid: int, ratio: float, floor: float, alone: float = float("nan")) -> float:
    """``max(floor, ratio * median of the other objects' figures)``; ``alone`` without another object."""
    others = [x for k, x in figures.items() if k != oid and np.isfinite(x)]
    return max(floor, ratio * float(np.median(others))) if others else alone


def assess_scene(objects: list[ObjectObservations], masks: np.ndarray, K: np.ndarray, timestamps: np.ndarray,
                 anchor: int, min_frames: int, names: dict[int, str] | None = None) -> dict[int, Verdict]:
    """Check every object's reconstruction against the masks, its other frames, the other objects
    and the anchor, and decide what to do with it (module docstring). ``masks (T, H, W)``: instance
    ids of the video the sparse pixels index; ``min_frames``: the fewest frames an object may keep.

    Frames that contradict the masks (most points miss) or, a minority, whose depths disagree with
    the other frames' are removed first and the object measured again without them; what remains
    is judged as a whole: points off its masks in its typical frame (:data:`MASK_RATIO` times the
    other objects', at least :data:`MASK_FLOOR`) drop it, depths that disagree take its depths, an
    orientation that jitters against the anchor's (:data:`KINK_RATIO` times the other movers'
    median kink, at least :data:`KINK_FLOOR`) is named.
    The anchor is never dropped here; the caller stops on an anchor whose verdict says ``drop``."""
    names = names or {}
    anchor_obs = next((o for o in objects if o.id == anchor), None)
    first = {o.id: _measure(o, masks, K, timestamps, anchor, anchor_obs) for o in objects}
    mask_fig = {k: m.mask_figure for k, m in first.items()}
    depth_fig = {k: m.depth_figure for k, m in first.items()}
    kink_fig = {k: m.kink_figure for k, m in first.items()}  # NaN for the anchor: not among the movers
    verdicts = {}
    for o in objects:
        m = first[o.id]
        depth_thr = _threshold(depth_fig, o.id, DEPTH_RATIO, DEPTH_FLOOR)
        mask_thr = _threshold(mask_fig, o.id, MASK_RATIO, MASK_FLOOR)
        kink_thr = (float("nan") if o.id == anchor
                    else _threshold(kink_fig, o.id, KINK_RATIO, KINK_FLOOR, alone=KINK_FLOOR))
        frame_depth = frame_medians(m.depth_pairs)
        v = Verdict(o.id, figures={
            "mask_tolerance_px": m.tol,
            "frame_mask_miss": _per_frame(o.frames, m.miss),
            "frame_depth_disagreement": _per_frame(o.frames, frame_depth),
            "frame_orientation_kink_deg": {k: x for k, x in _per_frame(o.frames, m.kinks).items() if x is not None},
        })
        off_masks = {int(t) for t, x in zip(o.frames, m.miss) if np.isfinite(x) and x > FRAME_MISS}
        core = consistent_core(m.depth_pairs, depth_thr) if np.isfinite(depth_thr) else np.ones(len(o.frames), bool)
        off_depth = {int(t) for t in o.frames[~core]}
        if 2 * int(core.sum()) < len(o.frames):
            off_depth = set()  # no half of the frames agrees: the depths' fault, judged below as a whole
        if off_masks:
            v.reasons.append("masks")
        if off_depth:
            v.reasons.append("depth_frames")
        v.bad_frames = sorted(off_masks | off_depth)
        rest = o
        if v.bad_frames and len(o.frames) - len(v.bad_frames) >= max(min_frames, 2):
            rest = _subset(o, ~np.isin(o.frames, v.bad_frames))
            m = _measure(rest, masks, K, timestamps, anchor, anchor_obs)
        v.figures.update(mask_miss=_finite(m.mask_figure), mask_miss_threshold=_finite(mask_thr),
                         depth_disagreement=_finite(m.depth_figure), depth_disagreement_threshold=_finite(depth_thr),
                         orientation_kink_deg=_finite(m.kink_figure), orientation_kink_threshold_deg=_finite(kink_thr))
        if np.isfinite(mask_thr) and np.isfinite(m.mask_figure) and m.mask_figure > mask_thr:
            v.reasons.append("object_masks")
        if np.isfinite(depth_thr) and np.isfinite(m.depth_figure) and m.depth_figure > depth_thr:
            v.reasons.append("depths")
            v.use_depths = False
        if np.isfinite(kink_thr) and np.isfinite(m.kink_figure) and m.kink_figure > kink_thr:
            v.reasons.append("orientation")
        _decide(v, len(o.frames), min_frames, o.id == anchor, f"object {o.id}" + (f" ({names[o.id]})" if o.id in names else ""))
        verdicts[o.id] = v
    return verdicts


def _decide(v: Verdict, registered: int, min_frames: int, is_anchor: bool, label: str) -> None:
    """Set what is done with ``v``'s object and its one-line ``v.message`` from its reasons."""
    what = []
    if "masks" in v.reasons:
        what.append("its poses send its points off its masks")
    if "depth_frames" in v.reasons:
        what.append("its depths disagree with its other frames'")
    if v.bad_frames:
        what[-1] += f" in {len(v.bad_frames)} of {registered} frames ({', '.join(map(str, v.bad_frames))})"
    f = v.figures
    if "object_masks" in v.reasons:
        what.append(f"{100 * f['mask_miss']:.0f}% of its points miss its masks in its typical frame "
                    f"(threshold {100 * f['mask_miss_threshold']:.0f}%)")
    if "depths" in v.reasons:
        what.append(f"its sparse depths disagree across frames by {100 * f['depth_disagreement']:.1f}% "
                    f"(threshold {100 * f['depth_disagreement_threshold']:.1f}%)")
    if "orientation" in v.reasons:
        what.append(f"its orientation against the anchor's cameras jumps by {f['orientation_kink_deg']:.1f} degrees "
                    f"in its typical frame (threshold {f['orientation_kink_threshold_deg']:.1f})")
    if not what:
        return
    left = registered - len(v.bad_frames)
    if "object_masks" in v.reasons or left < min_frames or 2 * len(v.bad_frames) >= registered:
        v.drop = True
        todo = ("the anchor cannot be dropped; use more frames, a higher resolution or more texture" if is_anchor
                else "its SfM is not used: training without it")
    else:
        todo = "; ".join(([f"those frames are dropped ({left} kept)"] if v.bad_frames else [])
                         + ([] if v.use_depths else ["it trains without its sparse depths"])
                         + (["its poses are trained as found (a spin about a round object's axis leaves its shape "
                             "right; a wrong turn puts its contacts off)"] if "orientation" in v.reasons else []))
    v.message = f"{label}: SfM inconsistent: {'; '.join(what)}; {todo}"

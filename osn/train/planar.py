"""The anchor's planes, found in its sparse depths of every frame, as depth targets where it has none.

SfM finds few points on a weakly textured floor, and photometric consistency alone draws such a
floor too near wherever its depths are missing, even from exact poses; that cuts the bound of every
object standing on it (docs/training.md, Losses). The anchor is static: its sparse depths of
all frames lie in one coordinate frame, where a floor or a wall is one plane however few points a
single frame gives it. A plane that enough points of several frames support, and that hides none
of the surfaces they show and lies behind none (:func:`kept_planes`), gives, in every frame, a depth on each
pixel whose ray meets it inside the hull of its points, the nearest such plane along the ray (a
camera inside a room sees the nearest wall), whether the anchor is visible there or hidden by an
object. Nothing is extrapolated: a ray that meets no plane inside its points' hull gets no
target, so an anchor that is not piecewise planar gets none.

Pure numpy on :class:`~osn.preprocess.inputs.SceneInputs`; nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay, QhullError

from scenecore.cameras import pixel_rays

from osn.preprocess.inputs import IGNORE_ID, SceneInputs

#: A point supports a plane when its distance to it is at most this share of its depth: SfM's
#: sparse depths scatter by a few per cent about the surface, so a plane's own points are kept
#: while a neighbouring surface's, at any angle to it, fall out a few pixels from the seam.
PLANE_TOLERANCE = 0.03
#: A plane counts when this many of the anchor's points support it, from at least
#: :data:`MIN_PLANE_FRAMES` frames (a surface seen once is as likely a texture's outliers).
MIN_PLANE_POINTS = 30
MIN_PLANE_FRAMES = 3
#: At most this many plane searches (a box room has six planes); they stop earlier when one finds
#: no plane with enough support.
MAX_PLANES = 8
#: A plane's support is flat when a quadric through it leaves no less than ``1 / FLAT_RATIO`` of the
#: plane's residual (relative to depth): scattered depths about a plane gain nothing from the
#: quadric's three more terms, a curved surface's points within the tolerance band do (a sphere's
#: cap fits a plane to a few per cent and a quadric exactly).
FLAT_RATIO = 1.2
#: ... unless the plane's median residual is below this share of depth anyway: a bend that small
#: (a rendered floor's, 1e-4) moves no depth target enough to matter.
FLAT_FLOOR = 1e-3
#: A plane is dropped when, of the anchor's sparse depths whose rays meet it first among the planes
#: kept (inside its hull: the depths whose target it would set), more than this share lie off it by
#: more than :data:`PLANE_TOLERANCE` of their depth, on either side: behind it (it would hide what
#: the video shows) or in front of it (it is not the nearest surface there: SfM's back wall met by
#: the floor's rays when the floor is not kept). SfM's outliers about a surface the video shows are
#: a minority of its depths; a plane where the anchor is not has most of them off it.
MAX_CONTRADICTED = 0.5
#: RANSAC draws of three points per plane searched (a plane holding a tenth of the points is
#: drawn with probability 1 - (1 - 0.001)^512, about 0.4 per search, and its inliers are refit).
RANSAC_DRAWS = 512


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . x + offset = 0`` in anchor coordinates (``normal`` of unit length), the
    2D coordinates of its supporting points in the plane (``basis`` rows span it) and how many
    points and frames support it."""

    normal: np.ndarray
    offset: float
    basis: np.ndarray
    hull: Delaunay
    points: int
    frames: int


@dataclass(frozen=True)
class PlanarDepths:
    """Depth targets of the anchor: flat ``frame * H * W + pixel`` indices and planar depths in
    the anchor's unit, plus the planes they come from."""

    flat: np.ndarray
    depth: np.ndarray
    planes: list[Plane]

    def record(self) -> dict:
        """Plain data for a run's records."""
        return {"planes": [{"points": p.points, "frames": p.frames} for p in self.planes],
                "targets": int(len(self.depth))}


def anchor_points(inputs: SceneInputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The anchor's sparse depths of every frame in anchor coordinates: points ``(N, 3)``, each
    one's depth in its frame ``(N,)`` and frame index ``(N,)``."""
    o = inputs.objects[inputs.anchor_pos]
    pts, dep, frm = [], [], []
    for slot, t in enumerate(o.frames):
        pix, d = o.sparse_pix[slot], o.sparse_depth[slot]
        if len(d) == 0:
            continue
        _, dirs = pixel_rays(inputs.K, np.eye(4), inputs.width, inputs.height, pix)
        cam = dirs * d[:, None]
        pose = o.cam_to_obj[slot]
        pts.append(cam @ pose[:3, :3].T + pose[:3, 3])
        dep.append(np.asarray(d, dtype=np.float64))
        frm.append(np.full(len(d), t))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    return np.concatenate(pts), np.concatenate(dep), np.concatenate(frm)


def _fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through ``points (N >= 3, 3)``: unit normal and offset."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    return normal, -float(normal @ centre)


def _in_plane(normal: np.ndarray) -> np.ndarray:
    """Two unit rows spanning the plane with normal ``normal``."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def _flat(p: np.ndarray, depth: np.ndarray, normal: np.ndarray, offset: float, basis: np.ndarray) -> bool:
    """Whether points ``p (N, 3)`` (depths ``(N,)``) lie about the plane as scatter, not as a curve:
    the median absolute residual (relative to depth) of the plane against a quadric's over the
    plane's coordinates (:data:`FLAT_RATIO`); medians, so a few stray depths decide nothing."""
    h = p @ normal + offset
    u, v = (p @ basis.T).T
    design = np.stack([u * u, u * v, v * v, u, v, np.ones_like(u)], axis=1)
    coef = np.linalg.lstsq(design, h, rcond=None)[0]
    plane = np.median(np.abs(h / depth))
    quadric = np.median(np.abs((h - design @ coef) / depth))
    return bool(plane <= FLAT_RATIO * quadric + FLAT_FLOOR)


def fit_planes(points: np.ndarray, depth: np.ndarray, frames: np.ndarray, seed: int = 0,
               tolerance: float = PLANE_TOLERANCE, min_points: int = MIN_PLANE_POINTS,
               min_frames: int = MIN_PLANE_FRAMES, max_planes: int = MAX_PLANES) -> list[Plane]:
    """Planes supported by ``points (N, 3)`` (``depth (N,)`` each point's depth in its frame,
    ``frames (N,)``), found one after another by RANSAC on the points no earlier plane holds and
    refit by least squares on their supporting points. Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    left = np.arange(len(points))
    planes: list[Plane] = []
    for _ in range(max_planes):  # searches, counted whether a plane is kept or not
        if len(left) < min_points:
            break
        p = points[left]
        tol = tolerance * depth[left]
        draws = np.stack([rng.choice(len(left), 3, replace=False) for _ in range(RANSAC_DRAWS)])
        a, b, c = p[draws[:, 0]], p[draws[:, 1]], p[draws[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12 * np.maximum(np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - a, axis=1), 1e-300)
        if not ok.any():
            break
        n = n[ok] / norm[ok, None]
        off = -np.einsum("ij,ij->i", n, a[ok])
        support = np.abs(p @ n.T + off) <= tol[:, None]  # (N, draws)
        best = int(np.argmax(support.sum(axis=0)))
        # The plane's own scatter, measured on its support (median absolute residual relative to
        # depth, as a standard deviation): it is fit again to the points within three of it, so
        # a neighbouring surface's points near the seam do not tilt it, and exact depths give a
        # thin plane, SfM's a thick one. Every point of the search band is then taken out.
        normal, offset = n[best], float(off[best])
        d = depth[left]
        band = tol
        for _ in range(3):
            r = np.abs(p @ normal + offset)
            within = r <= band
            scatter = 1.4826 * float(np.median(r[within] / d[within]))
            core = r <= np.minimum(3.0 * scatter * d, tol)
            if core.sum() < 3:
                break
            normal, offset = _fit(p[core])
            band = np.minimum(3.0 * scatter * d, tol)
        r = np.abs(p @ normal + offset)
        inl, taken = r <= band, r <= tol
        if inl.sum() < min_points or len(np.unique(frames[left][inl])) < min_frames:
            break
        basis = _in_plane(normal)
        if not _flat(p[inl], d[inl], normal, offset, basis):
            left = left[~taken]  # a curved surface's points: no plane of theirs, none through them
            continue
        try:
            hull = Delaunay(p[inl] @ basis.T)
        except QhullError:  # collinear support: no area to interpolate over
            left = left[~taken]
            continue
        planes.append(Plane(normal, offset, basis, hull, int(inl.sum()), int(len(np.unique(frames[left][inl])))))
        left = left[~taken]
    return planes


def nearest_planes(planes: list[Plane], dirs: np.ndarray, cam_to_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray the depth of the nearest plane it meets inside its points' hull and that plane's
    index in ``planes``: ``dirs (N, 3)`` camera-frame directions with unit z, ``cam_to_obj (4, 4)``;
    NaN and -1 where it meets none."""
    best = np.full(len(dirs), np.inf)
    which = np.full(len(dirs), -1, dtype=np.int64)
    world = dirs @ cam_to_obj[:3, :3].T
    origin = cam_to_obj[:3, 3]
    for k, pl in enumerate(planes):
        along = world @ pl.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(pl.normal @ origin + pl.offset) / along
        hit = np.isfinite(t) & (t > 0) & (t < best)
        if not hit.any():
            continue
        idx = np.nonzero(hit)[0]
        xy = (origin + t[idx, None] * world[idx]) @ pl.basis.T
        inside = idx[pl.hull.find_simplex(xy) >= 0]
        best[inside], which[inside] = t[inside], k
    return np.where(np.isfinite(best), best, np.nan), which


def plane_depths(planes: list[Plane], dirs: np.ndarray, cam_to_obj: np.ndarray) -> np.ndarray:
    """Per ray the depth of the nearest plane it meets inside its points' hull (NaN where none);
    :func:`nearest_planes`."""
    return nearest_planes(planes, dirs, cam_to_obj)[0]


def contradicted_shares(planes: list[Plane], inputs: SceneInputs, tolerance: float = PLANE_TOLERANCE) -> np.ndarray:
    """``(P,)``: per plane, of the anchor's sparse depths whose rays meet it first among
    ``planes`` (inside its hull: the depths whose target it would set), the share lying off it by
    more than ``tolerance`` of their depth, behind it (it would hide them) or in front of it (it
    lies behind what they show); 0 for a plane that sets no depth's target. A plane behind
    another one is judged only where it is the nearest."""
    o = inputs.objects[inputs.anchor_pos]
    met, behind, front = (np.zeros(len(planes), dtype=np.int64) for _ in range(3))
    for slot in range(len(o.frames)):
        pix, d = o.sparse_pix[slot], np.asarray(o.sparse_depth[slot], dtype=np.float64)
        if len(d) == 0:
            continue
        _, dirs = pixel_rays(inputs.K, np.eye(4), inputs.width, inputs.height, pix)
        at, which = nearest_planes(planes, dirs, o.cam_to_obj[slot])
        hit = which >= 0
        met += np.bincount(which[hit], minlength=len(planes))
        behind += np.bincount(which[hit], weights=at[hit] < d[hit] * (1.0 - tolerance), minlength=len(planes)).astype(np.int64)
        front += np.bincount(which[hit], weights=d[hit] < at[hit] * (1.0 - tolerance), minlength=len(planes)).astype(np.int64)
    return (behind + front) / np.maximum(met, 1)


def kept_planes(planes: list[Plane], inputs: SceneInputs, most: float = MAX_CONTRADICTED) -> list[Plane]:
    """``planes`` less those the anchor's depths contradict (:func:`contradicted_shares` above
    ``most``), dropped one at a time, the most contradicted first, each time judged again among
    those left (a dropped plane in front of another gives the depths behind it to that one)."""
    keep = list(planes)
    while keep:
        shares = contradicted_shares(keep, inputs)
        worst = int(np.argmax(shares))
        if shares[worst] <= most:
            break
        del keep[worst]
    return keep


def planar_depths(inputs: SceneInputs, seed: int = 0) -> PlanarDepths:
    """Depth targets of the anchor from its planes (:func:`fit_planes`, less those its own depths
    contradict: :func:`kept_planes`) on every pixel of every frame it is posed in, but pixels of objects preprocessing dropped and pixels showing nothing."""
    pts, dep, frm = anchor_points(inputs)
    planes = kept_planes(fit_planes(pts, dep, frm, seed), inputs)
    o = inputs.objects[inputs.anchor_pos]
    H, W = inputs.height, inputs.width
    if not planes:
        return PlanarDepths(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32), [])
    _, dirs = pixel_rays(inputs.K, np.eye(4), W, H)
    flat, depth = [], []
    for slot, t in enumerate(o.frames):
        d = plane_depths(planes, dirs, o.cam_to_obj[slot])
        m = inputs.masks[t].reshape(-1)
        keep = np.isfinite(d) & (m != IGNORE_ID) & np.isin(m, [ob.id for ob in inputs.objects])
        flat.append(int(t) * H * W + np.nonzero(keep)[0])
        depth.append(d[keep])
    return PlanarDepths(np.concatenate(flat), np.concatenate(depth).astype(np.float32), planes)

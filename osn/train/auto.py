"""What each ``auto`` option of :class:`osn.train.config.TrainConfig` becomes on a scene's inputs.

Every rule reads a measured property of the inputs (whether their depths agree across frames,
how many pixels a box spans), never their source: the oracle's inputs and SfM's go through the
same rules.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from scenecore.cameras import project

from osn.model.fields import FieldConfig
from osn.preprocess.inputs import SceneInputs


#: ``depth_robust: auto`` on noisy inputs (:mod:`osn.preprocess.depth_noise`; SfM's): the Cauchy
#: scale of the sparse-depth loss in multiples of the batch's median residual (docs/preprocess.md).
DEPTH_ROBUST_NOISY = 3.0


def by_noise(value: float | str, noisy: bool, exact: float, other: float) -> float:
    """An option that may be ``auto``: ``exact`` on inputs whose depths agree across frames,
    ``other`` on noisy ones (:func:`osn.preprocess.depth_noise.depth_consistency`: a measured
    property, never the inputs' source); a number stays itself. The resolvers below say, per
    option, why the two differ."""
    if value == "auto":
        return other if noisy else exact
    return float(value)


#: ``w_edge: auto`` on noisy inputs: the weight of the silhouette-depth term
#: (:func:`osn.train.losses.edge_excess`; docs/training.md, "Losses").
W_EDGE_NOISY = 1.0


def resolve_w_edge(value: float | str, noisy: bool) -> float:
    """The silhouette-depth term's weight: ``auto`` is off on exact inputs, whose silhouettes need
    no correction (there the term lowers the valid set's IoU), and :data:`W_EDGE_NOISY` on noisy
    ones, where the objects' fields read their silhouettes too far and cut the contact bounds
    tight; the term restores their recall (measurements in docs/experiments/)."""
    return by_noise(value, noisy, 0.0, W_EDGE_NOISY)


#: ``anchor_guide_samples: auto``: the guide pass's density samples along each of the anchor's
#: rays (:func:`osn.model.volume.guided_positions`) where its grid under-resolves what it sees.
ANCHOR_GUIDE_SAMPLES = 64


def resolve_anchor_guide_samples(value: int | str, fcfg: FieldConfig, inputs: SceneInputs) -> int:
    """The anchor's guide samples (0: even samples): ``auto`` is :data:`ANCHOR_GUIDE_SAMPLES`
    unless the anchor's box spans no more pixels than its grid has voxels (:func:`anchor_pixels`;
    without sparse depths it is on). Where the room's grid is coarser than the pixels that see
    it, even samples miss its surfaces and the guide finds them, for best of N and the valid set
    alike, on SfM's inputs and the oracle's; where the grid already has a voxel per pixel (the
    tiny test scene) the guide only costs recall (measurements in docs/experiments/)."""
    if value != "auto":
        return int(value)
    n = anchor_pixels(inputs)
    return 0 if n is not None and n <= fcfg.resolution else ANCHOR_GUIDE_SAMPLES


def checkpoint_anchor_guide_samples(ckpt: dict[str, Any], source: str) -> int:
    """The anchor's guide samples a checkpoint's training used (its ``anchor_guide``). A checkpoint
    without that key does not say: its config's ``auto`` meant :data:`ANCHOR_GUIDE_SAMPLES` on SfM
    inputs and 0 on the oracle's, and a config without ``anchor_guide_samples`` trained without
    the guide (0)."""
    if "anchor_guide" in ckpt:
        return int(ckpt["anchor_guide"])
    value = ckpt["config"].get("anchor_guide_samples", 0)
    return int(value) if value != "auto" else (0 if source == "oracle" else ANCHOR_GUIDE_SAMPLES)


def resolve_depth_robust(value: float | str, noisy: bool) -> float:
    """The sparse-depth loss's robustness: ``auto`` is the squared error on exact depths (a robust
    loss there lowers the valid set's IoU) and :data:`DEPTH_ROBUST_NOISY` on noisy ones, which
    hold SfM's phantom points."""
    return by_noise(value, noisy, 0.0, DEPTH_ROBUST_NOISY)


#: ``field.object_resolution: auto`` keeps at least this many voxels per axis (an object a few
#: pixels wide still gets a grid that trilinear interpolation can shape).
MIN_OBJECT_RESOLUTION = 16


def footprint_resolution(bbox: np.ndarray, cam_to_obj: np.ndarray, K: np.ndarray, cap: int) -> int:
    """Voxels per axis at which one voxel is about one pixel of the training frames: the median,
    over the frames that see the whole box in front of the camera, of the box's projected extent
    (the longer side of its eight corners' image bounding box, in pixels), rounded and clamped to
    ``[MIN_OBJECT_RESOLUTION, cap]``; ``cap`` when no frame sees the box whole (a camera inside it).

    ``bbox (2, 3)`` min / max corner in object units, ``cam_to_obj (F, 4, 4)`` OpenCV camera-to-object
    poses, ``K (3, 3)`` intrinsics.
    """
    lo, hi = np.asarray(bbox, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    extents = []
    for pose in np.asarray(cam_to_obj, dtype=np.float64):
        uv, depth = project(corners, K, pose)
        if np.all(depth > 0) and np.all(np.isfinite(uv)):
            extents.append(float(np.ptp(uv, axis=0).max()))
    if not extents:
        return int(cap)
    return int(np.clip(round(float(np.median(extents))), min(MIN_OBJECT_RESOLUTION, cap), cap))


def object_resolutions(fcfg: FieldConfig, inputs: SceneInputs, noisy: bool) -> list[list[int]]:
    """Per object position its fields' resolution schedule (:meth:`FieldConfig.resolutions`): the
    anchor's ends at ``field.resolution``, every other object's at ``field.object_resolution``
    (0: ``resolution``; never above it). ``auto``: :func:`footprint_resolution` on noisy inputs
    (``noisy``, :mod:`osn.preprocess.depth_noise`; SfM's), where a small object's voxels at
    ``resolution`` are a fraction of a pixel and coarser ones, a voxel per pixel, render its test
    pixels and best of N better; ``resolution`` on exact inputs, whose contacts lose recall on
    coarser grids (measurements in docs/experiments/)."""
    out = []
    for k, o in enumerate(inputs.objects):
        final = fcfg.resolution
        r = fcfg.object_resolution
        if k != inputs.anchor_pos and r == "auto" and noisy:
            final = footprint_resolution(o.bbox, o.cam_to_obj, inputs.K, fcfg.resolution)
        elif k != inputs.anchor_pos and r not in ("auto", 0):
            final = min(int(r), fcfg.resolution)
        out.append(fcfg.resolutions(final))
    return out


#: ``field.anchor_planes: auto`` keeps the anchor's colour planes within these sizes (texels per side).
MIN_ANCHOR_PLANES, MAX_ANCHOR_PLANES = 16, 1024


def anchor_pixels(inputs: SceneInputs) -> float | None:
    """How many pixels the anchor's box spans: the longest side of its box over the pixel
    footprint at the median of its sparse depths (depth / focal length; both in the anchor's unit,
    so the figure does not depend on it). None when the anchor has no sparse depth."""
    a = inputs.objects[inputs.anchor_pos]
    depths = np.concatenate([np.asarray(d, dtype=np.float64).reshape(-1) for d in a.sparse_depth] + [np.zeros(0)])
    depths = depths[np.isfinite(depths) & (depths > 0)]
    if not len(depths):
        return None
    footprint = float(np.median(depths)) / float(inputs.K[0, 0])
    return float(np.max(np.asarray(a.bbox[1]) - np.asarray(a.bbox[0]))) / footprint


def anchor_plane_size(fcfg: FieldConfig, inputs: SceneInputs) -> int:
    """Texels per side of the anchor's colour planes (0: none; dense fields only). ``auto``: about
    one texel per pixel where the anchor's surfaces are (:func:`anchor_pixels`), within
    [:data:`MIN_ANCHOR_PLANES`, :data:`MAX_ANCHOR_PLANES`]; 0 where that is no more than the
    anchor's grid resolution (the grid holds as much) or the anchor has no sparse depth. The
    planes give the room's colour the detail its grid cannot hold where the room spans more pixels
    than the grid has voxels; below that they only add parameters to fit (measurements in
    docs/experiments/)."""
    if fcfg.kind != "dense" or fcfg.anchor_planes == 0:
        return 0
    if fcfg.anchor_planes != "auto":
        return int(fcfg.anchor_planes)
    n = anchor_pixels(inputs)
    if n is None or n <= fcfg.resolution:
        return 0
    return int(np.clip(round(n), MIN_ANCHOR_PLANES, MAX_ANCHOR_PLANES))


#: ``label_stride: 0`` keeps about this many pool pixels per frame side: the per-object depth
#: renders of a scale phase cost ~ T * (side / stride)^2 rays per object, 16x more at 512 px
#: than at 128 px for no better labels (a bound is set by a few contact rays either way).
AUTO_LABEL_SIDE = 128


def label_stride(configured: int, height: int, width: int) -> int:
    """The label pool's pixel stride: ``configured`` when > 0, else one that keeps about
    ``AUTO_LABEL_SIDE`` pixels along the longer image side (1 up to 128 px, 4 at 512 px)."""
    if configured > 0:
        return configured
    return max(1, -(-max(height, width) // AUTO_LABEL_SIDE))

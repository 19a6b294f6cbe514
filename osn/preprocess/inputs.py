"""Per-object inputs of OSN: the format every preprocessing path writes and training reads.

OSN never sees a shared metric scene. For every object k it gets what per-object SfM would give:
camera-to-object poses for the frames where k is seen, sparse planar depths at some of its
pixels, both in k's *own unknown unit*, plus the instance masks. This module owns that format
(:class:`SceneInputs`; ``inputs.json`` + ``inputs.npz`` in a directory: :func:`save_inputs`,
:func:`load_inputs`, :func:`check_inputs`) and the normalisation shared by its writers
(:func:`object_inputs_from_observations`). ``osn oracle`` (:mod:`osn.preprocess.oracle`) computes
the inputs from a benchgen dataset's ground truth, which separates learning errors from SfM
errors; ``osn preprocess`` (pycolmap, :mod:`osn.preprocess.sfm`) writes the same format from
images alone.

Conventions:
* Object coordinates: the OpenCV camera frame of the object's first frame with sparse depths
  (bridged frames, :mod:`osn.preprocess.bridge`, carry none), in the object's own
  unit (the oracle picks the unit that makes its median sparse depth 1, as an SfM
  reconstruction normalised by its points would). Poses ``cam_to_obj`` are rigid in that unit.
* A configuration with actual (de-normalised) scales ``sbar`` puts a camera-frame point ``x``
  (scene units = the anchor's unit) into object k at ``cam_to_obj_k[n] @ (x / sbar_k)``:
  scaling about the training camera centre, exactly as benchgen defines a configuration.
* Eq. 1 of the paper maps a normalised scale ``s`` in [0, 1) to
  ``sbar = scene_near / near_k * (1 - s) + scene_far / far_k * s`` (:func:`denormalise_scales`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from scenecore import dataset as D
from scenecore import scale_space
from scenecore.cameras import invert_pose, pixel_rays
from scenecore.config import Rule, number

#: Mask value of pixels that no loss may use (objects dropped by preprocessing).
IGNORE_ID = 254

INPUTS_FORMAT = "osn-inputs"
INPUTS_VERSION = 1


class InputsError(ValueError):
    """Per-object inputs are missing, malformed or degenerate (message names file and problem)."""


@dataclass
class ObjectInputs:
    """Everything OSN learns object ``id`` from, in the object's own unit.

    Attributes:
        id, name: as in the dataset (``id`` indexes the instance masks).
        frames: ``(F,)`` time indices of the training frames used for this object.
        cam_to_obj: ``(F, 4, 4)`` rigid camera-to-object poses (OpenCV camera frame).
        near, far: range of the object's planar depths over its frames, object units.
        bbox: ``(2, 3)`` min / max corner of the canonical box holding the object's field.
        sparse_pix: per frame, ``(M, 2)`` int pixel indices ``(u, v)`` with a sparse depth.
        sparse_depth: per frame, ``(M,)`` planar depth in object units.
        sparse_weight: per frame, ``(M,)`` confidence (1 for the oracle); stored, not used by
            training (docs/preprocess.md: SfM's phantoms fit their matches better than good depths).
        unit_to_world: metres per object unit; ground truth known only to the oracle, used for
            evaluation (relative scale error, valid-set IoU), never for training.
    """

    id: int
    name: str
    frames: np.ndarray
    cam_to_obj: np.ndarray
    near: float
    far: float
    bbox: np.ndarray
    sparse_pix: list[np.ndarray]
    sparse_depth: list[np.ndarray]
    sparse_weight: list[np.ndarray]
    unit_to_world: float | None = None

    def frame_slot(self, time_index: int) -> int | None:
        """Position of ``time_index`` in ``frames`` or None when the object is not used there."""
        hit = np.nonzero(self.frames == time_index)[0]
        return int(hit[0]) if len(hit) else None


@dataclass
class SceneInputs:
    """The whole input of OSN for one video."""

    width: int
    height: int
    K: np.ndarray
    timestamps: np.ndarray
    images: np.ndarray  # (T, H, W, 3) uint8
    masks: np.ndarray  # (T, H, W) uint8, NO_OBJECT = none
    objects: list[ObjectInputs]
    anchor: int
    scene_near: float
    scene_far: float
    world_to_anchor: np.ndarray | None = None  # similarity: dataset world -> anchor coordinates
    source: str = "oracle"
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def anchor_pos(self) -> int:
        """Position of the anchor in ``objects`` (``anchor`` is its id, as in the masks)."""
        for k, o in enumerate(self.objects):
            if o.id == self.anchor:
                return k
        raise InputsError(f"the anchor (object {self.anchor}) is not among the objects {[o.id for o in self.objects]}")

    def object(self, object_id: int) -> ObjectInputs:
        """The inputs of object ``object_id`` (ids index the masks; dropped objects are absent)."""
        for o in self.objects:
            if o.id == object_id:
                return o
        raise InputsError(f"no inputs for object {object_id}")

    def scale_ranges(self) -> np.ndarray:
        """``(K, 2)`` de-normalised scale range ``[sbar(0), sbar(1)]`` of every object (Eq. 1)."""
        return np.array([scale_range(self.scene_near, self.scene_far, o.near, o.far) for o in self.objects])


def scale_range(scene_near: float, scene_far: float, near: float, far: float) -> tuple[float, float]:
    """Eq. 1's range for one object (:func:`scenecore.scale_space.scale_range`), as an ``InputsError``."""
    try:
        return scale_space.scale_range(scene_near, scene_far, near, far)
    except ValueError as e:
        raise InputsError(str(e)) from None


#: Eq. 1 on ``(..., K)`` normalised scales given ``ranges (K, 2)``, and its inverse.
denormalise_scales = scale_space.denormalise
normalise_scales = scale_space.normalise


# --------------------------------------------------------------------------------------------
# Storage
# --------------------------------------------------------------------------------------------


def save_inputs(out_dir: str | Path, inputs: SceneInputs) -> None:
    """Write ``inputs.json`` and ``inputs.npz`` atomically (npz first, json last = complete)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {"K": inputs.K, "timestamps": inputs.timestamps, "images": inputs.images, "masks": inputs.masks}
    if inputs.world_to_anchor is not None:
        arrays["world_to_anchor"] = inputs.world_to_anchor
    objs = []
    for o in inputs.objects:
        p = f"obj{o.id}_"
        arrays[p + "frames"] = o.frames
        arrays[p + "cam_to_obj"] = o.cam_to_obj
        arrays[p + "bbox"] = o.bbox
        counts = np.array([len(d) for d in o.sparse_depth], dtype=np.int64)
        arrays[p + "sparse_counts"] = counts
        arrays[p + "sparse_pix"] = np.concatenate(o.sparse_pix) if len(counts) else np.zeros((0, 2), np.int64)
        arrays[p + "sparse_depth"] = np.concatenate(o.sparse_depth) if len(counts) else np.zeros(0)
        arrays[p + "sparse_weight"] = np.concatenate(o.sparse_weight) if len(counts) else np.zeros(0)
        objs.append({"id": o.id, "name": o.name, "near": o.near, "far": o.far, "unit_to_world": o.unit_to_world})
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    D.atomic_write_bytes(out / "inputs.npz", buf.getvalue())
    D.atomic_write_json(
        out / "inputs.json",
        {
            "format": INPUTS_FORMAT,
            "version": INPUTS_VERSION,
            "source": inputs.source,
            "width": inputs.width,
            "height": inputs.height,
            "anchor": inputs.anchor,
            "scene_near": inputs.scene_near,
            "scene_far": inputs.scene_far,
            "objects": objs,
            "meta": inputs.meta,
        },
    )


def load_inputs(in_dir: str | Path) -> SceneInputs:
    """Read inputs written by :func:`save_inputs`; raise ``InputsError`` naming the bad file."""
    d = Path(in_dir)
    meta = D.read_json(d / "inputs.json")
    if not isinstance(meta, dict):
        raise InputsError(f"{d / 'inputs.json'}: not {INPUTS_FORMAT} v{INPUTS_VERSION} (a JSON {type(meta).__name__}, not an object)")
    if meta.get("format") != INPUTS_FORMAT or meta.get("version") != INPUTS_VERSION:
        raise InputsError(f"{d / 'inputs.json'}: not {INPUTS_FORMAT} v{INPUTS_VERSION} (found {meta.get('format')!r} v{meta.get('version')!r})")
    try:
        z = np.load(d / "inputs.npz")
        arr = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputsError(f"{d / 'inputs.npz'}: missing file") from None
    except Exception as e:
        raise InputsError(f"{d / 'inputs.npz'}: cannot read ({e})") from None
    try:
        inputs = _inputs_from(meta, arr)
    except KeyError as e:
        # Arrays are named "K", "images", ..., "obj<id>_<what>"; anything else is a JSON key.
        key = str(e.args[0]) if e.args else "?"
        npz = key in ("K", "timestamps", "images", "masks") or (key.startswith("obj") and "_" in key)
        where = d / ("inputs.npz" if npz else "inputs.json")
        raise InputsError(f"{where}: missing {key!r} (written by another version, or damaged)") from None
    except (TypeError, ValueError) as e:
        raise InputsError(f"{d / 'inputs.json'}: malformed ({e})") from None
    check_inputs(inputs, d)
    return inputs


def _inputs_from(meta: dict[str, Any], arr: dict[str, np.ndarray]) -> SceneInputs:
    """Assemble :class:`SceneInputs` from the parsed ``inputs.json`` and ``inputs.npz`` arrays."""
    objects = []
    for o in meta["objects"]:
        p = f"obj{o['id']}_"
        counts = arr[p + "sparse_counts"]
        splits = np.cumsum(counts)[:-1]
        objects.append(
            ObjectInputs(
                id=int(o["id"]),
                name=o["name"],
                frames=arr[p + "frames"],
                cam_to_obj=arr[p + "cam_to_obj"],
                near=float(o["near"]),
                far=float(o["far"]),
                bbox=arr[p + "bbox"],
                sparse_pix=np.split(arr[p + "sparse_pix"], splits),
                sparse_depth=np.split(arr[p + "sparse_depth"], splits),
                sparse_weight=np.split(arr[p + "sparse_weight"], splits),
                unit_to_world=o.get("unit_to_world"),
            )
        )
    return SceneInputs(
        width=int(meta["width"]),
        height=int(meta["height"]),
        K=arr["K"],
        timestamps=arr["timestamps"],
        images=arr["images"],
        masks=arr["masks"],
        objects=objects,
        anchor=int(meta["anchor"]),
        scene_near=float(meta["scene_near"]),
        scene_far=float(meta["scene_far"]),
        world_to_anchor=arr.get("world_to_anchor"),
        source=meta.get("source", "unknown"),
        meta=meta.get("meta", {}),
    )


def check_inputs(inputs: SceneInputs, where: str | Path = "inputs") -> None:
    """Raise ``InputsError`` on shapes, an unknown anchor, frames outside the video, sparse
    pixels outside the image, empty boxes, non-finite poses, inverted ranges, or an object with
    no mask pixel in the frames where it has a pose."""
    T = len(inputs.timestamps)
    if inputs.images.shape != (T, inputs.height, inputs.width, 3):
        raise InputsError(f"{where}: images have shape {inputs.images.shape}, expected {(T, inputs.height, inputs.width, 3)}")
    if inputs.masks.shape != (T, inputs.height, inputs.width):
        raise InputsError(f"{where}: masks have shape {inputs.masks.shape}")
    if not inputs.objects:
        raise InputsError(f"{where}: no objects")
    try:
        _ = inputs.anchor_pos
    except InputsError as e:
        raise InputsError(f"{where}: {e}") from None
    for o in inputs.objects:
        label = f"object {o.id} ({o.name})"
        if len(o.frames) == 0:
            raise InputsError(f"{where}: {label} has no frames")
        if np.any(o.frames < 0) or np.any(o.frames >= T):
            raise InputsError(f"{where}: {label} uses frames outside 0..{T - 1}")
        if o.cam_to_obj.shape != (len(o.frames), 4, 4) or not np.all(np.isfinite(o.cam_to_obj)):
            raise InputsError(f"{where}: {label} has malformed or non-finite poses")
        box = np.asarray(o.bbox, dtype=np.float64)
        if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[1] <= box[0]):
            raise InputsError(f"{where}: {label} has an empty or malformed box {box.tolist()}")
        if not (len(o.sparse_pix) == len(o.sparse_depth) == len(o.sparse_weight) == len(o.frames)):
            raise InputsError(f"{where}: {label} needs one sparse-depth entry per frame")
        for pix in o.sparse_pix:
            pix = np.asarray(pix).reshape(-1, 2)
            if np.any(pix < 0) or np.any(pix[:, 0] >= inputs.width) or np.any(pix[:, 1] >= inputs.height):
                raise InputsError(f"{where}: {label} has sparse pixels outside the {inputs.width}x{inputs.height} image")
        if not np.any(inputs.masks[o.frames] == o.id):
            raise InputsError(f"{where}: {label} covers no mask pixel in the {len(o.frames)} frame(s) where it has a pose; "
                              "nothing can train its field (drop it from the masks, or register it in frames that show it)")
        scale_range(inputs.scene_near, inputs.scene_far, o.near, o.far)


def check_downscale(width: int, height: int, factor: int) -> None:
    """Raise ``InputsError`` unless ``width x height`` frames can be averaged down by ``factor``
    (callers check before SfM, which costs minutes, rather than after it)."""
    if not isinstance(factor, int) or factor < 1:
        raise InputsError(f"downscale factor must be a positive integer, got {factor}")
    if height % factor or width % factor:
        raise InputsError(f"cannot downscale {width}x{height} frames by {factor}: the size is not a multiple of it")


def downscale_inputs(inputs: SceneInputs, factor: int) -> SceneInputs:
    """The same inputs at ``1/factor`` of the resolution: SfM registers small objects only in
    large frames, while the fields train at the resolution they are asked to render.

    Frames are averaged over ``factor x factor`` blocks (an area filter), each block's mask takes
    the id covering most of its pixels (ties go to the smaller id), intrinsics are divided by
    ``factor`` (pixel ``(u, v)`` covers ``[u, u+1)``, so block ``(u // factor, v // factor)``
    covers the same area), sparse depths move to the block holding them, and poses, ranges and
    boxes stay as they are. Raises ``InputsError`` when the frame size is not a multiple of
    ``factor`` or an object no longer covers any pixel where it has a pose.
    """
    W, H, f = inputs.width, inputs.height, factor
    if f == 1:
        check_downscale(W, H, f)
        return inputs
    images, masks, K = downscale_video(inputs.images, inputs.masks, inputs.K, f)
    h, w = masks.shape[1:]
    objects = [replace(o, sparse_pix=[np.asarray(p).reshape(-1, 2) // f for p in o.sparse_pix]) for o in inputs.objects]
    out = replace(inputs, width=w, height=h, K=K, images=images, masks=masks, objects=objects,
                  meta={**inputs.meta, "downscaled_from": [W, H], "downscale": f})
    check_inputs(out, f"inputs downscaled {W}x{H} -> {w}x{h}")
    return out


def with_video(inputs: SceneInputs, images: np.ndarray, masks: np.ndarray, where: str | Path = "inputs") -> SceneInputs:
    """The same inputs on another rendering of their video, of the same size: ``images (T, H, W,
    3)`` uint8 and instance-id ``masks (T, H, W)``. SfM may run on the video rendered larger (small
    objects register only there), but the fields must learn the video a method is given: the
    benchmark's own frames, which the evaluation's ground truth was rendered like (a larger video
    averaged down differs from them: area averages, where the benchmark renders each pixel's
    centre ray; docs/preprocess.md). Poses, sparse depths, ranges and boxes are kept; objects
    preprocessing dropped stay ignored (``IGNORE_ID``). Raises ``InputsError`` naming ``where``
    when the sizes differ or an object no longer covers a pixel where it has a pose.
    """
    T, H, W = inputs.masks.shape
    if images.shape != (T, H, W, 3) or masks.shape != (T, H, W):
        raise InputsError(f"{where}: a video of {images.shape[:3]} frames with {masks.shape} masks cannot replace "
                          f"the inputs' {(T, H, W)}")
    masks = np.array(masks, dtype=inputs.masks.dtype, copy=True)
    for oid in inputs.meta.get("dropped_objects", []):
        masks[masks == oid] = IGNORE_ID
    out = replace(inputs, images=np.ascontiguousarray(images, dtype=np.uint8), masks=masks,
                  meta={**inputs.meta, "video": str(where)})
    check_inputs(out, where)
    return out


def downscale_video(images: np.ndarray, masks: np.ndarray, K: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``images (T, H, W, 3)``, ``masks (T, H, W)`` and pixel intrinsics ``K`` at ``1/factor``
    of the resolution, as :func:`downscale_inputs` takes them (block means, majority ids);
    ``InputsError`` when the frame size is not a multiple of ``factor``."""
    T, H, W = masks.shape
    f = factor
    check_downscale(W, H, f)
    h, w = H // f, W // f
    small = np.rint(images.reshape(T, h, f, w, f, 3).mean(axis=(2, 4))).astype(np.uint8)
    mask_blocks = masks.reshape(T, h, f, w, f).transpose(0, 1, 3, 2, 4).reshape(T, h, w, f * f)
    ids = np.unique(masks)  # ascending: argmax's first maximum is the smaller id
    counts = np.stack([(mask_blocks == i).sum(axis=-1) for i in ids], axis=-1)
    small_masks = ids[np.argmax(counts, axis=-1)].astype(masks.dtype)
    K = np.array(K, dtype=np.float64, copy=True)
    K[:2, :] /= f
    return small, small_masks, K


def auto_points_per_frame(width: int, height: int) -> int:
    """Sparse depths per object and frame that training gets by default (``points_per_frame: 0``
    of the oracle and of SfM): a sixteenth of the frame's pixels, at least 256. Larger frames get
    more depths because the valid set learned from them improves with the count; the 64 px demo
    keeps 256 (measurements in docs/experiments/)."""
    return max(256, (width * height) // 16)


def subsample_sparse_depths(inputs: SceneInputs, per_frame: int = 0, seed: int = 0) -> SceneInputs:
    """The same inputs with at most ``per_frame`` sparse depths per object and frame (0:
    :func:`auto_points_per_frame` of the inputs' frames), chosen uniformly at random.

    Field steps draw their depth rays from all objects' depths at once, so an object's share of
    the depth supervision is its share of the depths. SfM gives a textured room many times the
    depths of a small object (the oracle: at most 256 each); capping SfM's at the oracle's count
    keeps the small objects' share and so their contacts, which raises the valid set's IoU
    (docs/preprocess.md). Poses, ranges and boxes are kept: they were set from every depth.
    One generator over the objects in order; a frame with fewer depths keeps them all.
    """
    if per_frame < 0:
        raise InputsError(f"sparse depths per frame must be >= 0 (0: automatic), got {per_frame}")
    cap = per_frame or auto_points_per_frame(inputs.width, inputs.height)
    rng = np.random.default_rng(seed)
    objects = []
    for o in inputs.objects:
        keep = [np.sort(rng.choice(len(d), size=cap, replace=False)) if len(d) > cap else slice(None)
                for d in o.sparse_depth]
        objects.append(replace(
            o,
            sparse_pix=[np.asarray(p)[k] for p, k in zip(o.sparse_pix, keep)],
            sparse_depth=[np.asarray(d)[k] for d, k in zip(o.sparse_depth, keep)],
            sparse_weight=[np.asarray(w)[k] for w, k in zip(o.sparse_weight, keep)],
        ))
    return replace(inputs, objects=objects, meta={**inputs.meta, "sparse_depths_per_frame": cap})


#: Defaults shared by every writer of inputs (oracle and SfM normalise alike): the scene volume
#: is ``[SCENE_NEAR_FACTOR * min_k near_k, SCENE_FAR_FACTOR * max_k far_k]`` (Eq. 1) and each
#: canonical box is padded by ``BOX_PADDING`` of its extent.
SCENE_NEAR_FACTOR = scale_space.SCENE_NEAR_FACTOR
SCENE_FAR_FACTOR = scale_space.SCENE_FAR_FACTOR
BOX_PADDING = 0.1

#: Config rules of the fields named like the defaults above (what :func:`scene_volume` and
#: :func:`object_inputs_from_observations` accept), for :func:`scenecore.config.validate`.
NORMALISATION_RULES: dict[str, Rule] = {
    "scene_near_factor": number(0.0, 1.0, lo_open=True, hi_open=True),
    "scene_far_factor": number(1.0),
    "box_padding": number(0.0),
}


def scene_volume(objects: list[ObjectInputs], near_factor: float, far_factor: float) -> tuple[float, float]:
    """Scene near/far of Eq. 1: below every object's near and beyond every object's far."""
    try:
        return scale_space.scene_volume([o.near for o in objects], [o.far for o in objects], near_factor, far_factor)
    except ValueError as e:
        raise InputsError(str(e)) from None


def object_inputs_from_observations(
    object_id: int,
    name: str,
    frames: np.ndarray,
    cam_to_obj: np.ndarray,
    sparse_pix: list[np.ndarray],
    sparse_depth: list[np.ndarray],
    sparse_weight: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
    box_padding: float,
    metres_per_unit: float | None,
) -> ObjectInputs:
    """Normalise one object's poses and sparse depths (any unit) into :class:`ObjectInputs`.

    Shared by the oracle and SfM so both produce identical conventions: the object frame becomes
    the camera of its first frame with sparse depths, the unit makes the median sparse depth 1, near/far come from
    robust percentiles of the depths, and the canonical box from percentiles of the points.

    Args:
        cam_to_obj: ``(F, 4, 4)`` rigid camera-to-object poses in the input unit.
        metres_per_unit: metres per input unit when known (ground truth), else None.
    """
    all_d = np.concatenate(sparse_depth) if sparse_depth else np.zeros(0)
    if len(all_d) == 0 or not np.all(np.isfinite(all_d)) or np.any(all_d <= 0):
        raise InputsError(f"object {object_id} ({name}): no usable positive sparse depths")
    unit = float(np.median(all_d))
    ref_inv = invert_pose(cam_to_obj[next(n for n, d in enumerate(sparse_depth) if len(d))])
    poses = ref_inv[None] @ cam_to_obj  # camera t -> camera-of-first-frame, input unit, rigid
    poses[:, :3, 3] /= unit
    depths = [np.asarray(d, dtype=np.float64) / unit for d in sparse_depth]
    pts = []
    for pix, dep, M in zip(sparse_pix, depths, poses):
        o, d = pixel_rays(K, np.eye(4), width, height, pixels=pix)
        p_cam = o + dep[:, None] * d
        pts.append(p_cam @ M[:3, :3].T + M[:3, 3])
    pts_a = np.concatenate(pts)
    lo, hi = np.percentile(pts_a, 0.5, axis=0), np.percentile(pts_a, 99.5, axis=0)
    # Pad every axis, also a flat one (a wall): at least a small fraction of the largest extent.
    pad = box_padding * np.maximum(hi - lo, 1e-2 * float(np.max(hi - lo)))
    all_u = all_d / unit
    near, far = float(np.percentile(all_u, 0.5)) * 0.9, float(np.percentile(all_u, 99.5)) * 1.1
    return ObjectInputs(
        id=object_id,
        name=name,
        frames=np.asarray(frames, dtype=np.int64),
        cam_to_obj=poses,
        near=near,
        far=far,
        bbox=np.stack([lo - pad, hi + pad]),
        sparse_pix=[np.asarray(p, dtype=np.int64) for p in sparse_pix],
        sparse_depth=depths,
        sparse_weight=[np.asarray(w, dtype=np.float64) for w in sparse_weight],
        unit_to_world=None if metres_per_unit is None else unit * metres_per_unit,
    )

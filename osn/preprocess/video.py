"""Per-object SfM of a whole video (``osn preprocess``): from a folder of frames and masks, or a benchgen dataset.

:func:`preprocess_video` reconstructs every object (:func:`osn.preprocess.sfm.reconstruct_object`)
and normalises each reconstruction into per-object inputs exactly as the oracle does
(:func:`osn.preprocess.inputs.object_inputs_from_observations`), so ``osn train`` accepts either.
:func:`load_video` and :func:`intrinsics_from_args` read any video; :func:`preprocess_dataset`
runs on a benchgen dataset's training video and then measures the result against its ground
truth (:mod:`osn.preprocess.alignment`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np

from scenecore import dataset as D
from scenecore.cameras import intrinsics_from_fov
from osn.preprocess.alignment import align_to_ground_truth
from osn.preprocess.bridge import Bridged, bridge_object
from osn.preprocess.consistency import ObjectObservations, Verdict, assess_scene, frame_points
from osn.preprocess.freespace import occluding_flags
from osn.preprocess.inputs import (
    IGNORE_ID,
    InputsError,
    ObjectInputs,
    SceneInputs,
    check_downscale,
    check_inputs,
    downscale_inputs,
    downscale_video,
    object_inputs_from_observations,
    scene_volume,
    subsample_sparse_depths,
)
from osn.preprocess.sfm import ObjectRegistrationError, ObjectSfM, PreprocessConfig, PreprocessReport, reconstruct_object

log = logging.getLogger(__name__)


def preprocess_video(
    images: np.ndarray,
    masks: np.ndarray,
    K: np.ndarray,
    timestamps: np.ndarray,
    object_names: dict[int, str],
    anchor: int,
    cfg: PreprocessConfig,
    progress: Callable[[str], None] | None = None,
    work_dir: str | Path | None = None,
    workers: int = 1,
) -> tuple[SceneInputs, PreprocessReport]:
    """Per-object SfM for a whole video; returns inputs (SfM frames and units) and a report.

    ``images (T, H, W, 3)`` uint8, ``masks (T, H, W)`` instance ids, ``K (3, 3)`` pixel
    intrinsics, ``timestamps (T,)``. An object that fails to register stops everything when
    ``cfg.on_failure`` is ``stop`` or it is the ``anchor``; otherwise it is dropped (its pixels
    become ``IGNORE_ID``) and the report says why. Every reconstruction is then checked against
    the masks and its own frames (:mod:`osn.preprocess.consistency`): contradicting frames are
    dropped, an object whose depths disagree keeps no sparse depth, one that contradicts its masks
    as a whole is dropped like a failed one (an anchor so contradicted stops everything).
    ``work_dir`` keeps each object's COLMAP working directory as ``work_dir/object_<id>``
    (:func:`object_work_dir`) for inspection. ``workers``: objects reconstructed at once, on
    threads (pycolmap releases the GIL; each object's SfM is single-threaded and seeded, so the
    result does not depend on it).
    """
    inputs, report = _preprocess_video(images, masks, K, timestamps, object_names, anchor, cfg, progress, work_dir, workers)
    return without_untrusted_depths(inputs), report


def _preprocess_video(
    images: np.ndarray, masks: np.ndarray, K: np.ndarray, timestamps: np.ndarray, object_names: dict[int, str],
    anchor: int, cfg: PreprocessConfig, progress: Callable[[str], None] | None, work_dir: str | Path | None, workers: int,
) -> tuple[SceneInputs, PreprocessReport]:
    """:func:`preprocess_video` with the sparse depths the consistency check distrusts still in
    the inputs (``meta["untrusted_depths"]``): ground truth measures each object's unit on them."""
    T, H, W = masks.shape
    check_downscale(W, H, cfg.anchor_downscale)  # before SfM, which costs minutes
    report = PreprocessReport()
    objects: list[ObjectInputs] = []
    results = reconstruct_objects(images, masks, K, object_names, anchor, cfg, progress, work_dir, workers)
    verdicts = check_reconstructions(results, masks, K, timestamps, object_names, anchor, cfg)
    bridged = bridge_unposed(results, verdicts, masks, K, timestamps, anchor, cfg) if cfg.bridge_unposed else {}
    for oid, name in sorted(object_names.items()):
        sfm = results[oid]
        if isinstance(sfm, ObjectRegistrationError):
            log.warning("%s -- training without it", sfm)
            report.dropped.append(oid)
            report.objects.append({"id": oid, "name": name, "error": str(sfm)})
            continue
        verdict = verdicts[oid]
        if sfm.twin.get("fits_better"):
            log.warning("%s", reversed_message(oid, name, sfm.twin))
        if verdict.drop:
            log.warning("%s", verdict.message)
            report.dropped.append(oid)
            report.objects.append({"id": oid, "name": name, "error": verdict.message, "consistency": verdict.record()})
            continue
        if verdict.message:
            log.warning("%s", verdict.message)
        sfm = with_bridged(without_frames(sfm, verdict.bad_frames), bridged.get(oid))
        flags = occluding_flags(sfm.cam_to_obj, sfm.sparse_pix, sfm.sparse_depth, K, W, H)
        drop = cfg.drop_occluding != "none"
        # The anchor's flagged depths still set its near plane (the scene volume of Eq. 1) under
        # `training`; they are dropped only once it is normalised.
        before = drop and (cfg.drop_occluding == "all" or oid != anchor)
        keep = [~f if before else np.ones(len(f), dtype=bool) for f in flags]
        pix, dep, wt = ([x[k] for x, k in zip(xs, keep)] for xs in (sfm.sparse_pix, sfm.sparse_depth, sfm.sparse_weight))
        obj = object_inputs_from_observations(oid, name, sfm.frames, sfm.cam_to_obj, pix, dep, wt, K, W, H,
                                              cfg.box_padding, metres_per_unit=None)
        objects.append(without_depths(obj, flags) if drop and not before else obj)
        b = bridged.get(oid)
        report.objects.append({**_object_report(oid, name, sfm, flags, drop, b.frames if b else []),
                               "consistency": verdict.record(), **bridge_record(b)})
    masks = masks.copy()
    for oid in report.dropped:
        masks[masks == oid] = IGNORE_ID
    scene_near, scene_far = scene_volume(objects, cfg.scene_near_factor, cfg.scene_far_factor)
    inputs = SceneInputs(
        width=W, height=H, K=K, timestamps=np.asarray(timestamps, dtype=np.float64), images=images, masks=masks,
        objects=objects, anchor=anchor, scene_near=scene_near, scene_far=scene_far, source="colmap",
        meta={"preprocess": cfg.__dict__, "dropped_objects": report.dropped,
              "untrusted_depths": [k for k, v in sorted(verdicts.items()) if not v.use_depths and not v.drop],
              "bridged_frames": {str(k): b.frames for k, b in sorted(bridged.items())
                                 if b.frames and k not in report.dropped},
              "consistency": {str(k): consistency_summary(v) for k, v in sorted(verdicts.items())},
              "likely_reversed": {str(o.id): reversed_message(o.id, o.name, results[o.id].twin) for o in objects
                                  if results[o.id].twin.get("fits_better")}},
    )
    return inputs, report


def bridge_unposed(
    results: dict[int, ObjectSfM | ObjectRegistrationError], verdicts: dict[int, Verdict], masks: np.ndarray,
    K: np.ndarray, timestamps: np.ndarray, anchor: int, cfg: PreprocessConfig,
) -> dict[int, Bridged]:
    """Per kept object other than the anchor, the frames its mask shows it in without a pose,
    bridged from its registered neighbours and the anchor's cameras (:func:`osn.preprocess.bridge.bridge_object`;
    each reconstruction without the frames its consistency verdict dropped). Objects whose depths
    the verdict distrusts are not bridged: the test of a bridged pose projects them."""
    anc = results.get(anchor)
    if not isinstance(anc, ObjectSfM) or verdicts[anchor].drop:
        return {}
    anc = without_frames(anc, verdicts[anchor].bad_frames)
    anc_depth = float(np.median(np.concatenate(anc.sparse_depth))) if anc.sparse_depth else float("nan")
    out = {}
    for oid, sfm in sorted(results.items()):
        # The silhouette test projects the object's points: not from depths the checks distrust.
        if oid == anchor or isinstance(sfm, ObjectRegistrationError) or verdicts[oid].drop or not verdicts[oid].use_depths:
            continue
        sfm = without_frames(sfm, verdicts[oid].bad_frames)
        depths = np.concatenate(sfm.sparse_depth) if sfm.sparse_depth else np.zeros(0)
        out[oid] = bridge_object(
            sfm.frames, sfm.cam_to_obj, frame_points(sfm.cam_to_obj, sfm.sparse_pix, sfm.sparse_depth, K),
            float(np.median(depths)) if len(depths) else float("nan"), anc.frames, anc.cam_to_obj, anc_depth, masks,
            timestamps, oid, anchor, K, verdicts[oid].figures["mask_tolerance_px"], cfg.min_mask_pixels,
        )
    return out


def with_bridged(sfm: ObjectSfM, bridged: Bridged | None) -> ObjectSfM:
    """``sfm`` with the frames ``bridged`` posed (no sparse depth there), in time order."""
    if bridged is None or not bridged.frames:
        return sfm
    frames = np.concatenate([sfm.frames, np.asarray(bridged.frames, dtype=sfm.frames.dtype)])
    poses = np.concatenate([sfm.cam_to_obj, np.stack(bridged.poses)])
    empty = len(bridged.frames)
    pix = sfm.sparse_pix + [np.zeros((0, 2), dtype=np.int64)] * empty
    dep = sfm.sparse_depth + [np.zeros(0)] * empty
    wt = sfm.sparse_weight + [np.zeros(0)] * empty
    order = np.argsort(frames, kind="stable")
    return dataclasses.replace(sfm, frames=frames[order], cam_to_obj=poses[order], sparse_pix=[pix[i] for i in order],
                               sparse_depth=[dep[i] for i in order], sparse_weight=[wt[i] for i in order])


def bridge_record(bridged: Bridged | None) -> dict:
    """What the report says of an object's bridged frames (nothing when none was a candidate)."""
    if bridged is None or not bridged.record:
        return {}
    return {"bridged_frames": bridged.frames, "bridge": {"max_miss": bridged.max_miss, "min_cover": bridged.min_cover,
                                                         "frames": bridged.record}}


def reversed_message(oid: int, name: str, twin: dict) -> str:
    """One line on a model whose depth-reversed twin fits better (:func:`osn.preprocess.twin.compare_with_twin`)."""
    return (f"object {oid} ({name}): its depth-reversed twin fits {100 * twin['twin_better_share']:.0f}% of its "
            f"{twin['points']} points better (median {twin['twin_median_error_px']:.3f} px against "
            f"{twin['median_error_px']:.3f} px): likely depth-reversed, trained as SfM found it")


def check_reconstructions(
    results: dict[int, ObjectSfM | ObjectRegistrationError], masks: np.ndarray, K: np.ndarray, timestamps: np.ndarray,
    object_names: dict[int, str], anchor: int, cfg: PreprocessConfig,
) -> dict[int, Verdict]:
    """The consistency verdict of every registered object (:func:`osn.preprocess.consistency.assess_scene`,
    on the full frames the sparse pixels index). Raises ``ObjectRegistrationError`` when the
    anchor's reconstruction contradicts the video so much that it would have to be dropped."""
    observed = []
    for oid, sfm in sorted(results.items()):
        if isinstance(sfm, ObjectRegistrationError):
            continue
        # The anchor's SfM ran on frames averaged down: its error in full-frame pixels.
        f = cfg.anchor_downscale if oid == anchor else 1
        observed.append(ObjectObservations(oid, sfm.frames, sfm.cam_to_obj, sfm.sparse_pix, sfm.sparse_depth,
                                           sfm.reprojection_error_px * f))
    verdicts = assess_scene(observed, masks, K, timestamps, anchor, cfg.min_frames, object_names)
    if anchor in verdicts and verdicts[anchor].drop:
        raise ObjectRegistrationError(verdicts[anchor].message)
    return verdicts


def without_depths(obj: ObjectInputs, drop: list[np.ndarray]) -> ObjectInputs:
    """``obj`` without the sparse depths ``drop`` (per frame a boolean mask over its depths) marks;
    its frame, unit, near, far and box stay as normalised from all of them."""
    keep = [~d for d in drop]
    return dataclasses.replace(obj, sparse_pix=[x[k] for x, k in zip(obj.sparse_pix, keep)],
                               sparse_depth=[x[k] for x, k in zip(obj.sparse_depth, keep)],
                               sparse_weight=[x[k] for x, k in zip(obj.sparse_weight, keep)])


def without_frames(sfm: ObjectSfM, frames: list[int]) -> ObjectSfM:
    """``sfm`` without its registrations at the time indices ``frames``."""
    if not frames:
        return sfm
    keep = np.flatnonzero(~np.isin(sfm.frames, frames))
    return dataclasses.replace(
        sfm, frames=sfm.frames[keep], cam_to_obj=sfm.cam_to_obj[keep], sparse_pix=[sfm.sparse_pix[i] for i in keep],
        sparse_depth=[sfm.sparse_depth[i] for i in keep], sparse_weight=[sfm.sparse_weight[i] for i in keep],
    )


def consistency_summary(v: Verdict) -> dict:
    """What ``inputs.json`` keeps of a verdict (the per-frame figures stay in ``preprocess_report.json``)."""
    return {k: x for k, x in v.record().items() if not k.startswith("frame_")}


def without_untrusted_depths(inputs: SceneInputs) -> SceneInputs:
    """The inputs without the sparse depths of the objects in ``meta["untrusted_depths"]`` (the
    consistency check found them disagreeing across frames): those objects train on their pixels
    alone; their range and box, set from every depth, are kept."""
    untrusted = set(inputs.meta.get("untrusted_depths", []))
    if not untrusted:
        return inputs
    objects = [dataclasses.replace(o, sparse_pix=[p[:0] for p in o.sparse_pix], sparse_depth=[d[:0] for d in o.sparse_depth],
                                   sparse_weight=[w[:0] for w in o.sparse_weight]) if o.id in untrusted else o
               for o in inputs.objects]
    return dataclasses.replace(inputs, objects=objects)


def reconstruct_objects(
    images: np.ndarray,
    masks: np.ndarray,
    K: np.ndarray,
    object_names: dict[int, str],
    anchor: int,
    cfg: PreprocessConfig,
    progress: Callable[[str], None] | None = None,
    work_dir: str | Path | None = None,
    workers: int = 1,
) -> dict[int, ObjectSfM | ObjectRegistrationError]:
    """Each object's SfM (:func:`reconstruct_object`), ``workers`` objects at once on threads, and
    each object's mapper restarts ``workers`` at once (the room's restarts would otherwise run
    alone, one after another, once the objects beside it end); ``object id -> ObjectSfM``, or the
    error of an object that failed to register.

    The anchor is reconstructed at ``cfg.anchor_downscale`` (its sparse pixels mapped back to the
    full frames) with ``cfg.anchor_mapper_restarts`` mapper runs, and started first: it is usually
    the largest object (whole frames), so the others share the remaining workers meanwhile, and its
    failure (which stops everything) comes early.
    A failure that stops everything (``cfg.on_failure == "stop"``, or the anchor's) is raised once
    the objects before it in that order are done; objects not yet started are then dropped.
    """
    said = threading.Lock()  # one progress line at a time from the workers

    def sfm_of(oid: int, name: str) -> ObjectSfM | ObjectRegistrationError:
        if progress:
            with said:
                progress(f"SfM of object {oid} ({name})")
        f = cfg.anchor_downscale if oid == anchor else 1
        ocfg = dataclasses.replace(cfg, mapper_restarts=cfg.anchor_mapper_restarts) if oid == anchor else cfg
        try:
            imgs, msks, Ko = downscale_video(images, masks, K, f) if f > 1 else (images, masks, K)
            sfm = reconstruct_object(imgs, msks, oid, Ko, ocfg, name,
                                     object_work_dir(work_dir, oid) if work_dir is not None else None, workers)
        except ObjectRegistrationError as e:
            return e
        if f > 1:  # pixel p of the small frames covers [p f, p f + f) of the full ones
            sfm.sparse_pix = [p * f + f // 2 for p in sfm.sparse_pix]
        return sfm

    order = sorted(object_names.items(), key=lambda item: (item[0] != anchor, item[0]))
    pool = ThreadPoolExecutor(max(1, min(workers, len(order))), thread_name_prefix="sfm")
    results: dict[int, ObjectSfM | ObjectRegistrationError] = {}
    try:
        futures = {oid: pool.submit(sfm_of, oid, name) for oid, name in order}
        for oid, _ in order:
            results[oid] = futures[oid].result()
            if isinstance(results[oid], ObjectRegistrationError) and (cfg.on_failure == "stop" or oid == anchor):
                raise results[oid]
    finally:  # on an error or an interrupt, objects not yet started are dropped
        pool.shutdown(wait=True, cancel_futures=True)
    return results


def training_inputs(inputs: SceneInputs, factor: int, cfg: PreprocessConfig) -> SceneInputs:
    """SfM's inputs as training gets them: averaged down by ``factor``
    (:func:`~osn.preprocess.inputs.downscale_inputs`), then at most ``cfg.points_per_frame``
    sparse depths per object and frame (:func:`~osn.preprocess.inputs.subsample_sparse_depths`)."""
    return subsample_sparse_depths(downscale_inputs(inputs, factor), cfg.points_per_frame, cfg.seed)


def object_work_dir(work_dir: str | Path, object_id: int) -> Path:
    """Where object ``object_id``'s COLMAP images, ``database.db`` and ``model/`` are kept."""
    return Path(work_dir) / f"object_{object_id}"


def _object_report(oid: int, name: str, sfm: ObjectSfM, flags: list[np.ndarray], dropped: bool,
                   bridged: list[int] = ()) -> dict:
    """The report entry of a registered object (without ground truth; ``flags``: per frame the
    depths :func:`~osn.preprocess.freespace.occluding_flags` flags, ``dropped``: whether they were
    dropped; ``bridged``: the frames of ``sfm`` that :func:`with_bridged` added)."""
    return {
        "id": oid,
        "name": name,
        "candidate_frames": sfm.candidate_frames,
        "registered_frames": len(sfm.frames) - len(bridged),
        "features": sfm.num_features,
        "points": sfm.num_points,
        "points_behind_dropped": sfm.points_behind_dropped,
        # Without ground truth these say how much to trust the poses: the kept model's
        # error, and how the restarts disagreed (a reversed twin fits visibly worse).
        "reprojection_error_px": sfm.reprojection_error_px,
        "restarts": sfm.restarts,
        "repaired_frames": sfm.repaired_frames,
        "twin": sfm.twin,
        # Depths in front of what the other frames saw: phantoms, counted without ground truth.
        "sparse_depths": int(sum(len(d) for d in sfm.sparse_depth)),
        "occluding_depths": int(sum(f.sum() for f in flags)),
        "occluding_dropped": dropped,
    }


def report_lines(objects: list[dict]) -> list[str]:
    """One line per object of a :class:`PreprocessReport` (and one per repaired frame, and one
    for a reconstruction the consistency check found wrong)."""
    lines = []
    for r in objects:
        if "error" in r:
            lines.append(f"  object {r['id']} ({r['name']}): DROPPED: {r['error']}")
            continue
        line = (f"  object {r['id']} ({r['name']}): {r['registered_frames']}/{r['candidate_frames']} frames, "
                f"{r['points']} points, reprojection error {r['reprojection_error_px']:.2f} px")
        if r.get("sparse_depths"):
            line += f", {r['occluding_depths']} of {r['sparse_depths']} depths in front of what other frames saw"
            line += " (dropped)" if r.get("occluding_dropped") else ""
        if "rotation_error_deg_max" in r:
            line += (f", registered {100 * r['registered_fraction']:.0f}% of visible frames, rotation error "
                     f"max {r['rotation_error_deg_max']:.3f} deg, centre error mean {r['center_error_m_mean']:.4f} m")
        if r.get("sparse_depths_off_10pct") is not None:
            line += f", sparse depths >10% off {100 * r['sparse_depths_off_10pct']:.1f}%"
        lines.append(line)
        for f in r.get("repaired_frames", []):
            lines.append(f"    frame {f['frame']}: {f['action']} ({100 * f['consistency']:.1f}% of its verified "
                         f"matches fit SfM's pose, {100 * f['consistency_after']:.1f}% after)")
        if r.get("twin", {}).get("fits_better"):
            lines.append(f"    {reversed_message(r['id'], r['name'], r['twin'])}")
        if r.get("consistency", {}).get("message"):
            lines.append(f"    {r['consistency']['action']}: {r['consistency']['message']}")
        if r.get("bridge"):
            b = r["bridge"]
            line = (f"    bridged {len(r['bridged_frames'])} of {len(b['frames'])} unposed frames from its neighbours "
                    f"({', '.join(map(str, r['bridged_frames'])) or 'none fits its mask'})")
            if "bridged_rotation_error_deg_max" in r:
                line += (f", rotation error max {r['bridged_rotation_error_deg_max']:.3f} deg, centre error mean "
                         f"{r['bridged_center_error_m_mean']:.4f} m")
            lines.append(line)
    return lines


def preprocess_dataset(
    dataset_root: str | Path, cfg: PreprocessConfig, progress: Callable[[str], None] | None = None,
    video: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, work_dir: str | Path | None = None,
    workers: int = 1,
) -> tuple[SceneInputs, PreprocessReport]:
    """Per-object SfM on a benchgen dataset's training video, aligned to its ground truth.

    The dataset's instance masks stand in for a learned segmenter and its intrinsics are the
    known camera. Ground truth is used only *after* SfM, to measure accuracy and to record each
    object's unit and the world-to-anchor similarity (needed to place test cameras). ``video``:
    :func:`scenecore.dataset.read_training_video`'s result when the caller already read it;
    ``work_dir`` and ``workers`` as in :func:`preprocess_video`.
    """
    root = Path(dataset_root)
    scene = D.load_scene(root)
    images, depths, masks = video if video is not None else D.read_training_video(root, scene)
    names = {o.id: o.name for o in scene.objects}
    inputs, report = _preprocess_video(
        images, masks, scene.intrinsics.matrix(), scene.timestamps.copy(), names, scene.anchor_id, cfg, progress, work_dir,
        workers,
    )
    align_to_ground_truth(inputs, report, scene, depths, masks)
    inputs = without_untrusted_depths(inputs)  # measured above; never trained on
    inputs.meta["dataset"] = str(root)
    check_inputs(inputs, root)
    return inputs, report


def load_video(frames_dir: str | Path, masks_dir: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read a video as sorted PNG/JPG frames plus same-named instance-id PNG masks.

    Returns ``images (T, H, W, 3)`` uint8, ``ids (T, H, W)`` uint8 and the frames' file names.
    Masks are single-channel 8-bit images of object ids (``255`` = no object). Raises
    ``InputsError`` naming the file on a missing mask, a size mismatch or an unreadable image.
    """
    frames_dir, masks_dir = Path(frames_dir), Path(masks_dir)
    if not frames_dir.is_dir():
        raise InputsError(f"{frames_dir}: not a directory of frames")
    files = sorted(p for p in frames_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputsError(f"{frames_dir}: no .png/.jpg frames")
    images, masks = [], []
    for p in files:
        try:
            img = D.read_rgb(p)
        except D.DatasetError as e:
            raise InputsError(str(e)) from None
        mp = masks_dir / (p.stem + ".png")
        try:
            m = D.read_ids(mp)
        except D.DatasetError as e:
            raise InputsError(str(e)) from None
        if m.shape != img.shape[:2] or (images and img.shape != images[0].shape):
            raise InputsError(f"{mp}: size {m.shape[::-1]} does not match frame {p} {img.shape[1::-1]} or the first frame")
        images.append(img)
        masks.append(m)
    ids = np.stack(masks)
    if not np.any((ids != 255) & (ids != IGNORE_ID)):
        raise InputsError(f"{masks_dir}: the masks hold no object id (every pixel is 255, no object)")
    return np.stack(images), ids, [p.name for p in files]


def intrinsics_from_args(intrinsics: str | None, fov: float | None, width: int, height: int) -> np.ndarray:
    """3x3 intrinsics from ``"fx,fy,cx,cy"`` or a horizontal field of view in degrees."""
    if intrinsics:
        try:
            fx, fy, cx, cy = (float(v) for v in intrinsics.split(","))
        except ValueError:
            raise InputsError(f"--intrinsics must be fx,fy,cx,cy (pixels), got {intrinsics!r}") from None
        if not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
            raise InputsError(f"--intrinsics needs finite, positive focal lengths, got {intrinsics!r}")
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if fov:
        if not 0 < fov < 180:
            raise InputsError(f"--fov must lie between 0 and 180 degrees, got {fov}")
        return intrinsics_from_fov(fov, width, height)
    raise InputsError("a video directory needs --intrinsics fx,fy,cx,cy or --fov DEGREES")

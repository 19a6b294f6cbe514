"""``osn preprocess``: per-object SfM with pycolmap, from frames and instance masks.

For every object, SIFT features are extracted only inside its mask, matched (exhaustively for
short videos, sequentially for long ones) and reconstructed by incremental mapping with the known,
shared pinhole camera (no intrinsics refinement). Each object's reconstruction has its own frame
and unit; :func:`osn.inputs.object_inputs_from_observations` normalises it exactly as the oracle
does, so ``osn train`` accepts either.

No GUI, every random seed fixed, single-threaded where threads change results.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from scenecore import dataset as D
from scenecore.cameras import fit_pose_similarity, intrinsics_from_fov, invert_pose, rotation_angle_deg
from osn.preprocess.inputs import (
    IGNORE_ID,
    InputsError,
    ObjectInputs,
    OracleConfig,
    SceneInputs,
    check_inputs,
    object_inputs_from_observations,
    oracle_inputs,
    scene_volume,
)
from osn.preprocess.repair import bundle_adjust, repair_registrations

log = logging.getLogger(__name__)

GREY_MODES = ("auto", "luminance", "principal")


@dataclass
class PreprocessConfig:
    """Options of per-object SfM.

    Attributes:
        matcher: ``exhaustive``, ``sequential`` or ``auto`` (exhaustive up to
            ``exhaustive_max_frames`` frames).
        sequential_overlap: neighbours matched per frame by the sequential matcher.
        max_features: SIFT features per image and object.
        peak_threshold: SIFT peak threshold (lower finds more features on small images).
        upscale: integer upsampling of frames before SIFT (small objects need it).
        guided_matching: re-match each verified pair under its two-view geometry. On gnome-house
            at 256 px it cut the sofa's worst rotation error from 11.5 to 1.3 degrees.
        grey: what SIFT sees: ``luminance`` (COLMAP's conversion), ``principal`` (the object's
            principal colour axis, :func:`principal_grey`) or ``auto`` (principal only when the
            object's colours differ mostly in hue).
        epipolar_error: two-view RANSAC and guided-matching threshold in pixels of the input
            frames (COLMAP's 4 px is for megapixel photos; 2 px let wrong matches into the tiny
            room and the gnome-house ring-toy at 512 px).
        mask_erosion: pixels removed from each mask border, so features do not straddle objects.
        min_frames: an object must register at least this many frames.
        min_points: ... and triangulate at least this many 3D points.
        min_mask_pixels: frames where the object covers fewer pixels are not used for it.
        on_failure: ``stop`` raises on an object that fails; ``skip`` trains without it.
        max_reprojection_error: observations above this (pixels) are dropped.
        min_matches, init_min_inliers, init_min_tri_angle, abs_pose_min_inliers: mapper
            thresholds, relaxed from COLMAP's megapixel defaults for small object crops.
        scene_near_factor, scene_far_factor, box_padding: as in the oracle (shared normalisation).
        seed: every random seed of pycolmap (restart ``k`` of the mapper uses ``seed + k``).
        mapper_restarts: incremental mapping runs on the same matches; the best one is kept
            (:func:`_best_of_restarts` explains why a single run is not enough).
        min_epipolar_consistency: a registered frame with a smaller fraction of its verified
            matches within ``2 * epipolar_error`` of the model's epipolar geometry is re-posed
            or dropped (:mod:`osn.sfm_repair`; correct frames measured 0.54-1.00, a wrong one 0.016).
        final_cauchy_px: scale (input-frame pixels) of the Cauchy loss of a last global bundle
            adjustment; 0 skips it. COLMAP's own global BA uses a squared loss, which lets the
            few bad observations of a weakly seen frame pull it (ring-toy at 1024 px, frame 0:
            4.7 degrees before, 2.9 after; 1 px: 4.5, 2 px: 5.2; docs/preprocess.md).
    """

    matcher: str = "auto"
    exhaustive_max_frames: int = 60
    sequential_overlap: int = 10
    max_features: int = 4096
    peak_threshold: float = 0.001
    guided_matching: bool = True
    epipolar_error: float = 0.5
    grey: str = "auto"
    mask_erosion: int = 1
    upscale: int = 2
    min_frames: int = 3
    min_points: int = 20
    min_mask_pixels: int = 16
    on_failure: str = "stop"
    max_reprojection_error: float = 4.0
    min_matches: int = 12
    init_min_inliers: int = 30
    init_min_tri_angle: float = 4.0
    abs_pose_min_inliers: int = 12
    scene_near_factor: float = OracleConfig.scene_near_factor
    scene_far_factor: float = OracleConfig.scene_far_factor
    box_padding: float = OracleConfig.box_padding
    seed: int = 0
    mapper_restarts: int = 4
    min_epipolar_consistency: float = 0.2
    final_cauchy_px: float = 0.5

    def __post_init__(self) -> None:
        if self.matcher not in ("auto", "exhaustive", "sequential"):
            raise ValueError(f"matcher must be auto, exhaustive or sequential, got {self.matcher!r}")
        if self.upscale < 1:
            raise ValueError(f"upscale must be a positive integer, got {self.upscale}")
        if not self.epipolar_error > 0:
            raise ValueError(f"epipolar_error must be a positive number of pixels, got {self.epipolar_error}")
        if self.grey not in GREY_MODES:
            raise ValueError(f"grey must be one of {', '.join(GREY_MODES)}, got {self.grey!r}")
        if not (np.isfinite(self.final_cauchy_px) and self.final_cauchy_px >= 0):
            raise ValueError(f"final_cauchy_px must be a finite number >= 0 (0: no final robust BA), got {self.final_cauchy_px}")
        if not 0.0 <= self.min_epipolar_consistency < 1.0:
            raise ValueError(f"min_epipolar_consistency must be in [0, 1), got {self.min_epipolar_consistency}")
        if self.on_failure not in ("stop", "skip"):
            raise ValueError(f"on_failure must be stop or skip, got {self.on_failure!r}")


class ObjectRegistrationError(InputsError):
    """An object could not be reconstructed; the message names it, the counts and what helps."""


@dataclass
class ObjectSfM:
    """Raw per-object reconstruction, in the reconstruction's own frame and unit."""

    frames: np.ndarray
    cam_to_obj: np.ndarray
    sparse_pix: list[np.ndarray]
    sparse_depth: list[np.ndarray]
    sparse_weight: list[np.ndarray]
    num_features: int
    num_points: int
    candidate_frames: int
    #: Mean reprojection error of the kept reconstruction, in input-frame pixels.
    reprojection_error_px: float = float("nan")
    #: Every model of every mapper restart: seed, frames registered, mean reprojection error (px).
    restarts: list[dict] = field(default_factory=list)
    #: Frames whose pose contradicted their verified matches, and what was done (osn.sfm_repair).
    repaired_frames: list[dict] = field(default_factory=list)


@dataclass
class PreprocessReport:
    """What SfM achieved per object; accuracy entries only when ground truth is known."""

    objects: list[dict] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# pycolmap
# --------------------------------------------------------------------------------------------


def _upscale(image: np.ndarray, factor: int, order: int = 3) -> np.ndarray:
    """Upsampling by an integer factor (bicubic for images, ``order=0`` for masks).

    SIFT finds few features on objects of ~30 pixels; a blocky (nearest) image gives fewer still.
    """
    if factor == 1:
        return image
    from skimage.transform import resize

    h, w = image.shape[:2]
    out = resize(image, (h * factor, w * factor) + image.shape[2:], order=order, preserve_range=True, anti_aliasing=False)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _erode(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask
    from scipy.ndimage import binary_erosion

    return binary_erosion(mask, iterations=r)


#: Rec. 709 luma weights, the grey conversion COLMAP applies to colour images.
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: ``grey: auto`` projects on the principal colour axis when the luminance's contrast is below
#: this fraction of that axis' contrast (both on unit colour vectors).
AUTO_GREY_RATIO = 0.5


def principal_grey(images: np.ndarray, masks: np.ndarray, mode: str = "principal") -> np.ndarray | None:
    """``(T,H,W)`` uint8 grey frames for SIFT: RGB projected on the object's principal colour axis.

    SIFT sees grey levels only. An object painted in two colours of about equal luminance (the
    gnome's red and blue) is nearly blank in luminance, but not along the axis joining its
    colours. The axis and the min-max stretch come from the pixels in ``masks`` over all frames,
    so one mapping serves every frame and descriptors stay comparable. With ``mode="auto"`` this
    happens only when luminance has less than ``AUTO_GREY_RATIO`` of the axis' contrast (a
    checker of a light and a dark colour keeps the luminance, whose fine detail a stretch along
    the checker's axis would drown); ``None`` means "use luminance".
    """
    px = images[masks].reshape(-1, 3).astype(np.float64)
    if len(px) < 2:
        return None
    mean = px.mean(axis=0)
    _, _, vt = np.linalg.svd(px - mean, full_matrices=False)
    axis = vt[0] if vt[0] @ LUMA >= 0 else -vt[0]  # brighter colours stay brighter
    if mode == "auto":
        luma_std = np.std(px @ (LUMA / np.linalg.norm(LUMA)))
        if luma_std >= AUTO_GREY_RATIO * np.std(px @ axis):
            return None
    proj = (images.astype(np.float64) - mean) @ axis
    lo, hi = proj[masks].min(), proj[masks].max()
    return np.clip(np.rint((proj - lo) / max(hi - lo, 1e-9) * 255.0), 0, 255).astype(np.uint8)


def reconstruct_object(
    images: np.ndarray, masks: np.ndarray, object_id: int, K: np.ndarray, cfg: PreprocessConfig, name: str = "",
    work_dir: Path | None = None,
) -> ObjectSfM:
    """SfM of one object from ``images (T,H,W,3) uint8`` and ``masks (T,H,W)`` instance ids.

    ``work_dir`` (created, must not exist) keeps COLMAP's images, ``database.db`` and the final
    model (``model/``, after the registration check and the final bundle adjustment) for inspection;
    by default they live in a temporary directory that is removed.

    Raises:
        ObjectRegistrationError: too few frames, features or points; the message says what helps.
    """
    import imageio.v3 as iio
    import pycolmap

    # COLMAP logs every step to stderr; our own messages say what matters.
    pycolmap.logging.minloglevel = int(os.environ.get("OSN_COLMAP_LOGLEVEL", 3))
    label = f"object {object_id}" + (f" ({name})" if name else "")
    T, H, W = masks.shape
    frames = [t for t in range(T) if (masks[t] == object_id).sum() >= cfg.min_mask_pixels]
    advice = "use more frames, a higher resolution, or more texture on the object"
    if len(frames) < cfg.min_frames:
        raise ObjectRegistrationError(
            f"{label}: visible in {len(frames)} frame(s) (>= {cfg.min_mask_pixels} pixels), "
            f"needs >= {cfg.min_frames}; {advice}"
        )
    if work_dir is None:
        work = Path(tempfile.mkdtemp(prefix=f"osn_sfm_{object_id}_"))
    else:
        work = Path(work_dir)
        work.mkdir(parents=True)
    try:
        img_dir, mask_dir, out_dir = work / "images", work / "masks", work / "sparse"
        for d in (img_dir, mask_dir, out_dir):
            d.mkdir()
        names = []
        frames_img = dict(zip(frames, images[frames]))
        if cfg.grey != "luminance":
            grey = principal_grey(images[frames], masks[frames] == object_id, cfg.grey)
            if grey is not None:
                frames_img = dict(zip(frames, grey))
        for t in frames:
            n = f"{t:05d}.png"
            names.append(n)
            m = _erode(masks[t] == object_id, cfg.mask_erosion)
            iio.imwrite(img_dir / n, _upscale(frames_img[t], cfg.upscale))
            iio.imwrite(mask_dir / f"{n}.png", _upscale((m * 255).astype(np.uint8), cfg.upscale, order=0))
        db = work / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        u = cfg.upscale  # pixel corners stay at integers, so every intrinsic scales by u
        reader.camera_params = f"{u * K[0, 0]},{u * K[1, 1]},{u * K[0, 2]},{u * K[1, 2]}"
        reader.mask_path = str(mask_dir)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = 1
        extraction.sift.max_num_features = cfg.max_features
        extraction.sift.peak_threshold = cfg.peak_threshold
        pycolmap.extract_features(
            db, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
        )
        database = pycolmap.Database.open(db)
        try:
            num_features = int(database.num_keypoints())
        finally:
            database.close()
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = 1
        matching.guided_matching = cfg.guided_matching
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.max_error = cfg.epipolar_error * cfg.upscale  # in SIFT-image pixels
        use_seq = cfg.matcher == "sequential" or (cfg.matcher == "auto" and len(frames) > cfg.exhaustive_max_frames)
        if use_seq:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = cfg.sequential_overlap
            pycolmap.match_sequential(
                db, matching_options=matching, pairing_options=pairing, verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        else:
            pycolmap.match_exhaustive(
                db, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
            )
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = 1
        opts.mapper.num_threads = 1
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.min_model_size = min(cfg.min_frames, 3)
        # COLMAP's defaults (100 inliers, 16 degrees) are tuned for megapixel photos; a 128x128
        # object crop has tens of matches and a short baseline.
        opts.min_num_matches = cfg.min_matches
        opts.mapper.init_min_num_inliers = cfg.init_min_inliers
        opts.mapper.init_min_tri_angle = cfg.init_min_tri_angle
        opts.mapper.abs_pose_min_num_inliers = cfg.abs_pose_min_inliers
        rec, tried = _best_of_restarts(db, img_dir, out_dir, opts, cfg)
        if rec is None:
            raise ObjectRegistrationError(
                f"{label}: SfM found no reconstruction ({num_features} features in {len(frames)} frames); {advice}"
            )
        repaired = repair_registrations(
            rec, db, np.diag([u, u, 1.0]) @ K, 2.0 * cfg.epipolar_error * u, cfg.min_epipolar_consistency,
            cfg.abs_pose_min_inliers, cfg.seed,
        )
        if cfg.final_cauchy_px > 0:
            bundle_adjust(rec, cfg.final_cauchy_px * u)
        if work_dir is not None:
            (work / "model").mkdir()
            rec.write(str(work / "model"))
        sfm = _collect(rec, label, frames, num_features, cfg, advice, W, H)
        sfm.reprojection_error_px = rec.compute_mean_reprojection_error() / cfg.upscale
        sfm.restarts = tried
        sfm.repaired_frames = repaired
        return sfm
    finally:
        if work_dir is None:
            shutil.rmtree(work, ignore_errors=True)


def _best_of_restarts(db: Path, img_dir: Path, out_dir: Path, opts, cfg: PreprocessConfig) -> tuple[object, list[dict]]:
    """Incremental mapping from ``cfg.mapper_restarts`` seeds: the best reconstruction (None if
    no restart found one) and, per model found, its seed, frames and mean reprojection error.

    A small object seen nearly in weak perspective has a depth-reversed twin: the mapper can
    settle in either, and the reversed one turns its rotations the wrong way, by an error that
    grows along the video (gnome-house sofa at 256 px: 17 degrees). Under full perspective the
    twin fits worse, so among the restarts the one registering the most frames with the lowest
    mean reprojection error wins (same sofa, 6 seeds: 0.75 px in the 2x-upsampled images and 2.5
    degrees for the true one against 0.84-0.87 px and 17 degrees for the five reversed ones).
    """
    import pycolmap

    best, best_key, best_idx, tried = None, None, -1, []
    for k in range(max(cfg.mapper_restarts, 1)):
        opts.random_seed = opts.mapper.random_seed = cfg.seed + k
        (out_dir / str(k)).mkdir()
        recs = pycolmap.incremental_mapping(db, img_dir, out_dir / str(k), options=opts)
        for rec in recs.values():
            err = rec.compute_mean_reprojection_error()
            tried.append({"seed": cfg.seed + k, "registered_frames": rec.num_reg_images(), "reprojection_error_px": err / cfg.upscale})
            key = (rec.num_reg_images(), -err)
            if best_key is None or key > best_key:
                best, best_key, best_idx = rec, key, len(tried) - 1
    for j, t in enumerate(tried):
        t["kept"] = j == best_idx
    return best, tried


def _collect(
    rec, label: str, frames: list[int], num_features: int, cfg: PreprocessConfig, advice: str, width: int, height: int
) -> ObjectSfM:
    reg = sorted(rec.images.values(), key=lambda im: im.name)
    reg = [im for im in reg if im.has_pose]
    if len(reg) < cfg.min_frames or rec.num_points3D() < cfg.min_points:
        raise ObjectRegistrationError(
            f"{label}: registered {len(reg)} of {len(frames)} frames with {rec.num_points3D()} points "
            f"from {num_features} features; needs >= {cfg.min_frames} frames and >= {cfg.min_points} points; {advice}"
        )
    out_frames, poses, pix_l, dep_l, w_l = [], [], [], [], []
    for im in reg:
        cfw = np.eye(4)
        cfw[:3, :] = im.cam_from_world().matrix()
        xy, z, err = [], [], []
        for p2 in im.points2D:
            if not p2.has_point3D():
                continue
            pt = rec.point3D(p2.point3D_id)
            if pt.error > cfg.max_reprojection_error:
                continue
            depth = float((cfw[:3, :3] @ pt.xyz + cfw[:3, 3])[2])
            if depth <= 0:
                continue
            xy.append(p2.xy)
            z.append(depth)
            err.append(pt.error)
        if not z:
            continue
        out_frames.append(int(Path(im.name).stem))
        poses.append(invert_pose(cfw))
        # Back to input pixels; pixel centres are at .5 in both COLMAP and our convention.
        pix = np.floor(np.asarray(xy) / cfg.upscale).astype(np.int64)
        pix_l.append(np.clip(pix, 0, [width - 1, height - 1]))
        dep_l.append(np.asarray(z))
        # Down-weight observations with large reprojection error (Cauchy-like, 1 px scale).
        w_l.append(1.0 / (1.0 + np.asarray(err) ** 2))
    return ObjectSfM(
        frames=np.array(out_frames, dtype=np.int64),
        cam_to_obj=np.stack(poses),
        sparse_pix=pix_l,
        sparse_depth=dep_l,
        sparse_weight=w_l,
        num_features=num_features,
        num_points=int(rec.num_points3D()),
        candidate_frames=len(frames),
    )


# --------------------------------------------------------------------------------------------
# Whole scenes
# --------------------------------------------------------------------------------------------


def preprocess_video(
    images: np.ndarray,
    masks: np.ndarray,
    K: np.ndarray,
    timestamps: np.ndarray,
    object_names: dict[int, str],
    anchor: int,
    cfg: PreprocessConfig,
    progress: Callable[[str], None] | None = None,
) -> tuple[SceneInputs, PreprocessReport]:
    """Per-object SfM for a whole video; returns inputs (SfM frames and units) and a report."""
    T, H, W = masks.shape
    report = PreprocessReport()
    objects: list[ObjectInputs] = []
    for oid, name in sorted(object_names.items()):
        if progress:
            progress(f"SfM of object {oid} ({name})")
        try:
            sfm = reconstruct_object(images, masks, oid, K, cfg, name)
        except ObjectRegistrationError as e:
            if cfg.on_failure == "stop" or oid == anchor:
                raise
            log.warning("%s -- training without it", e)
            report.dropped.append(oid)
            report.objects.append({"id": oid, "name": name, "error": str(e)})
            continue
        objects.append(
            object_inputs_from_observations(
                oid, name, sfm.frames, sfm.cam_to_obj, sfm.sparse_pix, sfm.sparse_depth, sfm.sparse_weight,
                K, W, H, cfg.box_padding, metres_per_unit=None,
            )
        )
        report.objects.append(
            {
                "id": oid,
                "name": name,
                "candidate_frames": sfm.candidate_frames,
                "registered_frames": len(sfm.frames),
                "features": sfm.num_features,
                "points": sfm.num_points,
                # Without ground truth these say how much to trust the poses: the kept model's
                # error, and how the restarts disagreed (a reversed twin fits visibly worse).
                "reprojection_error_px": sfm.reprojection_error_px,
                "restarts": sfm.restarts,
                "repaired_frames": sfm.repaired_frames,
            }
        )
    masks = masks.copy()
    for oid in report.dropped:
        masks[masks == oid] = IGNORE_ID
    scene_near, scene_far = scene_volume(objects, cfg.scene_near_factor, cfg.scene_far_factor)
    inputs = SceneInputs(
        width=W, height=H, K=K, timestamps=np.asarray(timestamps, dtype=np.float64), images=images, masks=masks,
        objects=objects, anchor=anchor, scene_near=scene_near, scene_far=scene_far, source="colmap",
        meta={"preprocess": cfg.__dict__, "dropped_objects": report.dropped},
    )
    return inputs, report


def report_lines(objects: list[dict]) -> list[str]:
    """One line per object of a :class:`PreprocessReport` (and one per repaired frame)."""
    lines = []
    for r in objects:
        if "error" in r:
            lines.append(f"  object {r['id']} ({r['name']}): DROPPED: {r['error']}")
            continue
        line = (f"  object {r['id']} ({r['name']}): {r['registered_frames']}/{r['candidate_frames']} frames, "
                f"{r['points']} points, reprojection error {r['reprojection_error_px']:.2f} px")
        if "rotation_error_deg_max" in r:
            line += (f", registered {100 * r['registered_fraction']:.0f}% of visible frames, rotation error "
                     f"max {r['rotation_error_deg_max']:.3f} deg, centre error mean {r['center_error_m_mean']:.4f} m")
        lines.append(line)
        for f in r.get("repaired_frames", []):
            lines.append(f"    frame {f['frame']}: {f['action']} ({100 * f['consistency']:.1f}% of its verified "
                         f"matches fit SfM's pose, {100 * f['consistency_after']:.1f}% after)")
    return lines


def preprocess_dataset(
    dataset_root: str | Path, cfg: PreprocessConfig, progress=None,
    video: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[SceneInputs, PreprocessReport]:
    """Per-object SfM on a benchgen dataset's training video, aligned to its ground truth.

    The dataset's instance masks stand in for a learned segmenter and its intrinsics are the
    known camera. Ground truth is used only *after* SfM, to measure accuracy and to record each
    object's unit and the world-to-anchor similarity (needed to place test cameras). ``video``:
    :func:`scenecore.dataset.read_training_video`'s result when the caller already read it.
    """
    root = Path(dataset_root)
    scene = D.load_scene(root)
    if video is None:
        video = D.read_training_video(root, scene)
    oracle = oracle_inputs(root, OracleConfig(min_pixels=1, points_per_frame=1), video)
    names = {o.id: o.name for o in scene.objects}
    inputs, report = preprocess_video(
        oracle.images, oracle.masks, oracle.K, oracle.timestamps, names, scene.anchor_id, cfg, progress
    )
    align_to_ground_truth(inputs, oracle, report, scene, depths=video[1])
    inputs.meta["dataset"] = str(root)
    check_inputs(inputs, root)
    return inputs, report


def align_to_ground_truth(
    inputs: SceneInputs, oracle: SceneInputs, report: PreprocessReport, scene: D.Scene, depths: np.ndarray
) -> None:
    """Fill units, world-to-anchor and accuracy figures from ground truth.

    Each object's metres per SfM unit is the median of ``depths (T, H, W)``, the rendered
    ground-truth planar depth, over SfM depth at its sparse points. A similarity per object maps
    the SfM camera poses (object frame) onto the ground-truth ones
    (:func:`scenecore.cameras.fit_pose_similarity`); rotation and camera-centre errors are
    measured after it. Its scale is not used as the unit: least squares on noisy camera centres
    shrinks it (on the tests' 128 px scene the block's came out 0.41 of the truth, which skewed
    every scale-based evaluation figure); its ratio to the depth unit is reported
    (``similarity_unit_ratio``). An object whose similarity cannot be fitted still gets its unit.
    """
    by_id = {o.id: o for o in oracle.objects}
    for o, rep in zip(inputs.objects, [r for r in report.objects if "error" not in r]):
        gt = by_id[o.id]
        o.unit_to_world = depth_unit(o, depths)
        if o.unit_to_world is None:
            rep["unit"] = "not measurable: no sparse point has a finite ground-truth depth"
        slots = [gt.frame_slot(int(t)) for t in o.frames]
        keep = [i for i, s in enumerate(slots) if s is not None]
        gt_poses = gt.cam_to_obj[[slots[i] for i in keep]]
        try:
            S = fit_pose_similarity(o.cam_to_obj[keep], gt_poses)
        except ValueError as e:
            rep["alignment"] = f"not measurable: {e}"
            continue
        scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
        R = S[:3, :3] / scale
        if o.unit_to_world is not None:
            rep["similarity_unit_ratio"] = scale * gt.unit_to_world / o.unit_to_world
        c_sfm, c_gt = o.cam_to_obj[keep, :3, 3], gt_poses[:, :3, 3]
        rot = [rotation_angle_deg(R @ o.cam_to_obj[i, :3, :3], gt.cam_to_obj[slots[i], :3, :3]) for i in keep]
        aligned = c_sfm @ S[:3, :3].T + S[:3, 3]
        err = np.linalg.norm(aligned - c_gt, axis=1) * gt.unit_to_world  # metres
        gt_visible = len(gt.frames)
        rep.update(
            gt_visible_frames=gt_visible,
            registered_fraction=len(o.frames) / max(gt_visible, 1),
            rotation_error_deg_max=float(max(rot)),
            rotation_error_deg_mean=float(np.mean(rot)),
            center_error_m_mean=float(err.mean()),
            center_error_m_max=float(err.max()),
        )
    # Test-view alignment: the similarity taking the ground-truth training cameras (world) onto
    # the anchor's SfM cameras, so evaluation can bring test cameras into the anchor's frame.
    anchor = inputs.object(inputs.anchor)
    c2w = {f.time_index: f.camera_to_world for f in scene.train_frames}
    try:
        inputs.world_to_anchor = fit_pose_similarity(np.stack([c2w[int(t)] for t in anchor.frames]), anchor.cam_to_obj)
    except ValueError as e:  # the inputs still train; evaluation says why it cannot place test views
        log.warning("test-view alignment failed for the anchor %s: %s", anchor.name, e)
        inputs.world_to_anchor = None
        for rep in report.objects:
            if rep.get("id") == anchor.id:
                rep["test_view_alignment"] = f"failed: {e}"


def depth_unit(obj: ObjectInputs, depths: np.ndarray) -> float | None:
    """Metres per unit of ``obj``: the median of ground-truth planar depth ``depths (T, H, W)``
    over the object's sparse depths at the same pixels (None without a usable point)."""
    ratio = np.concatenate([
        depths[int(t)][pix[:, 1], pix[:, 0]] / dep for t, pix, dep in zip(obj.frames, obj.sparse_pix, obj.sparse_depth)
    ] or [np.zeros(0)])
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    return float(np.median(ratio)) if len(ratio) else None


def load_video(frames_dir: str | Path, masks_dir: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read a video as sorted PNG/JPG frames plus same-named instance-id PNG masks.

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

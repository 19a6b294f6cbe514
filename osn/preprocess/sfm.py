"""Per-object SfM with pycolmap: the COLMAP reconstruction of one object (``osn preprocess``).

For every object, SIFT features are extracted only inside its mask, matched (exhaustively for
short videos, sequentially for long ones) and reconstructed by incremental mapping with the known,
shared pinhole camera (no intrinsics refinement); frames posed against their own matches are
repaired (:mod:`osn.preprocess.repair`), and the model is compared with its depth-reversed twin
(:mod:`osn.preprocess.twin`, reported). Each object's reconstruction has its own frame and unit;
:mod:`osn.preprocess.video` turns a whole video's reconstructions into per-object inputs.

No GUI, every random seed fixed, single-threaded where threads change results.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenecore.cameras import invert_pose
from scenecore.config import choice, flag, integer, number, validate
from osn.preprocess.inputs import BOX_PADDING, NORMALISATION_RULES, SCENE_FAR_FACTOR, SCENE_NEAR_FACTOR, InputsError
from osn.preprocess.mapping import best_of_restarts, extract_features, match_features
from osn.preprocess.repair import bundle_adjust, repair_registrations, settle_points
from osn.preprocess.sift_frames import GREY_MODES, crop_box, write_colmap_images
from osn.preprocess.twin import compare_with_twin

log = logging.getLogger(__name__)



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
        anchor_downscale: SfM of the anchor (background), which fills the frame, on frames
            averaged down by this factor (its sparse pixels mapped back to the blocks' centres);
            1 = full frames. Small objects need large frames, the anchor does not: gnome-house's
            room at 1024 px, upsampled like the objects, is 4x the pixels of 512 px. Which room
            SfM trains the best valid set is not settled (measurements in docs/experiments/).
        crop_margin: SIFT sees the frames cropped to the box of the object's masks over the video,
            grown by this many pixels and to hold the principal point (-1: whole frames). SIFT
            runs on every pixel it is given, however little of it the mask keeps: on a small
            object's whole frames, upsampled, most of SIFT's time goes outside the object. It
            changes which features SIFT finds near the crop's border (at 512 px it worsened the
            gnome-house ring-toy's worst frame), so it is off by default; at 1024 px it registers
            what whole frames do (docs/preprocess.md).
        guided_matching: re-match each verified pair under its two-view geometry: it removes the
            wrong matches that otherwise leave a small object's worst frames far off in rotation
            (gnome-house's sofa).
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
        drop_occluding: the sparse depths :func:`osn.preprocess.freespace.occluding_flags` flags
            (phantoms): ``training`` drops every object's from training, before normalising it,
            except the anchor's, which are dropped after (they still set its near plane, and with it
            Eq. 1's scene volume); ``all`` drops the anchor's before normalising too; ``none``
            keeps them. A few phantom depths on a small object (gnome-house's sofa) set its near
            plane and box; the room's pull its learned surface toward the camera next to the objects
            and cut their contact bounds tight; normalising the room without them makes the valid
            set worse (docs/preprocess.md).
        points_per_frame: sparse depths per object and frame kept for training, at the training
            resolution (after any downscale), chosen at random with ``seed``; 0 = as the oracle
            (:func:`osn.preprocess.inputs.auto_points_per_frame`). Near, far and boxes use all.
        seed: every random seed of pycolmap (restart ``k`` of the mapper uses ``seed + k``).
        mapper_restarts: incremental mapping runs on the same matches; the best one is kept
            (:func:`osn.preprocess.mapping.best_of_restarts` explains why a single run is not enough).
        anchor_mapper_restarts: the same for the anchor. It fills the frame, so it has no
            depth-reversed twin, and its restarts find models that agree in frames and error; yet
            the valid set trained from a single run spreads wider over training seeds, for little
            time saved, so it keeps four (measurements in docs/experiments/).
        min_epipolar_consistency: a registered frame with a smaller fraction of its verified
            matches within ``2 * epipolar_error`` of the model's epipolar geometry is re-posed
            or dropped (:mod:`osn.preprocess.repair`; correct frames lie far above the threshold, a
            wrong one far below it).
        final_cauchy_px: scale (input-frame pixels) of the Cauchy loss of a last global bundle
            adjustment; 0 skips it. COLMAP's own global BA uses a squared loss, which lets the
            few bad observations of a weakly seen frame pull it (the gnome-house ring-toy's first
            frame at 1024 px); the default scale corrects it best of those tried (docs/preprocess.md).
        bridge_unposed: pose an object in the frames its mask shows it in but SfM did not register
            it (or the consistency check dropped), from its registered neighbours and the anchor's
            cameras, where the bridged pose fits the mask as well as its registered poses fit
            theirs (:mod:`osn.preprocess.bridge`); those frames carry no sparse depth.
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
    anchor_downscale: int = 1
    crop_margin: int = -1
    min_frames: int = 3
    min_points: int = 20
    min_mask_pixels: int = 16
    on_failure: str = "stop"
    max_reprojection_error: float = 4.0
    min_matches: int = 12
    init_min_inliers: int = 30
    init_min_tri_angle: float = 4.0
    abs_pose_min_inliers: int = 12
    scene_near_factor: float = SCENE_NEAR_FACTOR
    scene_far_factor: float = SCENE_FAR_FACTOR
    box_padding: float = BOX_PADDING
    drop_occluding: str = "training"
    points_per_frame: int = 0
    seed: int = 0
    mapper_restarts: int = 4
    anchor_mapper_restarts: int = 4
    min_epipolar_consistency: float = 0.2
    final_cauchy_px: float = 0.5
    bridge_unposed: bool = True

    def __post_init__(self) -> None:
        validate(self, "preprocess", PREPROCESS_RULES)


#: What :class:`PreprocessConfig` accepts (checked in ``__post_init__``).
PREPROCESS_RULES = {
    "matcher": choice("auto", "exhaustive", "sequential"),
    "exhaustive_max_frames": integer(0),
    "sequential_overlap": integer(1),
    "max_features": integer(1),
    "peak_threshold": number(0.0, lo_open=True),
    "guided_matching": flag(),
    "epipolar_error": number(0.0, lo_open=True, what="a positive number of pixels"),
    "grey": choice(*GREY_MODES),
    "mask_erosion": integer(0),
    "upscale": integer(1),
    "anchor_downscale": integer(1),
    "crop_margin": integer(-1),
    "min_frames": integer(1),
    "min_points": integer(0),
    "min_mask_pixels": integer(1),
    "on_failure": choice("stop", "skip"),
    "max_reprojection_error": number(0.0, lo_open=True),
    "min_matches": integer(0),
    "init_min_inliers": integer(0),
    "init_min_tri_angle": number(0.0),
    "abs_pose_min_inliers": integer(0),
    **NORMALISATION_RULES,
    "drop_occluding": choice("training", "all", "none"),
    "points_per_frame": integer(0),
    "seed": integer(0),
    "mapper_restarts": integer(0),  # 0 runs the mapper once, like 1
    "anchor_mapper_restarts": integer(0),
    "min_epipolar_consistency": number(0.0, 1.0, hi_open=True),
    "final_cauchy_px": number(0.0, what="a finite number >= 0 (0: no final robust BA)"),
    "bridge_unposed": flag(),
}


#: ``anchor_downscale="auto"`` in :func:`pipeline_config`: the anchor's SfM on frames of at most
#: this size (the room fills the frame and registers as accurately at 512 px as above it:
#: docs/preprocess.md).
ANCHOR_SFM_SIZE = 512
#: ``crop_margin="auto"``: crops of this margin from this SfM resolution up, whole frames below (at
#: 512 px crops worsen the ring-toy's worst frame; from 768 px they register frames that whole
#: frames miss and shorten SfM at no cost in accuracy: docs/preprocess.md).
CROP_FROM, CROP_MARGIN = 768, 32
#: What ``osn preprocess`` and ``osn demo`` run SfM with where it differs from
#: :class:`PreprocessConfig`'s own defaults (the library's): sizes chosen for the frames' width,
#: and an object that fails to register dropped and reported (the anchor still stops).
PIPELINE_DEFAULTS: dict[str, int | str] = {"anchor_downscale": "auto", "crop_margin": "auto", "on_failure": "skip"}


def pipeline_config(width: int, **options: int | str | float | bool) -> PreprocessConfig:
    """The SfM settings of ``osn preprocess`` and ``osn demo`` for frames ``width`` px wide: the
    one owner of their defaults (:data:`PIPELINE_DEFAULTS` over :class:`PreprocessConfig`'s), so
    a hand-run ``osn preprocess`` reproduces the demo's SfM. ``auto`` sizes are resolved here.

    Raises:
        ValueError: an option out of range, or a size neither ``auto`` nor an integer.
    """
    opts = {**PIPELINE_DEFAULTS, **options}
    if opts["anchor_downscale"] == "auto":
        opts["anchor_downscale"] = max(1, width // ANCHOR_SFM_SIZE)
    if opts["crop_margin"] == "auto":
        opts["crop_margin"] = CROP_MARGIN if width >= CROP_FROM else -1
    for k in ("anchor_downscale", "crop_margin"):
        opts[k] = int(opts[k])
    return PreprocessConfig(**opts)


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
    #: Mean reprojection error of the final model's points that give sparse depths (input-frame pixels).
    reprojection_error_px: float = float("nan")
    #: Every model of every mapper restart: seed, frames registered, mean reprojection error (px).
    restarts: list[dict] = field(default_factory=list)
    #: Frames whose pose contradicted their verified matches, and what was done (osn.preprocess.repair).
    repaired_frames: list[dict] = field(default_factory=list)
    #: The kept model against its depth-reversed twin (:func:`osn.preprocess.twin.compare_with_twin`).
    twin: dict = field(default_factory=dict)
    #: Points deleted after the final adjustment because it left them behind a camera that sees them.
    points_behind_dropped: int = 0


@dataclass
class PreprocessReport:
    """What SfM achieved per object; accuracy entries only when ground truth is known."""

    objects: list[dict] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# pycolmap
# --------------------------------------------------------------------------------------------


def reconstruct_object(
    images: np.ndarray, masks: np.ndarray, object_id: int, K: np.ndarray, cfg: PreprocessConfig, name: str = "",
    work_dir: Path | None = None, restart_workers: int = 1,
) -> ObjectSfM:
    """SfM of one object from ``images (T,H,W,3) uint8`` and ``masks (T,H,W)`` instance ids.

    ``work_dir`` (created, must not exist) keeps COLMAP's images, ``database.db`` and the final
    model (``model/``, after the registration check and the final bundle adjustment) for inspection;
    by default they live in a temporary directory that is removed. ``restart_workers``: mapper
    restarts run at once, on threads (the result does not depend on it).

    Raises:
        ObjectRegistrationError: too few frames, features or points; the message says what helps.
    """
    import pycolmap

    # COLMAP logs every step to stderr; our own messages say what matters.
    pycolmap.logging.minloglevel = int(os.environ.get("OSN_COLMAP_LOGLEVEL", 3))
    label = f"object {object_id}" + (f" ({name})" if name else "")
    T = masks.shape[0]
    frames = [t for t in range(T) if (masks[t] == object_id).sum() >= cfg.min_mask_pixels]
    if len(frames) < cfg.min_frames:
        raise ObjectRegistrationError(
            f"{label}: visible in {len(frames)} frame(s) (>= {cfg.min_mask_pixels} pixels), "
            f"needs >= {cfg.min_frames}; {ADVICE}"
        )
    if work_dir is None:
        work = Path(tempfile.mkdtemp(prefix=f"osn_sfm_{object_id}_"))
    else:
        work = Path(work_dir)
        work.mkdir(parents=True)
    try:
        return _reconstruct_in(work, images, masks, frames, object_id, K, cfg, label, keep_model=work_dir is not None,
                               restart_workers=restart_workers)
    finally:
        if work_dir is None:
            shutil.rmtree(work, ignore_errors=True)


#: The end of every registration failure's message.
ADVICE = "use more frames, a higher resolution, or more texture on the object"


def _reconstruct_in(
    work: Path, images: np.ndarray, masks: np.ndarray, frames: list[int], object_id: int, K: np.ndarray,
    cfg: PreprocessConfig, label: str, keep_model: bool, restart_workers: int = 1,
) -> ObjectSfM:
    """:func:`reconstruct_object` inside the empty directory ``work``, from the ``frames`` where
    the object is visible; with ``keep_model`` the final model is written to ``work/model``."""
    H, W = masks.shape[1:]
    img_dir, mask_dir, out_dir = work / "images", work / "masks", work / "sparse"
    for d in (img_dir, mask_dir, out_dir):
        d.mkdir()
    x0, y0, x1, y1 = crop_box(masks[frames] == object_id, cfg.crop_margin, (K[0, 2], K[1, 2]))
    K = K.copy()
    K[:2, 2] -= (x0, y0)  # the crop's camera: the principal point moves with its corner
    names = write_colmap_images(img_dir, mask_dir, images[:, y0:y1, x0:x1], masks[:, y0:y1, x0:x1], frames, object_id,
                                cfg.grey, cfg.mask_erosion, cfg.upscale)
    db = work / "database.db"
    num_features = extract_features(db, img_dir, mask_dir, names, K, cfg)
    match_features(db, len(frames), cfg)
    rec, tried = best_of_restarts(db, img_dir, out_dir, cfg, restart_workers)
    if rec is None:
        raise ObjectRegistrationError(
            f"{label}: SfM found no reconstruction ({num_features} features in {len(frames)} frames); {ADVICE}"
        )
    u = cfg.upscale
    repaired = repair_registrations(
        rec, db, np.diag([u, u, 1.0]) @ K, 2.0 * cfg.epipolar_error * u, cfg.min_epipolar_consistency,
        cfg.abs_pose_min_inliers, cfg.seed,
    )
    cauchy = cfg.final_cauchy_px * u if cfg.final_cauchy_px > 0 else None
    if cauchy is not None:
        bundle_adjust(rec, cauchy)
    behind = settle_points(rec)  # the kept depths, their weights and the reported error: the final model's
    twin = compare_with_twin(rec, cauchy, pixel_scale=u)
    if keep_model:
        (work / "model").mkdir()
        rec.write(str(work / "model"))
    sfm = _collect(rec, label, frames, num_features, cfg, W, H, (x0, y0))
    sfm.restarts = tried
    sfm.repaired_frames = repaired
    sfm.twin = twin
    sfm.points_behind_dropped = behind
    return sfm


def _collect(
    rec, label: str, frames: list[int], num_features: int, cfg: PreprocessConfig, width: int, height: int,
    corner: tuple[int, int],
) -> ObjectSfM:
    """The registered frames' poses and sparse depths of ``rec`` (a ``pycolmap.Reconstruction``)
    in input pixels (``corner``: the crop's top-left pixel); raises when too few frames or points
    were reconstructed."""
    reg = sorted(rec.images.values(), key=lambda im: im.name)
    reg = [im for im in reg if im.has_pose]
    if len(reg) < cfg.min_frames or rec.num_points3D() < cfg.min_points:
        raise ObjectRegistrationError(
            f"{label}: registered {len(reg)} of {len(frames)} frames with {rec.num_points3D()} points "
            f"from {num_features} features; needs >= {cfg.min_frames} frames and >= {cfg.min_points} points; {ADVICE}"
        )
    out_frames, poses, pix_l, dep_l, w_l = [], [], [], [], []
    kept_errors: dict[int, float] = {}
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
            kept_errors[p2.point3D_id] = pt.error
        if not z:
            continue
        out_frames.append(int(Path(im.name).stem))
        poses.append(invert_pose(cfw))
        # Back to input pixels; pixel centres are at .5 in both COLMAP and our convention.
        pix = np.floor(np.asarray(xy) / cfg.upscale).astype(np.int64) + np.asarray(corner)
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
        reprojection_error_px=float(np.mean(list(kept_errors.values()))) / cfg.upscale if kept_errors else float("nan"),
    )

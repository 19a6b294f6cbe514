"""COLMAP's steps for one object's crop: SIFT inside its masks, matching with geometric
verification, and incremental mapping from several seeds, the best model kept (pycolmap; every
run single-threaded with its seed fixed). :mod:`osn.preprocess.sfm` drives them.
"""

from __future__ import annotations

import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from osn.preprocess.sfm import PreprocessConfig


def extract_features(db: Path, img_dir: Path, mask_dir: Path, names: list[str], K: np.ndarray, cfg: PreprocessConfig) -> int:
    """SIFT inside the masks into the database ``db`` with the known camera; returns the keypoint count."""
    import pycolmap

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
        return int(database.num_keypoints())
    finally:
        database.close()


def match_features(db: Path, num_frames: int, cfg: PreprocessConfig) -> None:
    """Match and geometrically verify the features of ``db`` (sequential for long videos)."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    matching.guided_matching = cfg.guided_matching
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = cfg.epipolar_error * cfg.upscale  # in SIFT-image pixels
    use_seq = cfg.matcher == "sequential" or (cfg.matcher == "auto" and num_frames > cfg.exhaustive_max_frames)
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


def _mapper_options(cfg: PreprocessConfig):
    """``pycolmap.IncrementalPipelineOptions``: single-threaded, fixed intrinsics, small-crop thresholds."""
    import pycolmap

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
    return opts


def best_of_restarts(db: Path, img_dir: Path, out_dir: Path, cfg: PreprocessConfig, workers: int = 1
                      ) -> tuple[object, list[dict]]:
    """Incremental mapping from ``cfg.mapper_restarts`` seeds, ``workers`` runs at once on threads:
    the best reconstruction (None if no restart found one) and, per model found, its seed, frames
    and mean reprojection error.

    A small object seen nearly in weak perspective has a depth-reversed twin: the mapper can
    settle in either, and the reversed one turns its rotations the wrong way, by an error that
    grows along the video (gnome-house's sofa). Under full perspective the twin fits worse, so
    among the restarts the one registering the most frames with the lowest mean reprojection
    error wins (on that sofa the true model's error is below every reversed one's). The restarts
    can all settle in the twin: :mod:`osn.preprocess.twin` then builds it from the kept model
    and reports whether it fits better.

    Each run is single-threaded with its own options and seed, and COLMAP's random generator is
    per thread, so runs side by side give the models they give one after the other (the demo's
    room and gnome: equal poses, errors and point counts; ``test_mapper_restarts_on_threads_equal_one_after_another``).
    """
    import pycolmap

    def run(k: int):
        opts = _mapper_options(cfg)
        opts.random_seed = opts.mapper.random_seed = cfg.seed + k
        (out_dir / str(k)).mkdir()
        # Side by side, each run reads its own copy: two mappers opening one database failed now
        # and then ("No registered database factory succeeded").
        own = db if workers <= 1 else Path(shutil.copy(db, out_dir / str(k) / "database.db"))
        return pycolmap.incremental_mapping(own, img_dir, out_dir / str(k), options=opts)

    restarts = range(max(cfg.mapper_restarts, 1))
    with ThreadPoolExecutor(max(1, min(workers, len(restarts))), thread_name_prefix="mapper") as pool:
        runs = list(pool.map(run, restarts))  # in seed order, so ties are broken as one after another
    best, best_key, best_idx, tried = None, None, -1, []
    for k, recs in zip(restarts, runs):
        for rec in recs.values():
            err = rec.compute_mean_reprojection_error()
            tried.append({"seed": cfg.seed + k, "registered_frames": rec.num_reg_images(), "reprojection_error_px": err / cfg.upscale})
            key = (rec.num_reg_images(), -err)
            if best_key is None or key > best_key:
                best, best_key, best_idx = rec, key, len(tried) - 1
    for j, t in enumerate(tried):
        t["kept"] = j == best_idx
    return best, tried

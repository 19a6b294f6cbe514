"""``validate``: check a dataset directory against format v1 and list every problem found."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from .covisibility import covisibility_path, read_covisibility
from .images import read_depth, read_ids, read_image, rgb_from_image
from .manifest import ids_problem, load_configuration, load_scene, load_valid_region, size_problem
from .model import NO_OBJECT, DatasetError, Frame, FramePaths, Scene, config_dirname, frame_paths

__all__ = ["validate", "iter_frame_files"]


def _rgb_problems(path: Path, scene: Scene) -> list[str]:
    """Readable, of the manifest's size, and stored as opaque 8-bit RGBA (what D-NeRF/nerfstudio read)."""
    try:
        img = read_image(path)
        rgb = rgb_from_image(img, path)
    except DatasetError as e:
        return [str(e)]
    if p := size_problem(path, rgb.shape[:2], scene):
        return [p]
    if img.ndim != 3 or img.shape[2] != 4:
        return [f"{path}: stored without alpha; the format stores 8-bit RGBA with alpha 255 (D-NeRF reads channel 4 as alpha)"]
    if (transparent := int((img[..., 3] != 255).sum())):
        return [f"{path}: {transparent} pixels have alpha below 255; the format stores opaque RGBA"]
    return []


def _check_frame_files(paths: FramePaths, scene: Scene, problems: list[str]) -> None:
    problems.extend(_rgb_problems(paths.rgb, scene))
    ids = depth = None
    try:
        ids = read_ids(paths.ids)
        if p := size_problem(paths.ids, ids.shape, scene):
            problems.append(p)
            ids = None
        elif p := ids_problem(paths.ids, ids, scene.num_objects):
            problems.append(p)
    except DatasetError as e:
        problems.append(str(e))
    try:
        depth = read_depth(paths.depth)
        if p := size_problem(paths.depth, depth.shape, scene):
            problems.append(p)
            depth = None
        elif np.isnan(depth).any():
            problems.append(f"{paths.depth}: {int(np.isnan(depth).sum())} NaN depths")
    except DatasetError as e:
        problems.append(str(e))
    if ids is not None and depth is not None:
        hit = ids != NO_OBJECT
        bad = hit & ~(np.isfinite(depth) & (depth > 0))
        if bad.any():
            problems.append(f"{paths.depth}: {int(bad.sum())} pixels with an object have non-finite or non-positive depth")


def validate(root: str | Path, check_images: bool = True) -> list[str]:
    """Check a dataset directory against format v1; return every problem found (empty = valid).

    Each problem names the file and what is wrong: missing file, unreadable file, wrong shape or
    dtype, unknown version, ids out of range, non-finite pose, inconsistent configuration, ...
    """
    root = Path(root)
    problems: list[str] = []
    if not root.is_dir():
        return [f"{root}: not a directory"]
    try:
        scene = load_scene(root)
    except DatasetError as e:
        return [str(e)]
    K = scene.num_objects
    region = None
    try:
        region = load_valid_region(root, K)
        if region.anchor != scene.anchor_id:
            problems.append(f"{root / 'valid_region.json'}: anchor {region.anchor} differs from the manifest's {scene.anchor_id}")
    except DatasetError as e:
        problems.append(str(e))
    if check_images:
        for f in scene.train_frames:
            _check_frame_files(frame_paths(root, f.name), scene, problems)
    for g in range(scene.num_configurations):
        try:
            cfg = load_configuration(root, g, K)
        except DatasetError as e:
            problems.append(str(e))
            continue
        cfg_path = root / "configs" / config_dirname(g) / "config.json"
        if abs(cfg.scales[scene.anchor_id] - 1.0) > 1e-12:
            problems.append(f"{cfg_path}: the anchor's scale is {cfg.scales[scene.anchor_id]}, must be 1")
        if region is not None and not region.contains(cfg.scales):
            problems.append(f"{cfg_path}: scales {cfg.scales.tolist()} lie outside the valid region")
        if check_images:
            for f in scene.test_frames:
                _check_frame_files(frame_paths(root, f.name, g), scene, problems)
    if check_images:
        problems += _covisibility_problems(root, scene)
    return problems


def _covisibility_problems(root: Path, scene: Scene) -> list[str]:
    """Stored co-visibility masks (optional: datasets written before them have none) are either
    absent for every configuration or readable and of the manifest's sizes for all of them.
    Their content is checked by ``benchgen verify``, which recomputes them."""
    G = scene.num_configurations
    present = [g for g in range(G) if covisibility_path(root, g).exists() or covisibility_path(root, g).is_symlink()]
    if not present:
        return []
    problems = [f"{covisibility_path(root, g)}: missing, while {len(present)} of {G} configurations store "
                "co-visibility masks (rerun 'benchgen generate' with the same options to add it)"
                for g in range(G) if g not in set(present)]
    for g in present:
        try:
            read_covisibility(root, scene, g)
        except DatasetError as e:
            problems.append(str(e))
    return problems


def iter_frame_files(root: str | Path, scene: Scene) -> Iterable[tuple[Frame, int | None, FramePaths]]:
    """Every (frame, configuration or None, paths) the dataset should contain."""
    for f in scene.train_frames:
        yield f, None, frame_paths(root, f.name)
    for g in range(scene.num_configurations):
        for f in scene.test_frames:
            yield f, g, frame_paths(root, f.name, g)

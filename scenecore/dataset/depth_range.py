"""The scene's near and far depth: ``near`` / ``far`` in ``scene.json`` and ``transforms_*.json``.

NeRF-style methods sample each ray between a near and a far plane, and their loaders' defaults
(2 and 6 world units in D-NeRF and nerfstudio) clip our rooms silently. ``benchgen generate``
therefore records a range that encloses every ground-truth surface, in both conventions such
methods use: ``near`` is at most every planar depth (camera-frame z; D-NeRF's rays have unit z)
and ``far`` at least every distance along the ray (nerfstudio's rays have unit length), over the
training video and every configuration's test views, with a margin of :data:`MARGIN` either side,
rounded outward to :data:`ROUND` world units.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from ..cameras import ray_lengths
from .images import read_depth
from .model import DatasetError, Scene
from .validation import iter_frame_files

__all__ = ["MARGIN", "ROUND", "depth_range", "with_depth_range"]

#: Relative margin: ``near = (1 - MARGIN) min planar depth``, ``far = (1 + MARGIN) max ray distance``.
MARGIN = 0.1
#: The range is rounded outward to this many world units (centimetres), so that it reads well as a flag.
ROUND = 0.01


def depth_range(root: str | Path, scene: Scene) -> tuple[float, float]:
    """``(near, far)`` enclosing every surface of every ground-truth frame of the dataset at ``root``
    (see the module docstring); ``+inf`` depths (nothing hit) are left out.

    Raises:
        DatasetError: a depth file is unreadable, or no frame hits any surface.
    """
    lengths = ray_lengths(scene.intrinsics.matrix(), scene.width, scene.height)
    lo, hi = math.inf, 0.0
    for _, _, paths in iter_frame_files(root, scene):
        depth = read_depth(paths.depth)
        if depth.shape != lengths.shape:
            raise DatasetError(f"{paths.depth}: depth of shape {depth.shape}, expected {lengths.shape}")
        hit = np.isfinite(depth) & (depth > 0)
        if hit.any():
            lo = min(lo, float(depth[hit].min()))
            hi = max(hi, float((depth[hit] * lengths[hit]).max()))
    if not math.isfinite(lo):
        raise DatasetError(f"{root}: no frame hits a surface; the dataset has no depth range")
    near, far = (1.0 - MARGIN) * lo, (1.0 + MARGIN) * hi
    rounded = round(math.floor(near / ROUND) * ROUND, 9)  # round(): 0.39, not 0.39000000000000001
    return (rounded if rounded > 0 else near), round(math.ceil(far / ROUND) * ROUND, 9)


def with_depth_range(root: str | Path, scene: Scene) -> Scene:
    """``scene`` with ``near`` / ``far`` of :func:`depth_range` (write it with ``write_scene``)."""
    near, far = depth_range(root, scene)
    return dataclasses.replace(scene, near=near, far=far)

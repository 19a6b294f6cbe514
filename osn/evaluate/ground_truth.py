"""The ground truth ``osn evaluate`` scores against: every configuration's test views and co-visibility masks."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenecore import dataset as D
from benchgen.score import metrics as M


@dataclass
class GroundTruth:
    """The evaluated test views of every configuration, with co-visibility masks."""

    scene: D.Scene
    frames: list[D.Frame]
    scales: np.ndarray  # (G, K_dataset) actual scales
    rgb: np.ndarray  # (G, V, H, W, 3) uint8
    depth: np.ndarray  # (G, V, H, W) float32
    ids: np.ndarray  # (G, V, H, W) uint8
    mask: np.ndarray  # (G, V, H, W) bool, co-visible pixels

    def first_views(self, v: int) -> "GroundTruth":
        """The same ground truths restricted to the first ``v`` evaluated views."""
        return GroundTruth(self.scene, self.frames[:v], self.scales, self.rgb[:, :v], self.depth[:, :v],
                           self.ids[:, :v], self.mask[:, :v])


def evaluated_views(scene: D.Scene, max_views: int = 0) -> list[D.Frame]:
    """The test views evaluated: all, or ``max_views`` of them evenly spread (time, then view order)."""
    test = sorted(scene.test_frames, key=lambda f: (f.time_index, f.view))
    if max_views and len(test) > max_views:
        test = [test[i] for i in np.linspace(0, len(test) - 1, max_views).round().astype(int)]
    return test


def load_ground_truth(root: str | Path, max_views: int = 0) -> GroundTruth:
    """Read the test views of every configuration and compute their co-visibility masks."""
    scene = D.load_scene(root)
    test = evaluated_views(scene, max_views)
    configs = D.load_configurations(root, scene)
    if not configs:
        raise ValueError(f"{root}: the dataset has no ground-truth configurations")
    _, t_depth, t_ids = D.read_training_video(root, scene)
    t_c2w = np.stack([f.camera_to_world for f in sorted(scene.train_frames, key=lambda f: f.time_index)])
    K = scene.intrinsics.matrix()
    G, V = len(configs), len(test)
    rgb = np.zeros((G, V, scene.height, scene.width, 3), np.uint8)
    depth = np.zeros((G, V, scene.height, scene.width), np.float32)
    ids = np.zeros((G, V, scene.height, scene.width), np.uint8)
    mask = np.zeros((G, V, scene.height, scene.width), bool)
    for g, cfg in enumerate(configs):
        t_depths = [M.configured_depth(d, i, cfg.scales) for d, i in zip(t_depth, t_ids)]
        for v, f in enumerate(test):
            rgb[g, v], depth[g, v], ids[g, v] = D.read_frame(root, f.name, g, scene=scene)
            mask[g, v] = M.covisibility_mask(
                depth[g, v], K, f.camera_to_world, t_depths, K, t_c2w,
                object_ids=np.where(ids[g, v] == D.NO_OBJECT, 0, ids[g, v]),
                object_transforms=M.covisibility_transforms(scene, cfg.scales, f.time_index),
            )
    return GroundTruth(scene, test, np.stack([c.scales for c in configs]), rgb, depth, ids, mask)

"""A small synthetic dataset built with numpy only (no rendering), for format tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenecore.cameras import intrinsics_from_fov, look_at
from scenecore.dataset import (
    NO_OBJECT,
    Configuration,
    Frame,
    Intrinsics,
    Scene,
    SceneObject,
    write_configuration,
    write_frame,
    write_scene,
    write_valid_region,
)
from scenecore.validity import ValidRegion


def make_scene(width: int = 24, height: int = 16, T: int = 3, V: int = 2, K: int = 3, G: int = 2) -> Scene:
    K_mat = intrinsics_from_fov(60.0, width, height)
    frames = []
    for t in range(T):
        for v in range(V):
            eye = np.array([4.0 * np.cos(0.3 * v + 0.1 * t), 4.0 * np.sin(0.3 * v + 0.1 * t), 1.5])
            split = "train" if v == t % V else "test"
            frames.append(Frame(f"v{v:02d}_t{t:02d}", v, t, split, look_at(eye, np.zeros(3))))
    objects = []
    for k in range(K):
        poses = np.tile(np.eye(4), (T, 1, 1))
        poses[:, 0, 3] = 0.1 * k * np.arange(T)
        objects.append(SceneObject(k, f"obj{k}", "anchor" if k == 0 else "object", poses))
    return Scene(width, height, Intrinsics.from_matrix(K_mat), np.linspace(0, 1, T), V, frames, objects, G)


def synthetic_images(scene: Scene, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    H, W = scene.height, scene.width
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    ids = rng.integers(0, scene.num_objects, (H, W)).astype(np.uint8)
    ids[0, 0] = NO_OBJECT
    depth = rng.uniform(0.5, 9.0, (H, W)).astype(np.float32)
    depth[ids == NO_OBJECT] = np.inf
    return rgb, depth, ids


def write_synthetic_dataset(root: Path, **kw) -> Scene:
    scene = make_scene(**kw)
    write_scene(root, scene)
    K = scene.num_objects
    B = np.full((K, K), 2.0)
    write_valid_region(root, ValidRegion.from_bounds(B, anchor=0))
    for i, f in enumerate(scene.train_frames):
        write_frame(root, f.name, *synthetic_images(scene, i))
    for g in range(scene.num_configurations):
        scales = np.ones(K)
        scales[1:] = 1.0 + 0.1 * (g + 1) * np.linspace(-1, 1, K - 1)
        write_configuration(root, Configuration(g, scales))
        for i, f in enumerate(scene.test_frames):
            write_frame(root, f.name, *synthetic_images(scene, 1000 * (g + 1) + i), config=g)
    return scene

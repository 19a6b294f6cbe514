"""The anchor's planes from its sparse depths (osn.train.planar): found in a box room's points,
nearest plane per ray, nothing outside the points' hull, none in a curved anchor, and depth targets
that match the real ``tiny`` dataset's depths."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import Delaunay

from osn.preprocess.oracle import oracle_inputs
from osn.train import Trainer
from osn.train.planar import (MAX_CONTRADICTED, anchor_points, contradicted_shares, fit_planes, kept_planes, plane_depths,
                              planar_depths)
from scenecore.dataset import load_scene, read_frame
from tests.osn.train.common import small_config


def _box_points(rng: np.random.Generator, n: int, noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the floor (z = 0) and the wall x = 2 of a room, seen from about (0, 0, 1) over 6
    frames: points, depth (distance to the camera), frame."""
    floor = np.c_[rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), np.zeros(n)]
    wall = np.c_[np.full(n, 2.0), rng.uniform(-2, 2, n), rng.uniform(0, 2, n)]
    pts = np.r_[floor, wall]
    depth = np.linalg.norm(pts - [0, 0, 1], axis=1)
    pts = pts + rng.normal(0, noise, pts.shape) * depth[:, None]
    return pts, depth, rng.integers(0, 6, len(pts))


def test_planes_of_a_box_room_are_found_and_the_nearest_is_seen() -> None:
    rng = np.random.default_rng(0)
    pts, depth, frames = _box_points(rng, 300, 0.005)
    planes = fit_planes(pts, depth, frames, seed=0)
    assert len(planes) == 2
    normals = np.abs(np.stack([p.normal for p in planes]))
    assert {int(np.argmax(n)) for n in normals} == {0, 2}  # the wall's x and the floor's z
    assert all(p.points >= 280 and p.frames == 6 for p in planes)
    # A camera at (0, 0, 1) looking along +x (OpenCV: x right, y down, z forward).
    cam_to_obj = np.eye(4)
    cam_to_obj[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    cam_to_obj[:3, 3] = [0, 0, 1]
    dirs = np.array([[0.0, 0.0, 1.0],    # straight ahead: the wall at x = 2
                     [0.0, 0.9, 1.0],    # down: the floor at x = 1/0.9, nearer than the wall
                     [0.0, -0.2, 1.0],   # a little up: the wall at z = 1.4
                     [0.0, -2.0, 1.0],   # steeply up: the wall at z = 5, outside its points (z <= 2)
                     [3.0, 0.0, 1.0]])   # far right: the wall at y = -6, outside its points
    d = plane_depths(planes, dirs, cam_to_obj)
    np.testing.assert_allclose(d[:3], [2.0, 1 / 0.9, 2.0], rtol=0.02)
    assert np.isnan(d[3]) and np.isnan(d[4])


def test_a_curved_anchor_and_too_few_points_give_no_plane() -> None:
    rng = np.random.default_rng(1)
    v = rng.normal(size=(600, 3))
    sphere = 3 * v / np.linalg.norm(v, axis=1, keepdims=True)
    depth = np.full(len(sphere), 3.0)
    assert fit_planes(sphere, depth, rng.integers(0, 6, 600), seed=0) == []
    pts, depth, frames = _box_points(rng, 300, 0.0)
    assert fit_planes(pts, depth, np.zeros(len(pts), dtype=int), seed=0) == []  # one frame only
    assert fit_planes(pts[:20], depth[:20], frames[:20], seed=0) == []


def test_planes_are_deterministic_per_seed() -> None:
    pts, depth, frames = _box_points(np.random.default_rng(2), 200, 0.01)
    a, b = fit_planes(pts, depth, frames, seed=3), fit_planes(pts, depth, frames, seed=3)
    assert [(p.points, p.offset) for p in a] == [(p.points, p.offset) for p in b]


def test_targets_on_the_tiny_room_match_its_depths(tiny_dataset: Path) -> None:
    """The oracle's inputs of the real tiny dataset: the room's planes give targets on most of its
    visible pixels, within 2% of the rendered depth, and behind the objects standing in it."""
    inputs = oracle_inputs(tiny_dataset)
    pd = planar_depths(inputs)
    assert len(pd.planes) >= 1 and len(anchor_points(inputs)[0]) > 0
    H, W = inputs.height, inputs.width
    scene = load_scene(tiny_dataset)
    frame_of = {f.time_index: f.name for f in scene.train_frames}
    anchor = inputs.objects[inputs.anchor_pos]
    frames, pixels = pd.flat // (H * W), pd.flat % (H * W)
    visible_err, hidden = [], 0
    for t in np.unique(frames):
        gt = read_frame(tiny_dataset, frame_of[int(t)])[1].reshape(-1)
        m = inputs.masks[t].reshape(-1)
        sel = frames == t
        vis = m[pixels[sel]] == inputs.anchor
        hidden += int((~vis).sum())
        visible_err.append(pd.depth[sel][vis] * anchor.unit_to_world / gt[pixels[sel][vis]] - 1)
    err = np.concatenate(visible_err)
    shown = sum(int((inputs.masks[t] == inputs.anchor).sum()) for t in anchor.frames)
    assert len(err) > 0.6 * shown and hidden > 0
    assert np.percentile(np.abs(err), 95) < 0.02


def test_training_holds_the_anchor_to_its_planar_targets(tiny_dataset: Path) -> None:
    """With ``w_planar`` the anchor's stage-1 objective has the planar term; at 0 the trainer
    builds no targets and has no such term."""
    inputs = oracle_inputs(tiny_dataset)
    on = Trainer(inputs, small_config(), torch.device("cpu"))  # on by default
    assert on.planar is not None and len(on.planar_depth) > 0
    losses = on.step_stage1()
    assert np.isfinite(losses["planar"]) and losses["planar"] > 0
    off = Trainer(inputs, small_config(w_planar=0.0), torch.device("cpu"))
    assert off.planar is None and "planar" not in off.step_stage1()


def test_a_plane_that_would_hide_what_the_video_shows_is_contradicted(tiny_dataset: Path) -> None:
    """The tiny room's own planes are contradicted by none of its depths; the same plane moved
    halfway to the cameras would hide the surfaces they show, and is dropped."""
    inputs = oracle_inputs(tiny_dataset)
    planes = fit_planes(*anchor_points(inputs))
    assert planes and all(contradicted_shares(planes, inputs) <= MAX_CONTRADICTED)
    anchor = inputs.objects[inputs.anchor_pos]
    centre = anchor.cam_to_obj[:, :3, 3].mean(axis=0)  # the cameras' centres, anchor coordinates
    p = planes[0]
    offset = 0.5 * (p.offset - float(p.normal @ centre))  # halfway between the cameras and the plane
    pts = anchor_points(inputs)[0]
    moved = dataclasses.replace(p, offset=offset, hull=Delaunay((pts - p.normal * (p.offset - offset)) @ p.basis.T))
    assert contradicted_shares([moved], inputs)[0] > 0.5
    assert kept_planes([moved, *planes], inputs) == planes  # in front of the true one: dropped
    assert len(planar_depths(inputs).planes) == len(planes)


def test_a_plane_behind_what_the_video_shows_is_contradicted_where_it_is_the_nearest(tiny_dataset: Path) -> None:
    """A plane behind the anchor's visible surface, alone, is not the nearest surface where the
    rays meet it (SfM's back wall met by the floor's rays when the floor is not found): the depths
    lie in front of it, and it is dropped. Behind a kept plane that is the nearest there, it sets
    no target and nothing contradicts it. A minority of depths off the true planes does not
    contradict them."""
    inputs = oracle_inputs(tiny_dataset)
    planes = fit_planes(*anchor_points(inputs))
    anchor = inputs.objects[inputs.anchor_pos]
    centre = anchor.cam_to_obj[:, :3, 3].mean(axis=0)
    p = planes[0]
    away = p.offset + 0.5 * (float(p.normal @ centre) + p.offset)  # half its distance from the cameras beyond it
    behind = dataclasses.replace(p, offset=away)
    assert contradicted_shares([behind], inputs)[0] > 0.5 and kept_planes([behind], inputs) == []
    both = contradicted_shares([behind, *planes], inputs)
    assert both[0] <= MAX_CONTRADICTED and all(both[1:] <= MAX_CONTRADICTED)
    # A fifth of the depths 5% nearer and a fifth 5% farther (beyond the 3% band), as SfM's
    # outliers about a floor: most depths still lie on the true planes.
    rng = np.random.default_rng(0)
    noisy = dataclasses.replace(anchor, sparse_depth=[d * rng.choice([0.95, 1.0, 1.05], len(d), p=[0.2, 0.6, 0.2])
                                                      for d in anchor.sparse_depth])
    inputs_noisy = dataclasses.replace(inputs, objects=[noisy if o is anchor else o for o in inputs.objects])
    assert kept_planes(planes, inputs_noisy) == planes

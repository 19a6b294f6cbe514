"""Bridging an object's unposed frames from its registered neighbours and the anchor's cameras:
the interpolation on exact motion, and on a real small reconstruction with frames taken away
(the bridged pose against the one SfM had found there), turned, or contradicted by the mask."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scenecore.cameras import invert_pose, rotation_angle_deg
from osn.evaluate.report import _consistency_lines
from osn.preprocess import video
from osn.preprocess.inputs import save_inputs
from osn.preprocess.bridge import bridged_pose
from tests.osn.preprocess.test_consistency import BALL, BLOCK, ROOM, _preprocess, _rotated, scene  # noqa: F401
from tests.osn.preprocess.test_sfm import sfm_scene  # noqa: F401  (the fixture: a render SfM registers)


def _similarity(s: float, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = s * R, p
    return out


def _orbit(t: float) -> np.ndarray:
    """Camera-to-anchor pose on a circle of radius 4 about the z axis, looking at its centre."""
    a = 0.6 * t
    c = np.array([4 * np.cos(a), 4 * np.sin(a), 1.0])
    z = -c / np.linalg.norm(c)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    M[:3, 3] = c
    return M


def _object_pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The object's orientation and position in the anchor's frame: a constant turn rate and a
    constant velocity, what the bridge interpolates exactly."""
    return Rotation.from_rotvec([0.1 * t, 0.3 * t, -0.2 * t]).as_matrix(), np.array([0.3, -0.2, 0.1]) + t * np.array([0.2, 0.1, -0.05])


@pytest.mark.parametrize("s", [0.05, 1.0, 20.0])
def test_bridged_pose_is_exact_for_a_steady_motion_at_the_true_scale(s):
    def cam_to_obj(t: float) -> np.ndarray:
        W, p = _object_pose(t)
        # Camera-to-object = inverse(object-to-anchor similarity) after camera-to-anchor, in object units.
        M = invert_pose(_similarity(s, W, p)) @ _orbit(t)
        M[:3, :3] *= s  # a rigid pose: the similarity's scale moves into the unit
        return M

    t0, t1 = 0.0, 3.0
    for t in (1.0, 2.5, 4.0):  # between the frames, and past the last one
        alpha = (t - t0) / (t1 - t0)
        got = bridged_pose(alpha, cam_to_obj(t0), cam_to_obj(t1), _orbit(t0), _orbit(t1), _orbit(t), s)
        want = cam_to_obj(t)
        assert rotation_angle_deg(got[:3, :3], want[:3, :3]) < 1e-6
        assert np.linalg.norm(got[:3, 3] - want[:3, 3]) < 1e-9 * max(1.0, np.linalg.norm(want[:3, 3]))
        # Straight-path bridging ignores the camera's turn: right orientation, centre off by the arc's sagitta / s.
        flat = bridged_pose(alpha, cam_to_obj(t0), cam_to_obj(t1), _orbit(t0), _orbit(t1), _orbit(t), np.inf)
        assert rotation_angle_deg(flat[:3, :3], want[:3, :3]) < 1e-6
        assert np.linalg.norm(flat[:3, 3] - want[:3, 3]) > 1e-3 / s


def _without(results: dict, oid: int, frames: list[int]) -> dict:
    out = copy.deepcopy(results)
    out[oid] = video.without_frames(out[oid], frames)
    return out


def _errors(inputs, oid: int, reference: dict, frames: list[int]) -> list[tuple[float, float]]:
    """Rotation (degrees) and camera-centre error (share of the object's median sparse depth)
    of the inputs' poses at ``frames`` against SfM's own poses there. Both are compared relative to
    a registered frame ``b`` (``M_b^-1 M_t``): normalisation changes them only by the unit, which a
    second registered frame measures."""
    o, ref = inputs.object(oid), reference[oid]
    got = {int(t): M for t, M in zip(o.frames, o.cam_to_obj)}
    want = {int(t): M for t, M in zip(ref.frames, ref.cam_to_obj)}
    b, c = [t for t in got if t in want and t not in frames][:2]
    rel = lambda poses, t: invert_pose(poses[b]) @ poses[t]  # noqa: E731
    unit = np.linalg.norm(rel(want, c)[:3, 3]) / np.linalg.norm(rel(got, c)[:3, 3])
    depth = float(np.median(np.concatenate(ref.sparse_depth)))
    out = []
    for t in frames:
        g, w = rel(got, t), rel(want, t)
        rot = rotation_angle_deg(g[:3, :3], w[:3, :3])
        out.append((rot, float(np.linalg.norm(g[:3, 3] * unit - w[:3, 3]) / depth)))
    return out


@pytest.mark.slow
def test_frames_sfm_did_not_register_are_bridged_close_to_the_poses_sfm_had(scene, monkeypatch, tmp_path):
    taken = [2, 5]
    results = _without(scene["results"], BALL, taken)
    inputs, report = _preprocess(scene, results, monkeypatch)
    ball = inputs.object(BALL)
    assert set(taken) <= set(map(int, ball.frames)), ball.frames
    assert inputs.meta["bridged_frames"][str(BALL)] == taken
    for rot, centre in _errors(inputs, BALL, scene["results"], taken):
        assert rot < 2.0 and centre < 0.05, (rot, centre)
    # No sparse depth in a bridged frame; the registered frames keep theirs.
    for t, d in zip(ball.frames, ball.sparse_depth):
        assert (len(d) == 0) == (int(t) in taken)
    entry = next(r for r in report.objects if r["id"] == BALL)
    assert entry["registered_frames"] == len(results[BALL].frames) and entry["bridged_frames"] == taken
    assert all(entry["bridge"]["frames"][str(t)]["kept"] for t in taken)
    assert any(line.strip().startswith("bridged 2 of 2 unposed frames") for line in video.report_lines(report.objects))
    # The run's report names them, from the inputs the run trained on.
    save_inputs(tmp_path / "run" / "inputs", inputs)
    assert "- object 1 (ball): frames 2, 5" in _consistency_lines(tmp_path / "run")
    # Without bridging the frames stay unposed and the rest is the same.
    monkeypatch.setattr(scene["cfg"], "bridge_unposed", False)
    plain, _ = _preprocess(scene, results, monkeypatch)
    assert list(plain.object(BALL).frames) == list(results[BALL].frames)
    keep = [n for n, t in enumerate(ball.frames) if int(t) not in taken]
    np.testing.assert_allclose(ball.cam_to_obj[keep], plain.object(BALL).cam_to_obj, atol=1e-12)
    np.testing.assert_allclose(ball.bbox, plain.object(BALL).bbox)


@pytest.mark.slow
def test_frames_dropped_as_turned_are_bridged_back_to_the_right_pose(scene, monkeypatch):
    broken = _rotated(scene["results"], BALL, [1, 3], 18.0)
    inputs, report = _preprocess(scene, broken, monkeypatch)
    entry = next(r for r in report.objects if r["id"] == BALL)
    assert entry["consistency"]["bad_frames"] == [1, 3] and entry["bridged_frames"] == [1, 3]
    for rot, centre in _errors(inputs, BALL, scene["results"], [1, 3]):
        assert rot < 2.0 and centre < 0.05, (rot, centre)  # the turned poses were 18 degrees off


@pytest.mark.slow
def test_a_bridge_the_mask_contradicts_is_refused(scene, monkeypatch):
    """The ball's mask in a frame it lost reshaped into a bar three times as wide (the same pixel
    count): no shift of the ball fits it as well as the registered poses fit theirs, so the frame
    stays unposed."""
    results = _without(scene["results"], BALL, [4])
    moved = scene["masks"].copy()
    ball = moved[4] == BALL
    v, u = np.nonzero(ball)
    moved[4][ball] = ROOM
    width = 3 * (u.max() - u.min() + 1)
    rows = -(-len(u) // width)
    top, left = int(v.mean()) - rows // 2, max(0, int(u.mean()) - width // 2)
    bar = np.zeros_like(ball)
    bar[top:top + rows, left:left + width] = True
    moved[4][bar & (moved[4] == ROOM)] = BALL
    inputs, report = _preprocess({**scene, "masks": moved}, results, monkeypatch)
    assert 4 not in set(map(int, inputs.object(BALL).frames))
    entry = next(r for r in report.objects if r["id"] == BALL)
    rec = entry["bridge"]["frames"]["4"]
    assert rec["kept"] is False and rec["refined"] is True
    assert rec["miss"] > entry["bridge"]["max_miss"] or rec["cover"] < entry["bridge"]["min_cover"]
    assert str(BALL) not in inputs.meta["bridged_frames"]

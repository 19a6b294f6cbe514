import dataclasses

import numpy as np
import pytest

from scenecore import dataset as D
from scenecore.cameras import invert_pose, pixel_rays
from osn.preprocess import inputs as I
from osn.preprocess.oracle import OracleConfig, oracle_inputs
from tests.synthetic import write_synthetic_dataset
from osn.evaluate.units import actual_scales, true_scales


@pytest.fixture()
def oracle(tmp_path):
    root = tmp_path / "ds"
    write_synthetic_dataset(root, T=4, V=2, K=3)
    return root, D.load_scene(root), oracle_inputs(root, OracleConfig(points_per_frame=40, min_pixels=1))


def test_oracle_poses_are_consistent_with_world_motion(oracle):
    root, scene, inp = oracle
    K = inp.K
    for o in inp.objects:
        obj = scene.objects[o.id]
        unit = o.unit_to_world
        # A sparse point seen in frame a, moved with the object to frame b, must land where the
        # object-space inverse pose of frame b puts it (rigid object, shared object coordinates).
        a, b = 0, len(o.frames) - 1
        ta, tb = o.frames[a], o.frames[b]
        pix, dep = o.sparse_pix[a][:5], o.sparse_depth[a][:5]
        orig, dirs = pixel_rays(K, np.eye(4), inp.width, inp.height, pixels=pix)
        p_cam_a = orig + dep[:, None] * dirs  # object units
        p_obj = p_cam_a @ o.cam_to_obj[a][:3, :3].T + o.cam_to_obj[a][:3, 3]
        b_from_obj = invert_pose(o.cam_to_obj[b])
        p_cam_b = p_obj @ b_from_obj[:3, :3].T + b_from_obj[:3, 3]
        # Ground truth in metres through the world.
        c2w = {f.time_index: f.camera_to_world for f in scene.train_frames}
        pw_a = (p_cam_a * unit) @ c2w[ta][:3, :3].T + c2w[ta][:3, 3]
        pw_b = pw_a @ (obj.poses[tb] @ invert_pose(obj.poses[ta]))[:3, :3].T + (obj.poses[tb] @ invert_pose(obj.poses[ta]))[:3, 3]
        w2c_b = invert_pose(c2w[tb])
        expected = (pw_b @ w2c_b[:3, :3].T + w2c_b[:3, 3]) / unit
        assert np.allclose(p_cam_b, expected, atol=1e-9)
        if o.id == inp.anchor:  # the static anchor's frame is reachable from the world
            W = inp.world_to_anchor
            assert np.allclose(pw_a @ W[:3, :3].T + W[:3, 3], p_obj, atol=1e-9)
        # Rigid poses, median sparse depth 1 in object units.
        R = o.cam_to_obj[:, :3, :3]
        assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
        assert np.median(np.concatenate(o.sparse_depth)) == pytest.approx(1.0)


def test_scale_conversions_and_ranges(oracle):
    root, scene, inp = oracle
    ranges = inp.scale_ranges()
    assert np.all(ranges[:, 0] < ranges[:, 1])
    s = np.array([0.0, 0.5, 0.999])
    sbar = I.denormalise_scales(np.tile(s, (3, 1)).T[:, :3], ranges)
    assert np.allclose(I.normalise_scales(sbar, ranges), np.tile(s, (3, 1)).T)
    actual = np.array([1.0, 0.7, 1.3])
    assert np.allclose(actual_scales(inp, true_scales(inp, actual)), actual)
    # Not just round trips: Eq. 1 is linear between the range ends, and sbar_k = s_k u_k / u_anchor.
    assert np.allclose(I.denormalise_scales(np.full(3, 0.5), ranges), ranges.mean(axis=1))
    assert np.allclose(I.denormalise_scales(np.full(3, 0.25), ranges), 0.75 * ranges[:, 0] + 0.25 * ranges[:, 1])
    u = np.array([o.unit_to_world for o in inp.objects])
    assert np.allclose(true_scales(inp, actual), actual * u / u[inp.anchor_pos])
    assert true_scales(inp, np.ones(3))[inp.anchor_pos] == 1.0


def test_anchor_is_found_by_id_not_by_position(oracle):
    """With the anchor's object dropped from position 0 (SfM skipped an object) or listed last,
    scales are still relative to the anchor's unit, and an unknown anchor is a clear error."""
    import dataclasses

    _, _, inp = oracle
    units = np.array([o.unit_to_world for o in inp.objects])
    assert len(set(units.round(9))) == 3  # distinct units, or the test could not tell positions apart
    reordered = dataclasses.replace(inp, objects=inp.objects[::-1])
    sbar = true_scales(reordered, np.ones(3))
    assert reordered.anchor_pos == 2 and sbar[2] == 1.0
    assert np.allclose(sbar, units[::-1] / units[0])
    dropped = dataclasses.replace(inp, objects=inp.objects[1:], anchor=inp.objects[1].id)
    assert np.allclose(true_scales(dropped, np.ones(2)), units[1:] / units[1])
    with pytest.raises(I.InputsError, match=r"the anchor \(object 7\) is not among the objects"):
        I.check_inputs(dataclasses.replace(inp, anchor=7), "x")


def test_malformed_object_inputs_are_named(oracle):
    import dataclasses

    _, _, inp = oracle
    o = inp.objects[1]
    bad_frames = dataclasses.replace(o, frames=o.frames + 100)
    # each axis on its own, so a check of only one of them fails
    bad_u = dataclasses.replace(o, sparse_pix=[p + [inp.width, 0] for p in o.sparse_pix])
    bad_v = dataclasses.replace(o, sparse_pix=[p + [0, inp.height] for p in o.sparse_pix])
    bad_box = dataclasses.replace(o, bbox=o.bbox[::-1])
    for obj, msg in ((bad_frames, "frames outside"), (bad_u, "sparse pixels outside"), (bad_v, "sparse pixels outside"),
                     (bad_box, "empty or malformed box")):
        objects = list(inp.objects)
        objects[1] = obj
        with pytest.raises(I.InputsError, match=f"x: object {o.id} .*{msg}"):
            I.check_inputs(dataclasses.replace(inp, objects=objects), "x")


@pytest.mark.parametrize("field, value, phrase", [
    ("points_per_frame", -1, "points_per_frame must be an integer >= 0, got -1"),
    ("min_pixels", 2.5, "min_pixels must be an integer >= 1"),
    ("scene_near_factor", 1.0, r"scene_near_factor must be a number in \(0, 1\)"),
    ("scene_far_factor", 0.9, "scene_far_factor must be a number >= 1"),
    ("box_padding", -0.1, "box_padding must be a number >= 0"),
    ("seed", -1, "seed must be an integer >= 0"),
])
def test_oracle_config_rejects_bad_values(field, value, phrase):
    """Each bad option is one error naming the section, the key and the rule (the scene volume's
    factors as :func:`osn.preprocess.inputs.scene_volume` requires: 0 < near < 1 <= far)."""
    with pytest.raises(ValueError, match=f"oracle config: {phrase}"):
        OracleConfig(**{field: value})


def test_inverted_range_is_an_error():
    with pytest.raises(I.InputsError, match="empty scale range"):
        I.scale_range(1.0, 2.0, 0.5, 3.0)
    with pytest.raises(I.InputsError, match="finite and positive"):
        I.scale_range(0.0, 2.0, 0.5, 3.0)


def test_save_load_round_trip(oracle, tmp_path):
    root, scene, inp = oracle
    I.save_inputs(tmp_path / "in", inp)
    back = I.load_inputs(tmp_path / "in")
    assert back.source == "oracle" and back.num_objects == inp.num_objects
    assert np.array_equal(back.images, inp.images) and np.array_equal(back.masks, inp.masks)
    assert np.array_equal(back.world_to_anchor, inp.world_to_anchor)
    assert np.array_equal(back.K, inp.K) and np.array_equal(back.timestamps, inp.timestamps)
    assert (back.width, back.height, back.anchor) == (inp.width, inp.height, inp.anchor)
    assert (back.scene_near, back.scene_far) == (inp.scene_near, inp.scene_far)
    for a, b in zip(back.objects, inp.objects):
        assert (a.id, a.name, a.near, a.far, a.unit_to_world) == (b.id, b.name, b.near, b.far, b.unit_to_world)
        assert np.array_equal(a.frames, b.frames) and np.array_equal(a.bbox, b.bbox)
        assert np.array_equal(a.cam_to_obj, b.cam_to_obj)
        for field in ("sparse_depth", "sparse_pix", "sparse_weight"):
            assert all(np.array_equal(x, y) for x, y in zip(getattr(a, field), getattr(b, field)))


def test_ignored_pixels_are_never_drawn_for_training(oracle):
    import torch

    from osn.train.tensors import SceneTensors

    root, scene, inp = oracle
    inp.masks[inp.masks == 2] = I.IGNORE_ID  # as preprocessing does for a dropped object
    st = SceneTensors(inp, torch.device("cpu"))
    flat_masks = torch.from_numpy(inp.masks.reshape(-1))
    assert st.usable is not None and not torch.any(flat_masks[st.usable] == I.IGNORE_ID)
    assert len(st.usable) == int((flat_masks != I.IGNORE_ID).sum())
    assert len(st.obj_pixels[2]) == 0  # and no object claims them
    # Nor are they scored: training PSNR is measured on trainable pixels only.
    from osn.train import TrainConfig, Trainer, TrainingMonitor
    from osn.train.monitor import MONITOR_PIXELS

    ev = TrainingMonitor(Trainer(inp, TrainConfig(), torch.device("cpu")), None)
    assert len(ev.flat) == min(MONITOR_PIXELS, len(st.usable)) and not torch.any(flat_masks[ev.flat] == I.IGNORE_ID)


def test_oracle_density_grows_with_the_frame(tmp_path):
    """``points_per_frame: 0``: a sixteenth of the frame's pixels, at least 256 (the demo's 64 px
    keeps 256, gnome-house's 128 px gets 1024); an object smaller than that gives every pixel."""
    from osn.preprocess.inputs import auto_points_per_frame

    assert [auto_points_per_frame(w, w) for w in (32, 64, 128, 512)] == [256, 256, 1024, 16384]
    root = tmp_path / "ds"
    write_synthetic_dataset(root)
    scene = D.load_scene(root)
    auto, fixed = oracle_inputs(root), oracle_inputs(root, OracleConfig(points_per_frame=auto_points_per_frame(scene.width, scene.height)))
    for a, f in zip(auto.objects, fixed.objects):
        assert [len(d) for d in a.sparse_depth] == [len(d) for d in f.sparse_depth]
        for t, d in zip(a.frames, a.sparse_depth):
            covered = int((auto.masks[t] == a.id).sum())
            assert len(d) == min(covered, auto_points_per_frame(scene.width, scene.height))


def test_subsampling_caps_each_frame_with_a_subset_and_keeps_the_geometry(oracle):
    """At most ``per_frame`` depths per object and frame, each one of the originals (pixel,
    depth and weight together), the same for the same seed; poses, ranges and boxes untouched."""
    _, _, inp = oracle  # 40 depths per frame
    o0 = inp.objects[0]  # a frame below the cap keeps its depths (SfM's counts vary by frame)
    for field in (o0.sparse_pix, o0.sparse_depth, o0.sparse_weight):
        field[0] = field[0][:10]
    counts = [[len(d) for d in o.sparse_depth] for o in inp.objects]
    assert max(max(c) for c in counts) == 40 and min(min(c) for c in counts) == 10
    out = I.subsample_sparse_depths(inp, 25, seed=3)
    assert out.meta["sparse_depths_per_frame"] == 25
    for o, c in zip(out.objects, counts):
        src = inp.object(o.id)
        assert [len(d) for d in o.sparse_depth] == [min(n, 25) for n in c]
        for p, d, w, sp, sd, sw in zip(o.sparse_pix, o.sparse_depth, o.sparse_weight,
                                       src.sparse_pix, src.sparse_depth, src.sparse_weight):
            rows = {(int(u), int(v), float(z), float(x)) for (u, v), z, x in zip(sp, sd, sw)}
            assert {(int(u), int(v), float(z), float(x)) for (u, v), z, x in zip(p, d, w)} <= rows
        np.testing.assert_array_equal(o.cam_to_obj, src.cam_to_obj)
        np.testing.assert_array_equal(o.bbox, src.bbox)
        assert (o.near, o.far) == (src.near, src.far)
    again, other = I.subsample_sparse_depths(inp, 25, seed=3), I.subsample_sparse_depths(inp, 25, seed=4)
    assert all(np.array_equal(a, b) for o, g in zip(out.objects, again.objects) for a, b in zip(o.sparse_depth, g.sparse_depth))
    assert not all(np.array_equal(a, b) for o, g in zip(out.objects, other.objects) for a, b in zip(o.sparse_depth, g.sparse_depth))
    # 0: the oracle's automatic count (256 here, above every frame's 40): nothing is dropped.
    auto = I.subsample_sparse_depths(inp)
    assert auto.meta["sparse_depths_per_frame"] == 256 and [[len(d) for d in o.sparse_depth] for o in auto.objects] == counts
    with pytest.raises(I.InputsError, match="must be >= 0"):
        I.subsample_sparse_depths(inp, -1)


def test_a_frame_left_without_sparse_depths_is_carried_through(oracle, tmp_path):
    """SfM's phantom drop can take every depth of a frame: the object still normalises from its
    other frames, and the empty frame survives checking, saving, downscaling and the cap."""
    _, _, inp = oracle
    o = inp.objects[1]
    pix, dep, wt = ([x.copy() for x in xs] for xs in (o.sparse_pix, o.sparse_depth, o.sparse_weight))
    pix[1], dep[1], wt[1] = np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros(0)
    obj = I.object_inputs_from_observations(o.id, o.name, o.frames, o.cam_to_obj, pix, dep, wt, inp.K, inp.width,
                                            inp.height, I.BOX_PADDING, None)
    kept = np.concatenate(dep)
    assert obj.sparse_depth[1].shape == (0,) and obj.sparse_pix[1].shape == (0, 2)
    # The unit is the median of the depths left: every other frame's depths scale by it alone.
    np.testing.assert_allclose(obj.sparse_depth[0], dep[0] / np.median(kept))
    assert np.isfinite([obj.near, obj.far]).all() and np.isfinite(obj.bbox).all()
    objects = [obj if x.id == o.id else x for x in inp.objects]
    near, far = I.scene_volume(objects, I.SCENE_NEAR_FACTOR, I.SCENE_FAR_FACTOR)
    out = dataclasses.replace(inp, objects=objects, scene_near=near, scene_far=far)
    I.check_inputs(out)
    I.save_inputs(tmp_path / "in", out)
    back = I.load_inputs(tmp_path / "in")
    assert [len(d) for d in back.object(o.id).sparse_depth] == [len(d) for d in obj.sparse_depth]
    for x in (I.downscale_inputs(back, 2), I.subsample_sparse_depths(back, 5)):
        assert len(x.object(o.id).sparse_depth[1]) == 0 and x.object(o.id).sparse_pix[1].shape == (0, 2)


def test_with_video_swaps_the_frames_and_keeps_dropped_objects_ignored(oracle):
    _, _, inp = oracle
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, inp.images.shape, dtype=np.uint8)
    dropped = int(inp.objects[-1].id)
    # Inputs that dropped an object (as preprocessing records it) keep its pixels ignored.
    inp = dataclasses.replace(inp, meta={**inp.meta, "dropped_objects": [dropped]},
                              objects=[o for o in inp.objects if o.id != dropped])
    out = I.with_video(inp, images, inp.masks, "video")
    np.testing.assert_array_equal(out.images, images)
    assert not np.any(out.masks == dropped) and np.any(out.masks == I.IGNORE_ID)
    assert out.objects == inp.objects and out.meta["video"] == "video"
    with pytest.raises(I.InputsError, match="^frames/: a video of .* cannot replace"):
        I.with_video(inp, images[:, :-1], inp.masks[:, :-1], "frames/")

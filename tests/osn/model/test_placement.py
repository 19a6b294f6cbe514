import numpy as np

from scenecore import dataset as D
from scenecore.cameras import invert_pose
from osn.preprocess.oracle import OracleConfig, oracle_inputs
from osn.model.placement import novel_to_training_camera, object_transforms
from tests.synthetic import write_synthetic_dataset
from osn.evaluate.units import true_scales


def test_test_camera_points_land_in_the_right_object_coordinates(tmp_path):
    root = tmp_path / "ds"
    write_synthetic_dataset(root, T=3, V=3, K=3)
    scene = D.load_scene(root)
    inp = oracle_inputs(root, OracleConfig(points_per_frame=30, min_pixels=1))
    rng = np.random.default_rng(0)
    train_c2w = {f.time_index: f.camera_to_world for f in scene.train_frames}
    mu = np.array([o.unit_to_world for o in inp.objects])
    for f in scene.test_frames:
        t = f.time_index
        for actual in (np.ones(3), np.array([1.0, 0.6, 1.7])):
            sbar = true_scales(inp, actual)
            M = novel_to_training_camera(inp, f.camera_to_world, t)
            T = object_transforms(inp, M, t, sbar)
            for k, obj in enumerate(scene.objects):
                # A point on object k (body frame), placed in the world of configuration `actual`.
                p_body = rng.normal(size=3)
                pose = scene.configured_pose(k, t, actual[k])
                p_world = pose[:3, :3] @ p_body + pose[:3, 3]
                w2c = invert_pose(f.camera_to_world)
                x_cam = (w2c[:3, :3] @ p_world + w2c[:3, 3]) / mu[inp.anchor]  # scene units
                got = T[k][:3, :3] @ x_cam + T[k][:3, 3]
                # Ground truth: the same body point seen from the training camera in the base scene.
                base = obj.poses[t]
                w2t = invert_pose(train_c2w[t])
                x_train = (w2t[:3, :3] @ (base[:3, :3] @ p_body + base[:3, 3]) + w2t[:3, 3]) / mu[k]
                slot = inp.objects[k].frame_slot(t)
                expected = inp.objects[k].cam_to_obj[slot][:3, :3] @ x_train + inp.objects[k].cam_to_obj[slot][:3, 3]
                assert np.allclose(got, expected, atol=1e-9), (f.name, k, actual)

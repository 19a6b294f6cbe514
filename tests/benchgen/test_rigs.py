"""Camera rig protocols: orbit (the paper's 15 x 15), stereo (Oxford Multimotion) and
multi-camera (NVIDIA Dynamic Scenes). Geometry checks are pure numpy; one tiny render per new
protocol checks that generation and verification run on it."""

from __future__ import annotations

import numpy as np
import pytest

from benchgen.render.generate import generate
from benchgen.scene.geometry import build_scene, rig_cameras
from benchgen.scene.spec import SpecError, load_preset, spec_from_dict


def _tiny_with_rig(**rig) -> dict:
    d = load_preset("tiny").to_dict()
    if "protocol" in rig:
        del d["rig"]["views"]  # the protocol implies it
    d["rig"].update(rig)
    return d


def test_orbit_is_the_default_and_every_other_pair_is_a_test_view():
    scene = build_scene(load_preset("gnome-house")).scene
    train = [f for f in scene.frames if f.split == "train"]
    assert [f.view for f in train] == list(range(15))
    assert len(scene.frames) == 225 and len(scene.test_frames) == 210


def test_stereo_pair_is_parallel_and_baseline_apart_and_tests_on_the_right_camera():
    spec = spec_from_dict(_tiny_with_rig(protocol="stereo", baseline=0.3, times=5, arc=[-10, 10]), "s")
    scene = build_scene(spec).scene
    assert spec.rig.views == 2
    train = sorted((f for f in scene.frames if f.split == "train"), key=lambda f: f.time_index)
    test = sorted(scene.test_frames, key=lambda f: f.time_index)
    assert [f.view for f in train] == [0] * 5 and [f.view for f in test] == [1] * 5
    for left, right in zip(train, test):
        rel = np.linalg.inv(left.camera_to_world) @ right.camera_to_world
        np.testing.assert_allclose(rel[:3, :3], np.eye(3), atol=1e-12)  # parallel
        np.testing.assert_allclose(rel[:3, 3], [0.3, 0, 0], atol=1e-12)  # along the image x axis (right)
    # The pair moves along the arc over the video; equal arc ends give a static camera.
    assert np.linalg.norm(train[0].camera_to_world[:3, 3] - train[-1].camera_to_world[:3, 3]) > 0.1
    static = rig_cameras(spec_from_dict(_tiny_with_rig(protocol="stereo", arc=[5, 5]), "s").rig, 0)
    np.testing.assert_allclose(static, rig_cameras(spec_from_dict(_tiny_with_rig(protocol="stereo", arc=[5, 5]), "s").rig, 2))


def test_multi_camera_grid_trains_on_cameras_1_to_n_and_tests_on_camera_0_at_every_time():
    spec = spec_from_dict(_tiny_with_rig(protocol="multi-camera", grid=[2, 3], spacing=0.2, times=8), "m")
    scene = build_scene(spec).scene
    assert spec.rig.views == 6
    train = sorted((f for f in scene.frames if f.split == "train"), key=lambda f: f.time_index)
    assert [f.view for f in train] == [1, 2, 3, 4, 5, 1, 2, 3]
    assert sorted((f.view, f.time_index) for f in scene.test_frames) == [(0, t) for t in range(8)]
    cams = rig_cameras(spec.rig, 0)
    np.testing.assert_allclose(cams, rig_cameras(spec.rig, 7))  # fixed cameras
    centres = cams[:, :3, 3]
    assert np.isclose(np.linalg.norm(centres[1] - centres[0]), 0.2) and np.isclose(np.linalg.norm(centres[3] - centres[0]), 0.2)
    # Every camera looks at the target.
    for c in cams:
        to_target = np.asarray(spec.rig.target) - c[:3, 3]
        np.testing.assert_allclose(c[:3, 2], to_target / np.linalg.norm(to_target), atol=1e-12)


@pytest.mark.parametrize(
    "rig, message",
    [
        ({"protocol": "trinocular"}, "unknown protocol 'trinocular'"),
        ({"protocol": "stereo", "views": 3}, "the stereo protocol has 2 cameras"),
        ({"protocol": "multi-camera", "grid": [2, 2], "views": 5}, "the multi-camera protocol has 4 cameras"),
        ({"protocol": "multi-camera", "grid": [2]}, "rig.grid: expected \\[rows, cols\\]"),
        ({"protocol": "stereo", "baseline": 0}, "rig.baseline: must be > 0.0"),
    ],
)
def test_bad_rig_fields_are_one_line_errors_naming_the_field(rig, message):
    with pytest.raises(SpecError, match=message) as e:
        spec_from_dict(_tiny_with_rig(**rig), "scene.yaml")
    assert str(e.value).startswith("scene.yaml: ") and "\n" not in str(e.value)


@pytest.mark.slow
@pytest.mark.parametrize("rig", [{"protocol": "stereo", "times": 4}, {"protocol": "multi-camera", "grid": [1, 3], "times": 4}])
def test_new_protocols_generate_and_verify(tmp_path, rig):
    spec = spec_from_dict(_tiny_with_rig(**rig), "rig.yaml").with_overrides(configs=2)
    summary = generate(spec, tmp_path / "d", progress=False)
    assert summary.passed, summary.lines()
    assert (tmp_path / "d" / "transforms_test.json").is_file()  # every split starts at t = 0

import json
import sys
import subprocess
from pathlib import Path

import numpy as np
import pytest

from scenecore import atomic
from scenecore import dataset as D
from tests.synthetic import synthetic_images, write_synthetic_dataset


@pytest.fixture()
def ds(tmp_path):
    root = tmp_path / "ds"
    scene = write_synthetic_dataset(root)
    return root, scene


def test_round_trip_bit_exact(ds):
    root, scene = ds
    loaded = D.load_scene(root)
    assert loaded.num_objects == scene.num_objects and loaded.anchor_id == 0
    for a, b in zip(loaded.frames, scene.frames):
        assert (a.name, a.view, a.time_index, a.split) == (b.name, b.view, b.time_index, b.split)
        assert np.array_equal(a.camera_to_world, b.camera_to_world)
    for a, b in zip(loaded.objects, scene.objects):
        assert np.array_equal(a.poses, b.poses) and a.role == b.role
    assert np.array_equal(loaded.timestamps, scene.timestamps)
    for i, f in enumerate(scene.train_frames):
        rgb, depth, ids = D.read_frame(root, f.name)
        e_rgb, e_depth, e_ids = synthetic_images(scene, i)
        assert np.array_equal(rgb, e_rgb) and np.array_equal(ids, e_ids)
        assert depth.dtype == np.float32 and np.array_equal(depth, e_depth)
    configs = D.load_configurations(root)
    assert len(configs) == 2 and configs[1].scales[0] == 1.0
    region = D.load_valid_region(root)
    assert np.isinf(region.ratio_bounds[0, 0]) and region.ratio_bounds[0, 1] == 2.0
    assert D.validate(root) == []


def test_transforms_json_interop(ds):
    root, scene = ds
    D.write_transforms_json(root, scene)
    tr = json.loads((root / "transforms_train.json").read_text())
    assert len(tr["frames"]) == len(scene.train_frames)
    f0 = tr["frames"][0]
    assert (root / (f0["file_path"] + ".png")).exists()
    # OpenGL camera-to-world: the camera looks down its -z axis.
    assert np.allclose(-np.array(f0["transform_matrix"])[:3, 2], scene.train_frames[0].camera_to_world[:3, 2])
    te = json.loads((root / "transforms_test.json").read_text())
    assert all((root / (f["file_path"] + ".png")).exists() for f in te["frames"])


@pytest.mark.parametrize("make_view", [lambda a: a.T, lambda a: a[::2, ::2], lambda a: np.asfortranarray(a)])
def test_exr_non_contiguous_written_correctly(tmp_path, make_view):
    base = np.arange(48 * 64, dtype=np.float32).reshape(48, 64) * 0.5
    view = make_view(base)
    D.write_depth(tmp_path / "d.exr", view)
    assert np.array_equal(D.read_depth(tmp_path / "d.exr"), np.asarray(view))


def test_float64_depth_is_stored_as_float32(tmp_path):
    d = np.linspace(1e-3, 1e4, 20).reshape(4, 5)
    D.write_depth(tmp_path / "d.exr", d)
    assert np.array_equal(D.read_depth(tmp_path / "d.exr"), d.astype(np.float32))


def test_atomic_write_leaves_no_partial_file(tmp_path, monkeypatch):
    target = tmp_path / "x.json"
    D.atomic_write_json(target, {"a": 1})

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(OSError):
        D.atomic_write_json(target, {"a": 2})
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]


def _edit_manifest(root: Path, fn) -> None:
    d = json.loads((root / "scene.json").read_text())
    fn(d)
    (root / "scene.json").write_text(json.dumps(d))


def _one(problems, *needles):
    assert problems, "validator found nothing"
    hits = [p for p in problems if all(n in p for n in needles)]
    assert hits, f"no problem mentions {needles}: {problems}"
    return hits[0]


def test_validator_unknown_version(ds):
    root, _ = ds
    _edit_manifest(root, lambda d: d.update(version=7))
    _one(D.validate(root), "scene.json", "unknown format version 7")


def test_validator_non_finite_pose(ds):
    root, _ = ds

    def f(d):
        d["objects"][1]["poses"][0][0][3] = float("nan")

    _edit_manifest(root, f)
    _one(D.validate(root), "scene.json", "object 1 poses", "non-finite")


def test_validator_missing_file(ds):
    root, scene = ds
    p = D.frame_paths(root, scene.train_frames[1].name).depth
    p.unlink()
    _one(D.validate(root), str(p), "missing file")


def test_validator_wrong_shape_and_dtype(ds):
    root, scene = ds
    paths = D.frame_paths(root, scene.test_frames[0].name, config=1)
    D.write_rgb(paths.rgb, np.zeros((5, 7, 3), np.uint8))
    import imageio.v3 as iio

    iio.imwrite(paths.ids, np.zeros((scene.height, scene.width), np.uint16))
    problems = D.validate(root)
    _one(problems, str(paths.rgb), "size 7x5")
    _one(problems, str(paths.ids), "uint16")


def test_rgb_is_stored_as_opaque_rgba_and_read_back_as_rgb(tmp_path):
    import imageio.v3 as iio

    rgb = np.random.default_rng(0).integers(0, 256, (6, 9, 3), dtype=np.uint8)
    D.write_rgb(tmp_path / "f.png", rgb)
    stored = iio.imread(tmp_path / "f.png")
    assert stored.shape == (6, 9, 4) and np.all(stored[..., 3] == 255) and np.array_equal(stored[..., :3], rgb)
    assert np.array_equal(D.read_rgb(tmp_path / "f.png"), rgb)


def test_validator_rgb_without_alpha_or_transparent(ds):
    import imageio.v3 as iio

    root, scene = ds
    a, b = (D.frame_paths(root, f.name).rgb for f in scene.train_frames[:2])
    iio.imwrite(a, np.zeros((scene.height, scene.width, 3), np.uint8))
    rgba = np.full((scene.height, scene.width, 4), 255, np.uint8)
    rgba[0, :3, 3] = 0
    iio.imwrite(b, rgba)
    problems = D.validate(root)
    _one(problems, str(a), "without alpha")
    _one(problems, str(b), "3 pixels have alpha below 255")
    assert len(problems) == 2


def test_validator_ids_out_of_range(ds):
    root, scene = ds
    p = D.frame_paths(root, scene.train_frames[0].name).ids
    ids = D.read_ids(p)
    ids[3, 3] = 9
    D.write_ids(p, ids)
    _one(D.validate(root), str(p), "ids out of range", "[9]")


def test_validator_truncated_png_and_exr(ds):
    root, scene = ds
    paths = D.frame_paths(root, scene.train_frames[0].name)
    paths.rgb.write_bytes(paths.rgb.read_bytes()[:40])
    paths.depth.write_bytes(paths.depth.read_bytes()[:30])
    problems = D.validate(root)
    _one(problems, str(paths.rgb), "cannot read the image")
    _one(problems, str(paths.depth), "cannot read EXR")


def test_validator_config_outside_region_and_bad_anchor(ds):
    root, scene = ds
    D.write_configuration(root, D.Configuration(0, np.array([1.0, 5.0, 1.0])))
    _one(D.validate(root), "configs/000/config.json", "outside the valid region")
    D.write_configuration(root, D.Configuration(0, np.array([2.0, 2.0, 2.0])))
    _one(D.validate(root), "configs/000/config.json", "anchor's scale")


def test_validator_depth_missing_where_object_is(ds):
    root, scene = ds
    p = D.frame_paths(root, scene.train_frames[0].name)
    d = D.read_depth(p.depth)
    d[2, 2] = np.inf
    D.write_depth(p.depth, d)
    _one(D.validate(root), str(p.depth), "non-finite or non-positive depth")


def test_validator_not_a_dataset(tmp_path):
    _one(D.validate(tmp_path), "scene.json", "missing file")
    (tmp_path / "scene.json").write_text("{not json")
    _one(D.validate(tmp_path), "scene.json", "not valid JSON")


@pytest.mark.parametrize("mutate", [
    lambda d: d["image"].update(width=None),
    lambda d: d.update(timestamps=5),
    lambda d: d["intrinsics"].update(fx="wide"),
])
def test_manifest_fields_of_the_wrong_type_are_named(ds, mutate):
    """A field of the wrong type is one problem naming scene.json, not a TypeError traceback."""
    root, _ = ds
    d = json.loads((root / "scene.json").read_text())
    mutate(d)
    (root / "scene.json").write_text(json.dumps(d))
    _one(D.validate(root), "scene.json", "malformed manifest")


def test_dataset_module_imports_neither_bpy_nor_torch():
    code = "import sys, scenecore.dataset, scenecore.atomic, scenecore.export_format, scenecore.cameras, scenecore.validity; print('bpy' in sys.modules, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False False"


def test_cli_validate(ds):
    root, scene = ds
    exe = [sys.executable, "-m", "benchgen.cli", "validate", str(root)]
    assert subprocess.run(exe, capture_output=True).returncode == 0
    D.frame_paths(root, scene.train_frames[0].name).rgb.unlink()
    r = subprocess.run(exe, capture_output=True, text=True)
    assert r.returncode == 1 and "missing file" in r.stdout

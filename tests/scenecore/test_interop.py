"""The D-NeRF / nerfstudio ``dnerf-data`` contract of ``transforms_{train,val,test}.json``.

Re-states, in numpy/imageio/PIL, what D-NeRF's ``load_blender_data`` + ``run_dnerf.py`` and
nerfstudio's dnerf dataparser read and assert (docs/dataset-format.md, "D-NeRF and nerfstudio"),
on the real ``tiny`` preset (rendered by ``benchgen generate``, which writes the files) and on a
synthetic dataset with more frames.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from PIL import Image

from scenecore import dataset as D
from scenecore.cameras import pixel_rays
from tests.synthetic import make_scene, write_synthetic_dataset

SPLITS = ("train", "val", "test")


@pytest.fixture(params=["tiny", "synthetic"])
def exported(request, tmp_path) -> tuple[Path, D.Scene, dict[str, dict]]:
    """A dataset with its transforms files: ``(root, scene, {split: parsed json})``."""
    if request.param == "tiny":
        root = request.getfixturevalue("tiny_dataset")
    else:
        root = tmp_path / "ds"
        # 5 timestamps x 3 views: 10 test views, so val is a strict subset; T odd, so testskip 2 works.
        D.write_transforms_json(root, write_synthetic_dataset(root, T=5, V=3))
    metas = {s: json.loads((root / f"transforms_{s}.json").read_text()) for s in SPLITS}
    return root, D.load_scene(root), metas


def _frame_of(scene: D.Scene, file_path: str) -> D.Frame:
    return next(f for f in scene.frames if f.name == Path(file_path).name)


def test_three_files_with_one_camera_angle(exported):
    _, _, metas = exported
    angles = {m["camera_angle_x"] for m in metas.values()}
    assert len(angles) == 1 and isinstance(next(iter(angles)), float)
    assert all(m["frames"] for m in metas.values())


def test_every_frame_entry_is_well_formed(exported):
    _, _, metas = exported
    for meta in metas.values():
        for fr in meta["frames"]:
            fp = fr["file_path"]
            assert isinstance(fp, str) and fp.startswith("./") and fp.count("./") == 1
            assert Path(fp).suffix == "" and ".." not in fp.split("/") and not os.path.isabs(fp)
            assert isinstance(fr["time"], float) and math.isfinite(fr["time"]) and 0.0 <= fr["time"] <= 1.0
            M = np.array(fr["transform_matrix"])
            assert M.shape == (4, 4) and np.all(np.isfinite(M))
            assert np.array_equal(M[3], [0, 0, 0, 1])
            R = M[:3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)


def test_both_path_joins_name_the_same_rgba_png(exported):
    root, scene, metas = exported
    shapes = set()
    for meta in metas.values():
        for fr in meta["frames"]:
            dnerf = os.path.join(str(root), fr["file_path"] + ".png")  # D-NeRF's join
            nerfstudio = root / Path(fr["file_path"].replace("./", "") + ".png")  # nerfstudio's
            assert os.path.isfile(dnerf) and os.path.samefile(dnerf, nerfstudio)
            img = imageio.imread(dnerf)
            assert img.dtype == np.uint8 and img.shape == (scene.height, scene.width, 4)
            with Image.open(nerfstudio) as im:
                assert im.mode == "RGBA"
            shapes.add(img.shape)
    assert len(shapes) == 1  # D-NeRF concatenates every split


def test_white_background_compositing_gives_our_rgb(exported):
    """D-NeRF ``white_bkgd`` / nerfstudio ``alpha_color="white"``: rgb * a + (1 - a) equals the stored RGB."""
    root, _, metas = exported
    for meta in metas.values():
        for fr in meta["frames"][:4]:
            path = os.path.join(str(root), fr["file_path"] + ".png")
            img = imageio.imread(path).astype(np.float64) / 255.0
            composite = img[..., :3] * img[..., -1:] + (1.0 - img[..., -1:])
            assert np.array_equal(composite, D.read_rgb(path) / 255.0)


@pytest.mark.parametrize("skip", [1, 2])
def test_times_start_at_zero_and_training_ends_at_one(exported, skip):
    _, scene, metas = exported
    T = len(scene.timestamps)
    for meta in metas.values():
        assert meta["frames"][::skip][0]["time"] == 0.0  # D-NeRF asserts this per split after ::testskip
    train = np.array([fr["time"] for fr in metas["train"]["frames"]], dtype=np.float32)
    assert len(train) == T and np.all(np.diff(train) >= 0)
    if (T - 1) % skip == 0:  # run_dnerf.py: times[i_train[0]] == 0 and times[i_train[-1]] == 1
        assert train[::skip][0] == 0 and train[::skip][-1] == 1


def test_focal_and_principal_point(exported):
    _, scene, metas = exported
    f = 0.5 * scene.width / math.tan(0.5 * metas["test"]["camera_angle_x"])
    k = scene.intrinsics
    assert abs(f - k.fx) <= 1e-6 * k.fx and k.fx == k.fy
    assert (k.cx, k.cy) == (scene.width / 2, scene.height / 2)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def test_opengl_rays_from_transform_matrix_equal_pixel_rays(exported):
    _, scene, metas = exported
    W, H = scene.width, scene.height
    f = 0.5 * W / math.tan(0.5 * metas["train"]["camera_angle_x"])
    pixels = np.array([[0, 0], [W - 1, 0], [W // 3, H - 1], [W // 2, H // 2]])
    for meta in metas.values():
        for fr in meta["frames"][:3]:
            M = np.array(fr["transform_matrix"])
            d_cam = np.stack([(pixels[:, 0] + 0.5 - W / 2) / f, -(pixels[:, 1] + 0.5 - H / 2) / f, -np.ones(len(pixels))], 1)
            d = d_cam @ M[:3, :3].T
            o, d_ref = pixel_rays(scene.intrinsics.matrix(), _frame_of(scene, fr["file_path"]).camera_to_world, W, H, pixels)
            assert np.allclose(o, M[:3, 3], atol=1e-12)
            assert np.allclose(_unit(d), _unit(d_ref), atol=1e-9)


def test_split_contents(exported):
    _, scene, metas = exported
    paths = {s: [fr["file_path"] for fr in metas[s]["frames"]] for s in SPLITS}
    assert sorted(paths["train"]) == sorted(f"./train/rgb/{f.name}" for f in scene.train_frames)
    assert sorted(paths["test"]) == sorted(f"./configs/000/rgb/{f.name}" for f in scene.test_frames)
    val = paths["val"]
    assert val and set(val) <= set(paths["test"]) and len(val) == len(set(val)) <= D.MAX_VAL_VIEWS
    assert val[0] == paths["test"][0]
    order = [paths["test"].index(p) for p in val]
    assert order == sorted(order)  # in test order, evenly spread over it
    if len(paths["test"]) > D.MAX_VAL_VIEWS:
        assert len(val) == D.MAX_VAL_VIEWS


def test_val_is_a_strict_evenly_spaced_subset_of_many_test_views():
    scene = make_scene(T=7, V=3)  # 14 test views
    val = D.val_frames(scene.test_frames)
    test = sorted(scene.test_frames, key=lambda f: (f.time_index, f.view))
    assert len(val) == D.MAX_VAL_VIEWS and val[0] is test[0] and val[-1] is test[-1]
    gaps = np.diff([test.index(f) for f in val])
    assert gaps.min() >= 1 and gaps.max() - gaps.min() <= 1


def _no_transforms(root: Path) -> bool:
    return not any(root.glob("transforms_*.json"))


def test_writer_rejects_a_single_timestamp(tmp_path):
    scene = make_scene(T=1, V=2)
    with pytest.raises(D.DatasetError, match=r"transforms_train\.json: the training video ends at time 0\.0.*exactly 1"):
        D.write_transforms_json(tmp_path, scene)
    assert _no_transforms(tmp_path)


@pytest.mark.parametrize("change, message", [
    (dict(cx=13.0), "principal point"),
    (dict(cy=7.5), "principal point"),
    (dict(fy=None), "differs from fy"),
])
def test_writer_rejects_intrinsics_camera_angle_x_cannot_express(tmp_path, change, message):
    scene = make_scene()
    k = scene.intrinsics
    for name, value in change.items():
        setattr(k, name, value if value is not None else 1.01 * k.fx)
    with pytest.raises(D.DatasetError, match=message):
        D.write_transforms_json(tmp_path, scene)
    assert _no_transforms(tmp_path)


def test_writer_rejects_a_test_split_not_starting_at_time_zero(tmp_path):
    scene = make_scene(T=3, V=2)
    scene.frames = [f for f in scene.frames if not (f.split == "test" and f.time_index == 0)]
    with pytest.raises(D.DatasetError, match=r"transforms_val\.json: the first frame is at time 0\.5"):
        D.write_transforms_json(tmp_path, scene)
    assert _no_transforms(tmp_path)

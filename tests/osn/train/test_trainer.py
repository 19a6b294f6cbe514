"""One step at a time on the real ``tiny`` dataset: the schedule, the three steps, the label pool."""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from osn.model.volume import render
from osn.preprocess.inputs import normalise_scales
from osn.preprocess.oracle import oracle_inputs
from osn.train import TrainConfig, Trainer, build_schedule
from osn.train.trainer import FREE_BAND, FREE_BAND_OBJECTS
from osn.train.labels import COVERAGE_THRESHOLD, anchor_bias, build_label_pool, label_pixels, render_alone_depths
from osn.train.tensors import SceneTensors
from osn.train.losses import disparity_curvature, edge_excess, sparse_depth_loss
from tests.osn.train.common import small_config as _cfg
from tests.osn.train.common import with_phantoms


def test_schedule_has_rounds_and_skips_scale_phases_for_one_object() -> None:
    cfg = _cfg()
    names = [p.name for p in build_schedule(cfg, 3)]
    assert names == ["stage1", "scale", "fields", "scale", "fields", "scale"]
    assert [p.name for p in build_schedule(cfg, 1)] == ["stage1", "fields", "fields"]
    assert [p.name for p in build_schedule(dataclasses.replace(cfg, stage1_iters=0, scale_iters=0), 3)] == ["fields", "fields", "scale"]


def test_single_object_skips_the_scale_network(tiny_dataset: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    inputs.objects = [o for o in inputs.objects if o.id == inputs.anchor]
    tr = Trainer(inputs, _cfg(), torch.device("cpu"))
    assert tr.net is None and all(p.name != "scale" for p in tr.schedule)


def test_field_phase_survives_an_untrained_network(tiny_dataset: Path, caplog) -> None:
    """No candidate above the threshold: the best one is used, a warning is logged, no crash."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(), torch.device("cpu"))
    with torch.no_grad():  # a network that scores every configuration about 0.5
        tr.net.mlp[-1].weight.zero_()
        tr.net.mlp[-1].bias.zero_()
    with caplog.at_level(logging.WARNING):
        out = tr.step_fields()
    assert np.isfinite(out["rgb"]) and np.isfinite(out["seg"]) and tr.fallbacks == 1
    with caplog.at_level(logging.WARNING):
        tr.step_fields()
    assert tr.fallbacks == 2 and caplog.text.count("no candidate scored above") == 1  # once per run, not per step


def test_field_phase_finds_a_tiny_valid_set_near_remembered_positives(tiny_dataset: Path) -> None:
    """A valid set far smaller than the box (as with many objects) that uniform candidates miss:
    candidates around the scale phase's remembered valid vectors find it, no fallback."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(), torch.device("cpu"))
    centre = torch.tensor([0.7, 0.2])

    class Tiny(torch.nn.Module):  # valid only within 0.002 of centre: 1.6e-5 of the box
        num_free = 2

        def prob(self, s: torch.Tensor) -> torch.Tensor:
            return ((s - centre).abs().max(1).values < 0.002).float()

    tr.net = Tiny()
    sbar, score = tr.sample_configuration()
    assert tr.fallbacks == 1  # nothing remembered yet: the uniform draw misses, best one used
    tr.positives = centre[None].clone()
    for _ in range(5):
        sbar, score = tr.sample_configuration()
        assert score == 1.0
    assert tr.fallbacks == 1
    free = [k for k in range(tr.st.K) if k != tr.st.anchor]
    s = normalise_scales(sbar[free].double().numpy()[None], tr.st.ranges[free].numpy())[0]
    assert np.abs(s - centre.numpy()).max() < 0.002


def test_without_depth_there_is_no_depth_loss(tiny_dataset: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    for o in inputs.objects:
        o.sparse_pix = [p[:0] for p in o.sparse_pix]
        o.sparse_depth = [d[:0] for d in o.sparse_depth]
        o.sparse_weight = [w[:0] for w in o.sparse_weight]
    tr = Trainer(inputs, _cfg(), torch.device("cpu"))
    assert not tr.st.has_depth
    assert tr.step_stage1()["depth"] == 0.0 and tr.step_fields()["depth"] == 0.0


def test_every_object_covers_label_rays_above_the_coverage_threshold(tiny_dataset: Path) -> None:
    """The anchor covers a label ray as every object does, above ``COVERAGE_THRESHOLD``, whatever
    the inputs' source; a user's config that names the removed ``anchor_coverage`` is refused."""
    cfg = _cfg()
    for source in ("oracle", "colmap"):
        inputs = oracle_inputs(tiny_dataset)
        inputs.source = source
        tr = Trainer(inputs, cfg, torch.device("cpu"))
        for _ in range(150):  # objects opaque enough to contest rays; the room behind them is not yet
            tr.step_stage1()
        flat = label_pixels(tr.st, cfg)
        c = render_alone_depths(tr.st, tr.fields, flat, cfg)
        assert torch.equal(c["covered"], c["acc"] > COVERAGE_THRESHOLD)
        assert c["covered"][:, tr.st.anchor].any() and (~c["covered"][:, tr.st.anchor]).any()
    with pytest.raises(ValueError, match="anchor_coverage"):
        TrainConfig.from_dict({"anchor_coverage": 0.5})

def test_the_pool_reads_the_anchor_at_the_depth_its_own_depths_give_beside_each_object(tiny_dataset: Path) -> None:
    """``anchor_bias``: the anchor's rendered depth against its own sparse depths beside and behind
    each object, by which the pool moves the anchor's depth on that object's rays (not at
    ``anchor_bias: 0``); on exact depths the field's own error (under 10% after 150 stage-1 steps, the
    surface the objects hide not yet fitted from the other frames). Told 10% farther
    (its depths scaled), every measured object's bias falls by about log 1.1, and the pool reads the
    anchor's depth on that object's rays, and only there, moved by the change."""
    cfg = _cfg()
    tr = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    for _ in range(150):  # opaque enough for contested rays on this 32 px scene
        tr.step_stage1()
    st, a = tr.st, tr.st.anchor
    bias = anchor_bias(st, tr.fields, cfg)
    measured = [k for k in range(st.K) if k != a and float(bias[k]) != 0.0]
    assert measured and float(bias[a]) == 0.0  # the tiny scene has anchor depths beside its objects
    assert float(bias.abs().max()) < 0.1
    before = build_label_pool(st, tr.fields, cfg, 0)
    assert torch.equal(before["anchor_bias"], bias)
    off = build_label_pool(st, tr.fields, dataclasses.replace(cfg, anchor_bias=0.0), 0)  # the paper's reading
    assert not off["anchor_bias"].any()
    at = {f: i for i, f in enumerate(off["flat"].tolist())}
    common = [i for i, f in enumerate(before["flat"].tolist()) if f in at]
    assert common  # the two pools share rays
    rendered = off["depth"][[at[int(before["flat"][i])] for i in common], a]
    assert torch.allclose(before["depth"][common, a], rendered * torch.exp(-bias[before["gt"][common]]).float(), rtol=1e-5)
    st.sp_depth[st.sp_obj == a] *= 1.1
    moved = anchor_bias(st, tr.fields, cfg)
    assert torch.allclose(moved[measured], bias[measured] - math.log(1.1), atol=0.02)
    after = build_label_pool(st, tr.fields, cfg, 0)
    row = {int(f): i for i, f in enumerate(after["flat"])}
    both = [i for i, f in enumerate(before["flat"].tolist()) if f in row]
    assert len(both) > 0.9 * len(before["flat"])
    rows = [row[before["flat"][i].item()] for i in both]
    ratio = after["depth"][rows] / before["depth"][both]  # (rays, K)
    gt = before["gt"][both]
    assert torch.isin(gt, torch.tensor(measured)).all()  # this scene's pool: objects in front of the anchor
    assert torch.allclose(ratio[:, a], torch.exp(bias - moved)[gt].float(), rtol=1e-5)
    others = torch.isfinite(ratio) & (torch.arange(st.K) != a)
    assert others.any() and torch.all(ratio[others] == 1.0)  # the objects' own depths as rendered


def test_scale_phase_warns_when_no_ray_constrains_overlapping_objects(tiny_dataset: Path, caplog) -> None:
    """Untrained fields are transparent, so no ray constrains a depth order: the scale phase
    would label every sample valid and learn nothing; it says so. Trained fields do not warn."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(), torch.device("cpu"))
    with caplog.at_level(logging.WARNING):
        tr.ensure_cache(tr.schedule[1])
    assert len(tr.cache["flat"]) == 0
    assert "no contested ray among" in caplog.text and "learns no depth order" in caplog.text
    caplog.clear()
    for _ in range(150):  # opaque enough for a few contested rays on this 32 px scene
        tr.step_stage1()
    tr.cache_key = None
    with caplog.at_level(logging.WARNING):
        tr.ensure_cache(tr.schedule[1])
    assert len(tr.cache["flat"]) > 0 and "no contested ray" not in caplog.text


def test_label_pool_uses_the_configured_or_automatic_stride(tiny_dataset: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    st = SceneTensors(inputs, torch.device("cpu"))
    pools = {k: label_pixels(st, _cfg(label_stride=k)) for k in (0, 1, 2)}
    W = inputs.images.shape[2]
    assert torch.equal(pools[0], pools[1])  # 32 px frames: automatic = every pixel
    x, y = pools[2] % W, (pools[2] // W) % inputs.images.shape[1]
    assert torch.all(x % 2 == 0) and torch.all(y % 2 == 0) and 0 < len(pools[2]) < len(pools[1]) / 3


def test_free_pixels_are_the_anchor_near_each_object(tiny_dataset: Path) -> None:
    """Without the band against other objects an object's free pixels show the anchor (or
    nothing), lie within ``FREE_BAND`` pixels of its mask, in frames where it is present; the
    anchor gets none. The trainer carves these and the band against objects; without the term
    (``w_free: 0``) no object has any."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(), torch.device("cpu"))
    st, band = tr.st, FREE_BAND
    assert all(torch.equal(a, b) for a, b in zip(tr.free, st.free_pixels(FREE_BAND, FREE_BAND_OBJECTS)))
    lab = st.labels.reshape(st.T, st.H, st.W)
    for k, free in enumerate(st.free_pixels(FREE_BAND, 0)):
        if k == st.anchor:
            assert torch.all(st.labels.reshape(-1)[free] == -1)
            continue
        assert len(free) > 0
        t, y, x = free // (st.H * st.W), (free // st.W) % st.H, free % st.W
        assert torch.all(lab[t, y, x] == st.anchor) and torch.all(st.present[k, t])
        for i in range(0, len(free), max(1, len(free) // 20)):  # a spread of them: the mask is near
            win = lab[t[i], max(0, y[i] - band) : y[i] + band + 1, max(0, x[i] - band) : x[i] + band + 1]
            assert (win == k).any()
    off = Trainer(oracle_inputs(tiny_dataset), _cfg(w_free=0.0), torch.device("cpu"))
    assert all(len(f) == 0 for f in off.free)


def test_free_pixels_also_carve_other_objects_next_to_the_mask(tiny_dataset: Path) -> None:
    """``free_band_objects > 0``: the anchor's pixels, plus, for every object but the anchor, the
    pixels of other objects within ``free_band_objects`` of its mask (a field filling the gap
    between a chair's legs covers the table seen through it); the anchor is never carved there."""
    st = SceneTensors(oracle_inputs(tiny_dataset), torch.device("cpu"))
    lab = st.labels.reshape(st.T, st.H, st.W)
    anchor = st.free_pixels(4, 0)
    for ob in (1, 2):
        objects = st.free_pixels(4, ob)
        for k in range(st.K):
            base, more = set(anchor[k].tolist()), set(objects[k].tolist())
            assert base <= more
            extra = torch.tensor(sorted(more - base), dtype=torch.long)
            if k == st.anchor:
                assert not len(extra)
                continue
            assert len(extra) > 0  # the two objects of the tiny scene overlap in some frame
            t, y, x = extra // (st.H * st.W), (extra // st.W) % st.H, extra % st.W
            assert torch.all((lab[t, y, x] >= 0) & (lab[t, y, x] != k) & (lab[t, y, x] != st.anchor))
            for i in range(len(extra)):  # every one within the band of the object's mask
                win = lab[t[i], max(0, y[i] - ob) : y[i] + ob + 1, max(0, x[i] - ob) : x[i] + ob + 1]
                assert (win == k).any()
    wide = st.free_pixels(4, 2)
    narrow = st.free_pixels(4, 1)
    assert sum(map(len, wide)) > sum(map(len, narrow))


def test_free_pixels_spare_the_pixels_of_an_object_in_front(tiny_dataset: Path) -> None:
    """Once ``(j, k)`` says j is in front of k, j's pixels leave k's free set (k may be hidden
    there) and nothing else changes; the anchor's pixels stay carved whatever a pair says."""
    st = SceneTensors(oracle_inputs(tiny_dataset), torch.device("cpu"))
    lab = st.labels.reshape(-1)
    objects = st.free_pixels(4, 1)
    j, k = [i for i in range(st.K) if i != st.anchor]
    ordered = st.free_pixels(4, 1, frozenset({(j, k), (st.anchor, j)}))
    assert torch.equal(ordered[j], objects[j]) and torch.equal(ordered[st.anchor], objects[st.anchor])
    assert torch.equal(ordered[k], objects[k][lab[objects[k]] != j])
    assert len(ordered[k]) < len(objects[k])  # the tiny scene's two objects meet in some frame


def test_free_pixels_spare_the_pixels_of_objects_the_pool_holds_no_ray_with(tiny_dataset: Path) -> None:
    """Once a label pool exists, an object is no longer carved on the pixels of an object it
    shares no pool ray with (either order) while the pool holds rays of both: k may hide there,
    and the pair's bound lies there. Before the first pool (None), and for pairs the pool holds
    rays of, nothing changes."""
    st = SceneTensors(oracle_inputs(tiny_dataset), torch.device("cpu"))
    lab = st.labels.reshape(-1)
    objects = st.free_pixels(4, 1)
    j, k = [i for i in range(st.K) if i != st.anchor]
    before = st.free_pixels(4, 1, frozenset(), None)
    assert all(torch.equal(a, b) for a, b in zip(before, objects))
    for seen in ({(j, k)}, {(k, j)}, {(j, k), (k, j)}):  # the pair has rays, in either order
        same = st.free_pixels(4, 1, frozenset(), frozenset(seen | {(j, st.anchor), (k, st.anchor)}))
        assert all(torch.equal(a, b) for a, b in zip(same, objects))
    apart = st.free_pixels(4, 1, frozenset(), frozenset({(j, st.anchor), (k, st.anchor)}))
    for a, b in ((j, k), (k, j)):
        assert torch.equal(apart[a], objects[a][lab[objects[a]] != b])
        assert len(apart[a]) < len(objects[a])  # the tiny scene's two objects meet in some frame
    assert torch.equal(apart[st.anchor], objects[st.anchor])  # the anchor's pixels stay carved
    # An object the pool holds no ray of (its field not yet opaque) stays carved, and so do the
    # others on its pixels: the pool could not have seen the pair.
    unseen = st.free_pixels(4, 1, frozenset(), frozenset({(j, st.anchor)}))
    assert all(torch.equal(a, b) for a, b in zip(unseen, objects))


def test_ordered_free_space_follows_the_label_pool_and_resumes(tiny_dataset: Path) -> None:
    """The first scale phase's pool sets which pairs are in front, the free pixels follow, and a
    checkpoint brings both back."""
    from osn.model.depth_order import in_front_pairs

    cfg = _cfg(stage1_iters=200)  # after 30 steps no ray is contested yet
    tr = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    objects = [f.clone() for f in tr.free]
    assert tr.in_front == frozenset() and tr.constrained is None
    while tr.phase(tr.iteration).name != "scale":
        tr.step()
    tr.step()
    assert tr.in_front == in_front_pairs(tr.cache["constraints"].pairs)
    assert tr.constrained == frozenset(tr.cache["constraints"].pairs)
    behind = [k for j, k in tr.in_front if tr.st.anchor not in (j, k)]
    assert behind  # the tiny scene's two objects: one is in front of the other (measured: 1 of 2)
    expected = tr.st.free_pixels(FREE_BAND, FREE_BAND_OBJECTS, tr.in_front, tr.constrained)
    assert all(torch.equal(a, b) for a, b in zip(tr.free, expected))
    assert all(len(tr.free[k]) < len(objects[k]) for k in behind)
    back = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    back.load_state_dict(tr.state_dict())
    assert back.in_front == tr.in_front and back.constrained == tr.constrained and all(torch.equal(a, b) for a, b in zip(back.free, tr.free))


def test_free_space_loss_stops_objects_bleeding_past_their_silhouette(tiny_dataset: Path) -> None:
    """Stage 1 with the free-space term leaves less opacity on the anchor pixels next to each
    object than the same training without it (same seed, same rays otherwise)."""
    def bleed(w_free: float) -> float:
        tr = Trainer(oracle_inputs(tiny_dataset), _cfg(w_free=w_free), torch.device("cpu"))
        for _ in range(60):
            tr.step_stage1()
        one = torch.ones(tr.st.K)
        accs = []
        with torch.no_grad():
            free = tr.st.free_pixels(FREE_BAND, FREE_BAND_OBJECTS)  # the same pixels either way
            for k in range(tr.st.K):
                f = free[k]
                if k == tr.st.anchor or not len(f):
                    continue
                HW = tr.st.H * tr.st.W
                out = render(tr.st.object_rays(tr.fields, f // HW, one, [k]), tr.st.dirs[f % HW], tr.cfg.samples)
                accs.append(out.acc.mean())
        return float(torch.stack(accs).mean())

    with_free, without = bleed(1.0), bleed(0.0)
    assert with_free < 0.8 * without, (with_free, without)  # measured 0.049 vs 0.070


def test_distortion_term_concentrates_each_object_on_its_pixels(tiny_dataset: Path) -> None:
    """Stage 1 with ``w_distortion`` leaves every object's weights on its own pixels less spread
    along the ray than the same training without it, and logs the term."""
    def spread(w: float) -> tuple[float, dict]:
        tr = Trainer(oracle_inputs(tiny_dataset), _cfg(w_distortion=w), torch.device("cpu"))
        for _ in range(60):
            losses = tr.step_stage1()
        one = torch.ones(tr.st.K)
        HW = tr.st.H * tr.st.W
        with torch.no_grad():
            d = [render(tr.st.object_rays(tr.fields, px // HW, one, [k]), tr.st.dirs[px % HW], tr.cfg.samples,
                        with_distortion=True).distortion.mean() for k, px in enumerate(tr.st.obj_pixels)]
        return float(torch.stack(d).mean()), losses

    (sharp, logged), (loose, plain) = spread(1.0), spread(0.0)
    assert "distortion" in logged and "distortion" not in plain and np.isfinite(logged["distortion"])
    assert sharp < 0.93 * loose, (sharp, loose)  # measured 0.173 vs 0.196 (deterministic: fixed seeds)


def test_disparity_curvature_is_zero_on_a_plane_and_not_across_a_fold() -> None:
    """A plane's disparity is affine along an image line: no cost, at any depth scale; a fold
    (the hidden part bent toward the camera) costs, and only opaque triples count."""
    x = torch.arange(5.0)
    acc = torch.ones(2, 5)
    for scale in (1e-3, 1.0, 1e4):  # extreme depths: relative, so the same figure
        plane = scale / (0.5 + 0.1 * x)  # planar depth of a tilted plane along a row
        folded = plane.clone()
        folded[3:] = plane[3:] * 0.9  # the last two pixels' surface 10% nearer
        d = torch.stack([plane, folded]) * acc
        assert float(disparity_curvature(d[:1], acc[:1])) < 1e-10
        assert float(disparity_curvature(d[1:], acc[1:])) > 1e-3
    holes = torch.tensor([[1.0, 1.0, 0.0, 1.0, 1.0]])
    assert float(disparity_curvature(torch.stack([plane, folded])[1:] * holes, holes)) == 0.0  # no opaque triple
    depth = (folded * acc[:1]).requires_grad_()
    disparity_curvature(depth, acc[:1]).backward()
    assert torch.isfinite(depth.grad).all() and depth.grad.abs().sum() > 0
    # An empty ray beside opaque triples (the anchor missing a ray): its zero disparity may not
    # turn the gradient into NaN.
    gap = torch.tensor([[1.0, 1.0, 1.0, 0.0, 1.0]])
    depth = (folded[None] * gap).requires_grad_()
    loss = disparity_curvature(depth, gap)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(depth.grad).all(), depth.grad


def test_hidden_anchor_strips_cross_objects_and_smoothing_them_flattens_the_hidden_anchor(tiny_dataset: Path) -> None:
    """Every strip is 5 adjacent pixels of one row or column, all showing something, crossing a
    pixel where an object hides the anchor; stage 1 with ``w_hidden_smooth`` leaves the anchor's
    disparity curvature on them lower than the same training without it, and logs the term."""
    inputs = oracle_inputs(tiny_dataset)
    st = SceneTensors(inputs, torch.device("cpu"))
    strips = st.hidden_anchor_strips(5)
    lab = st.labels.reshape(-1)[strips]
    assert len(strips) and (lab >= 0).all() and ((lab != st.anchor) & (lab >= 0)).any(1).all()
    step = strips[:, 1:] - strips[:, :-1]
    assert ((step == 1) | (step == st.W)).all() and (step == step[:, :1]).all()
    assert (strips // (st.H * st.W) == strips[:, :1] // (st.H * st.W)).all()  # one frame per strip
    rows = strips % (st.H * st.W) // st.W
    assert ((step[:, 0] != 1) | (rows == rows[:, :1]).all(1)).all()  # row strips do not wrap

    def curvature(w: float) -> tuple[float, dict]:
        tr = Trainer(inputs, _cfg(w_hidden_smooth=w), torch.device("cpu"))
        for _ in range(60):
            losses = tr.step_stage1()
        with torch.no_grad():
            out = tr._render_alone(st.anchor, strips.reshape(-1))
            return float(disparity_curvature(out.depth.reshape(strips.shape), out.acc.reshape(strips.shape))), losses

    (smooth, logged), (free, plain) = curvature(50.0), curvature(0.0)
    assert "hidden_smooth" in logged and "hidden_smooth" not in plain and np.isfinite(logged["hidden_smooth"])
    assert smooth < 0.75 * free, (smooth, free)  # measured 0.00081 against 0.00148 (fixed seeds)


def test_hidden_anchor_term_is_on_whatever_the_inputs_source(tiny_dataset: Path) -> None:
    """The default ``w_hidden_smooth`` trains every input with the term, the oracle's and SfM's
    alike (the source label changes nothing); a word is refused."""
    for source in ("oracle", "colmap"):
        inputs = oracle_inputs(tiny_dataset)
        inputs.source = source
        tr = Trainer(inputs, _cfg(), torch.device("cpu"))
        assert tr.cfg.w_hidden_smooth == TrainConfig().w_hidden_smooth > 0 and tr.hidden_strips is not None
        assert "hidden_smooth" in tr.step_stage1()
    with pytest.raises(ValueError, match="w_hidden_smooth"):
        _cfg(w_hidden_smooth="always")


def test_anchor_guide_trains_and_renders_the_anchor_alone(tiny_dataset: Path, tmp_path: Path) -> None:
    """``anchor_guide_samples`` reaches the anchor's rays in training and in the trained run's
    renders (so evaluation samples the room as training did), never the other objects'; a run
    whose config predates the option renders evenly."""
    from osn.model.run import load_run
    from osn.train.loop import train
    from scenecore import dataset as D

    inputs = oracle_inputs(tiny_dataset)
    tr = Trainer(inputs, _cfg(anchor_guide_samples=16), torch.device("cpu"))
    rays = tr.st.object_rays(tr.fields, torch.zeros(1, dtype=torch.long), torch.ones(tr.st.K))
    assert [r.guide for r in rays] == [16 if k == tr.st.anchor else 0 for k in range(tr.st.K)]
    train(tmp_path / "r", _cfg(anchor_guide_samples=16, stage1_iters=20, rounds=1, final_scale_iters=5),
          inputs=inputs, progress=False)
    run = load_run(tmp_path / "r")
    pose = torch.eye(4)
    assert [run._object_rays(k, pose, 3).guide for k in range(inputs.num_objects)] == \
        [16 if k == run.anchor_pos else 0 for k in range(inputs.num_objects)]
    f = min(D.load_scene(tiny_dataset).train_frames, key=lambda fr: fr.time_index)
    guided = run.render_view(None, f.time_index, np.ones(inputs.num_objects))
    assert np.isfinite(guided["rgb"]).all() and np.isfinite(guided["acc"]).all()
    # A checkpoint written before the resolved value was stored: ``auto`` as it was then (0 on the
    # oracle's inputs), and a run trained before the option: even.
    from osn.train.auto import ANCHOR_GUIDE_SAMPLES, checkpoint_anchor_guide_samples, resolve_anchor_guide_samples
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    assert ckpt["anchor_guide"] == 16
    del ckpt["anchor_guide"]
    for config, guide in (({"anchor_guide_samples": "auto"}, 0), ({}, 0), ({"anchor_guide_samples": 8}, 8)):
        ckpt["config"] = {k: v for k, v in ckpt["config"].items() if k != "anchor_guide_samples"} | config
        torch.save(ckpt, tmp_path / "r" / "checkpoint.pt")
        old = load_run(tmp_path / "r")
        assert [old._object_rays(k, pose, 3).guide for k in range(inputs.num_objects)] == \
            [guide if k == run.anchor_pos else 0 for k in range(inputs.num_objects)]
    assert not np.array_equal(old.render_view(None, f.time_index, np.ones(inputs.num_objects))["rgb"], guided["rgb"])
    assert checkpoint_anchor_guide_samples({"config": {"anchor_guide_samples": "auto"}}, "colmap") == ANCHOR_GUIDE_SAMPLES > 0
    assert checkpoint_anchor_guide_samples({"anchor_guide": 0, "config": {"anchor_guide_samples": "auto"}}, "colmap") == 0
    # ``auto`` (the default): guided wherever the anchor's box spans more pixels than its grid has
    # voxels, whatever the inputs' source: the tiny scene's room (about 50 px across) at the CPU
    # config's 64^3 is even, at these tests' 24^3 guided; a number is itself.
    from osn.train import TrainConfig
    assert TrainConfig().anchor_guide_samples == "auto"
    small = dataclasses.replace(_cfg().field, anchor_planes="auto")
    cpu = dataclasses.replace(small, resolution=64)
    for source in ("oracle", "colmap"):
        src = dataclasses.replace(inputs, source=source)
        assert resolve_anchor_guide_samples("auto", cpu, src) == 0
        assert resolve_anchor_guide_samples("auto", small, src) == ANCHOR_GUIDE_SAMPLES
        assert resolve_anchor_guide_samples(8, cpu, src) == 8
    assert Trainer(inputs, _cfg(anchor_guide_samples="auto", field=small), torch.device("cpu")).st.guide == ANCHOR_GUIDE_SAMPLES
    assert Trainer(inputs, _cfg(anchor_guide_samples="auto", field=cpu), torch.device("cpu")).st.guide == 0


def test_scale_phase_samples_near_earlier_valid_vectors_and_resumes_them(tiny_dataset: Path) -> None:
    cfg = _cfg(label_replay=0.5, scale_samples=200)
    tr = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    s = tr._scale_samples()
    assert s.shape == (200, tr.st.K - 1) and len(tr.positives) == 0  # nothing to replay yet: uniform
    for _ in range(3):
        tr.step_scale(tr.schedule[1])
    assert len(tr.positives) > 0
    tr.positives = torch.tensor([[0.7, 0.2]])  # one remembered vector: replay must be near it
    s = tr._scale_samples()
    assert s.shape == (200, tr.st.K - 1) and torch.all((s >= 0) & (s < 1))
    d_near = (s[100:] - tr.positives).norm(dim=1)
    d_uniform = (s[:100] - tr.positives).norm(dim=1)
    assert float(d_near.max()) < 0.5 and float(d_near.median()) < 0.1  # jitter of 0.01-0.1
    assert float(d_uniform.median()) > 0.2  # the uniform half is not drawn there
    tr2 = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    assert len(tr2.positives) == 0
    tr2.load_state_dict(tr.state_dict())
    assert torch.equal(tr2.positives, tr.positives)


def test_final_scale_phase_labels_with_final_label_trim(tiny_dataset: Path) -> None:
    """The rounds' scale phases allow no violation beyond the best sample's, the final one
    ``final_label_trim``: with 1 the rounds reject samples while the final phase accepts every one
    (a trim of a pair's every ray allows any violation), and with 0 the final phase rejects too."""
    cfg = _cfg(final_label_trim=1.0)
    tr = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    for _ in range(150):  # opaque enough for contested rays (see the test above)
        tr.step_stage1()
    first, final = tr.schedule[1], tr.schedule[-1]
    assert first.name == final.name == "scale" and first.round == 1 and final.round == cfg.rounds + 1
    assert (tr.label_trim_at(first), tr.label_trim_at(final)) == (0.0, 1.0)
    assert tr.step_scale(first)["valid_frac"] < 0.9
    assert tr.step_scale(final)["valid_frac"] == 1.0
    tr.cfg = dataclasses.replace(cfg, final_label_trim=0.0)
    assert tr.step_scale(final)["valid_frac"] < 0.9


def test_sparse_depth_loss_is_the_squared_error_for_most_depths_and_bounded_for_far_ones() -> None:
    t = torch.ones(100, dtype=torch.float64)
    r = torch.linspace(-0.02, 0.02, 100, dtype=torch.float64)
    r[:10] = 0.5  # ten phantom depths, half a unit off
    d = (t + r).requires_grad_(True)
    assert torch.allclose(sparse_depth_loss(d, t, 0.0), r.square().mean(), rtol=1e-12, atol=0)
    sparse_depth_loss(d, t, 3.0).backward()
    g = d.grad.numpy() * 100  # per depth: 2r / (1 + r^2 / c^2), c = 3 x median |r|
    plain = 2 * r.numpy()
    inliers = (np.abs(r.numpy()) <= float(r.abs().median())) & (r.numpy() != 0)
    ratio = g[inliers] / plain[inliers]  # 1 / (1 + r^2 / c^2) >= 1 / (1 + 1/9) up to the median
    assert inliers.sum() >= 45 and np.all((ratio >= 0.9 - 1e-9) & (ratio <= 1.0 + 1e-9))
    assert np.all(g[:10] < 0.01 * plain[:10])  # the phantoms pull < 1% of what they would
    # Extreme residuals and an exact fit stay finite; an empty batch is zero.
    for res in (torch.full((4,), 1e6), torch.zeros(4), torch.tensor([0.0, 0.0, 0.0, 1e-30])):
        dd = (1.0 + res.double()).requires_grad_(True)
        loss = sparse_depth_loss(dd, torch.ones(4, dtype=torch.float64), 3.0)
        loss.backward()
        assert torch.isfinite(loss) and torch.all(torch.isfinite(dd.grad))
    assert float(sparse_depth_loss(d.detach()[:0], t[:0], 3.0)) == 0.0


def test_robust_depth_loss_keeps_phantom_sparse_depths_from_pulling_the_surface(tiny_dataset: Path) -> None:
    """A quarter of the room's sparse depths moved to half their depth (what SfM triangulates on a
    checker floor): after stage 1 with the robust loss the room renders closer to its true depth
    at those pixels, and no farther elsewhere, than with the squared error."""
    def errors(robust: float) -> tuple[float, float]:
        inputs = oracle_inputs(tiny_dataset)
        room = inputs.object(inputs.anchor)
        truth = np.concatenate(room.sparse_depth)
        rng = np.random.default_rng(0)
        moved = [rng.random(len(d)) < 0.25 for d in room.sparse_depth]
        for d, m in zip(room.sparse_depth, moved):
            d[m] *= 0.5
        tr = Trainer(inputs, _cfg(depth_robust=robust), torch.device("cpu"))
        for _ in range(240):
            tr.step_stage1()
        frames = torch.cat([torch.full((len(p),), int(f)) for f, p in zip(room.frames, room.sparse_pix)])
        pix = torch.from_numpy(np.concatenate([p[:, 1] * tr.st.W + p[:, 0] for p in room.sparse_pix]))
        with torch.no_grad():
            rays = tr.st.object_rays(tr.fields, frames, torch.ones(tr.st.K), [inputs.anchor_pos])
            depth = render(rays, tr.st.dirs[pix], tr.cfg.samples).depth.numpy()
        err, m = np.abs(depth - truth) / truth, np.concatenate(moved)
        return float(np.median(err[m])), float(np.median(err[~m]))

    (robust_moved, robust_kept), (plain_moved, plain_kept) = errors(3.0), errors(0.0)
    # measured 0.157 / 0.115 against 0.186 / 0.130 (fixed seeds)
    assert robust_moved < 0.9 * plain_moved, (robust_moved, plain_moved)
    assert robust_kept <= plain_kept, (robust_kept, plain_kept)


def test_trainer_resolves_auto_depth_robustness_from_the_measured_noise(tiny_dataset: Path) -> None:
    """Exact depths keep the squared error whatever their label; phantoms make the loss robust."""
    inputs = oracle_inputs(tiny_dataset)
    assert Trainer(inputs, _cfg(), torch.device("cpu")).depth_robust == 0.0  # exact depths: squared error
    inputs.source = "colmap"
    assert Trainer(inputs, _cfg(), torch.device("cpu")).depth_robust == 0.0  # the label is not read
    assert Trainer(with_phantoms(inputs), _cfg(), torch.device("cpu")).depth_robust == 3.0
    assert Trainer(with_phantoms(inputs), _cfg(depth_robust=0.0), torch.device("cpu")).depth_robust == 0.0


def test_edge_pairs_are_silhouette_pixels_and_their_inner_neighbours(tiny_dataset: Path) -> None:
    """Every edge pixel lies on its object's mask with a 4-neighbour off it (the image border is
    not a silhouette); its partner is a 4-neighbour on the mask farther from the boundary; every
    silhouette pixel with such a neighbour is there."""
    from scipy.ndimage import distance_transform_edt

    st = SceneTensors(oracle_inputs(tiny_dataset), torch.device("cpu"))
    lab = st.labels.reshape(st.T, st.H, st.W).numpy()
    HW = st.H * st.W
    for k, (edge, inner) in enumerate(st.edge_pairs()):
        assert len(edge) > 0 and len(edge) == len(inner)
        t, y, x = (edge // HW).numpy(), (edge % HW // st.W).numpy(), (edge % st.W).numpy()
        ti, yi, xi = (inner // HW).numpy(), (inner % HW // st.W).numpy(), (inner % st.W).numpy()
        assert np.all(t == ti) and np.all(np.abs(y - yi) + np.abs(x - xi) == 1)
        assert np.all(lab[t, y, x] == k) and np.all(lab[ti, yi, xi] == k)
        dist = np.stack([distance_transform_edt(lab[f] == k) for f in range(st.T)])
        assert np.all(dist[t, y, x] == 1.0) and np.all(dist[ti, yi, xi] > 1.0)
        got = set(edge.tolist())
        for f, yy, xx in zip(*np.nonzero(dist == 1.0)):
            nb = [dist[f, yy + dy, xx + dx] for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1))
                  if 0 <= yy + dy < st.H and 0 <= xx + dx < st.W]
            assert (f * HW + yy * st.W + xx in got) == (max(nb) > 1.0)


def test_edge_excess_is_one_sided_beyond_the_slope_and_skips_empty_rays() -> None:
    """Depths are the renderer's ``sum w t`` with opacity ``acc``: an edge reading 10% farther
    than inside costs (log 1.1 - slope)^2, one reading nearer or within the slope costs nothing,
    and a ray that misses the object (acc <= 0.5, depth +inf once normalised) is left out."""

    slope = 0.02

    acc = torch.tensor([1.0, 0.8, 1.0, 0.2, 1.0])
    depth = torch.tensor([2.2, 0.8 * 1.9, 2.0 * (1 + slope / 2), 0.0, 3.0], requires_grad=True)
    inner_depth = torch.tensor([2.0, 2.0, 2.0, 2.0, 3.0])
    inner_acc = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.3])
    loss = edge_excess(depth, acc, inner_depth, inner_acc, slope)
    expect = (np.log(1.1) - slope) ** 2 / 3  # rays 0-2 count; only ray 0 exceeds
    assert loss.item() == pytest.approx(expect, rel=1e-5)
    loss.backward()
    assert depth.grad[0] > 0 and torch.all(depth.grad[1:] == 0)  # pulls the far edge in, nothing else
    none = edge_excess(depth[3:4], acc[3:4], inner_depth[3:4], inner_acc[3:4], slope)
    assert float(none) == 0.0 and torch.isfinite(none)


def test_edge_term_is_reported_when_on_and_auto_follows_the_measured_noise(tiny_dataset: Path) -> None:
    """``w_edge > 0``: stage-1 steps report a finite edge loss. ``auto`` (the default) and the
    other options that correct for noisy inputs read whether the depths agree across frames
    (:mod:`osn.preprocess.depth_noise`), never the source label: exact inputs labelled SfM train
    as the oracle's do, the oracle's with phantom depths as SfM's do."""
    from osn.train.auto import DEPTH_ROBUST_NOISY, W_EDGE_NOISY, resolve_w_edge

    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(w_edge=1.0), torch.device("cpu"))
    out = tr.step_stage1()
    assert "edge" in out and np.isfinite(out["edge"])
    fcfg = dataclasses.replace(_cfg().field, object_resolution="auto")
    exact = oracle_inputs(tiny_dataset)
    for inputs in (exact, dataclasses.replace(exact, source="colmap")):
        auto = Trainer(inputs, _cfg(field=fcfg), torch.device("cpu"))
        assert auto.w_edge == 0.0 and auto.edges is None and "edge" not in auto.step_stage1()
        assert auto.depth_robust == 0.0 and not auto.depth_consistency.noisy
        assert auto.resolutions == [[16, 24]] * inputs.num_objects
    noisy = Trainer(with_phantoms(exact, 0.05), _cfg(field=fcfg), torch.device("cpu"))
    assert noisy.st.inputs.source == "oracle" and noisy.depth_consistency.noisy
    assert noisy.w_edge == W_EDGE_NOISY > 0 and noisy.depth_robust == DEPTH_ROBUST_NOISY > 0
    assert "edge" in noisy.step_stage1()
    a = exact.anchor_pos
    assert all(r[-1] < 24 for k, r in enumerate(noisy.resolutions) if k != a) and noisy.resolutions[a] == [16, 24]
    assert noisy.state_dict()["depth_consistency"]["noisy"] is True
    assert resolve_w_edge("auto", noisy=True) == W_EDGE_NOISY and resolve_w_edge(0.5, noisy=False) == 0.5
    with pytest.raises(ValueError, match="w_edge"):
        _cfg(w_edge="sometimes")


def test_final_phase_trims_the_same_whatever_the_inputs_source(tiny_dataset: Path) -> None:
    """The final scale phase trims ``final_label_trim`` (0.2% by default) on every input, the
    rounds nothing; the source label changes neither."""
    trims = {}
    for source in ("oracle", "colmap"):
        inputs = oracle_inputs(tiny_dataset)
        inputs.source = source
        tr = Trainer(inputs, _cfg(), torch.device("cpu"))
        scale = [p for p in tr.schedule if p.name == "scale"]
        assert scale[-1].round == tr.cfg.rounds + 1 and all(p.round <= tr.cfg.rounds for p in scale[:-1])
        trims[source] = [tr.label_trim_at(p) for p in scale]
    assert trims["oracle"] == trims["colmap"] == [0.0, 0.0, 0.002]


def test_objects_grids_grow_to_their_footprint_and_the_anchors_to_resolution(tiny_dataset: Path, tmp_path: Path) -> None:
    """``field.object_resolution: auto`` gives every object but the anchor a grid of about a voxel
    per training pixel on noisy inputs (here the tiny scene's oracle inputs with phantom depths on
    an object), grown on the anchor's schedule; the trained run loads each at its own size. On exact
    inputs, and with 0, every object stays at ``resolution``."""
    from osn.model.fields import FieldConfig
    from osn.model.run import load_run
    from osn.preprocess.depth_noise import depth_consistency
    from osn.train.auto import MIN_ANCHOR_PLANES, anchor_pixels, anchor_plane_size, object_resolutions
    from osn.train.loop import train

    oracle = oracle_inputs(tiny_dataset)
    inputs = with_phantoms(oracle, 0.1, k=oracle.num_objects - 1)  # an object's: the anchor's planes stay as they are
    assert depth_consistency(inputs).noisy and oracle.anchor_pos != oracle.num_objects - 1
    fcfg = FieldConfig(kind="dense", resolution=24, initial_resolution=16, upsample_steps=1, object_resolution="auto")
    sched = object_resolutions(fcfg, inputs, noisy=True)
    assert object_resolutions(fcfg, oracle, noisy=False) == [[16, 24]] * oracle.num_objects
    a = inputs.anchor_pos
    assert sched[a] == [16, 24]
    assert all(s[-1] < 24 and s[0] < s[-1] for k, s in enumerate(sched) if k != a), sched  # objects ~10 px wide at 32 px
    train(tmp_path / "r", _cfg(field=fcfg), inputs=inputs, progress=False)
    run = load_run(tmp_path / "r")
    assert [f.resolution for f in run.fields] == [s[-1] for s in sched]
    # Only the anchor carries colour planes (``anchor_planes: auto``: a texel about a pixel at its
    # median sparse depth), they trained, and the run loads them at their size.
    P = anchor_plane_size(fcfg, inputs)
    assert MIN_ANCHOR_PLANES < P < 128, P  # the tiny scene: 32 px frames
    assert [f.planes is not None for f in run.fields] == [k == a for k in range(inputs.num_objects)]
    assert run.fields[a].plane_size == P and run.fields[a].planes.abs().max() > 0
    assert anchor_plane_size(dataclasses.replace(fcfg, anchor_planes=0), inputs) == 0
    assert anchor_plane_size(dataclasses.replace(fcfg, anchor_planes=40), inputs) == 40
    assert anchor_plane_size(dataclasses.replace(fcfg, kind="tensorf"), inputs) == 0
    assert anchor_plane_size(fcfg, oracle) == P  # the same rule on the oracle's inputs
    # None where the grid holds as much: the box spans no more pixels than the grid has voxels.
    n = anchor_pixels(inputs)
    assert P == round(n) and anchor_plane_size(dataclasses.replace(fcfg, resolution=int(np.ceil(n))), inputs) == 0
    assert anchor_plane_size(dataclasses.replace(fcfg, resolution=int(np.floor(n))), inputs) == P

    def anchor_as(**kw) -> "SceneInputs":
        objects = list(inputs.objects)
        objects[a] = dataclasses.replace(objects[a], **kw)
        return dataclasses.replace(inputs, objects=objects)

    o = inputs.objects[a]
    for unit in (1e-3, 1e4):  # the anchor's unknown unit does not change the texel count
        assert anchor_plane_size(fcfg, anchor_as(bbox=o.bbox * unit, sparse_depth=[d * unit for d in o.sparse_depth])) == P
    assert anchor_plane_size(fcfg, anchor_as(sparse_depth=[d[:0] for d in o.sparse_depth])) == 0  # no depth: no planes
    # A run whose checkpoint predates the two options loads as it trained: each field at the
    # size its checkpoint holds, no planes.
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    for key in ("object_resolution", "anchor_planes"):
        del ckpt["config"]["field"][key]
    ckpt["fields"][a] = {k: v for k, v in ckpt["fields"][a].items() if k != "planes"}
    torch.save(ckpt, tmp_path / "r" / "checkpoint.pt")
    old = load_run(tmp_path / "r")
    t0 = int(inputs.objects[a].frames[0])
    assert old.fields[a].planes is None and np.isfinite(old.render_view(None, t0, np.ones(inputs.num_objects))["rgb"]).all()
    # Resuming one (trained without planes, where ``auto`` now gives P): the trainer rebuilds the
    # anchor's field as its checkpoint holds it, and its guide as it trained (no ``anchor_guide``
    # in the checkpoint: ``auto`` was even on the oracle's inputs).
    cfg = _cfg(field=dataclasses.replace(fcfg, anchor_planes=0), anchor_guide_samples=0)
    train(tmp_path / "p0", cfg, inputs=oracle, progress=False)
    ckpt = torch.load(tmp_path / "p0" / "checkpoint.pt", weights_only=True)
    del ckpt["anchor_guide"]
    resumed = Trainer(oracle, _cfg(field=fcfg, anchor_guide_samples="auto"), torch.device("cpu"))
    assert resumed.fields[a].planes is not None and resumed.st.guide > 0  # what ``auto`` gives on these inputs
    resumed.load_state_dict(ckpt)
    assert resumed.fields[a].planes is None and resumed.st.guide == 0
    resumed.step_fields()  # trains on as it trained
    assert resumed.non_finite_parameters() == []
    same = dataclasses.replace(fcfg, object_resolution=0)
    assert object_resolutions(same, inputs, noisy=True) == [[16, 24]] * inputs.num_objects
    assert object_resolutions(dataclasses.replace(fcfg, object_resolution=20), inputs, noisy=True) == \
        [[16, 24] if k == a else [13, 20] for k in range(inputs.num_objects)]

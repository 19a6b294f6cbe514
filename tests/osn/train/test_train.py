"""Training on the real ``tiny`` benchgen dataset: it learns, resumes exactly, handles one object."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from osn.model.fields import FieldConfig
from osn.preprocess.inputs import normalise_scales, oracle_inputs
from osn.train.loop import Evaluator, Trainer, TrainConfig, build_schedule, train
from osn.model.volume import render


def _cfg(**kw) -> TrainConfig:
    base = dict(
        stage1_iters=30, rounds=2, field_iters=10, scale_iters=10, final_scale_iters=10,
        rays_per_object=128, rays=256, depth_rays=32, samples=12, scale_samples=64, label_rays=512,
        label_stride=1, eval_every=20, eval_pixels=512, iou_samples=2000, checkpoint_every=25,
        field=FieldConfig(kind="dense", resolution=24, initial_resolution=16, upsample_steps=1),
    )
    base.update(kw)
    return TrainConfig(**base)


def _metrics(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def test_schedule_has_rounds_and_skips_scale_phases_for_one_object() -> None:
    cfg = _cfg()
    names = [p.name for p in build_schedule(cfg, 3)]
    assert names == ["stage1", "scale", "fields", "scale", "fields", "scale"]
    assert [p.name for p in build_schedule(cfg, 1)] == ["stage1", "fields", "fields"]


def test_training_improves_psnr_and_writes_metrics(tiny_dataset: Path, tmp_path: Path) -> None:
    run = train(tiny_dataset, tmp_path / "run", _cfg(), progress=False)
    m = _metrics(run)
    assert m[-1]["iteration"] == 30 + 2 * (10 + 10) + 10
    assert m[-1]["psnr"] > m[0]["psnr"] + 3.0
    for key in ("wall_time", "rgb", "iou", "precision", "recall", "scale_rel_err"):
        assert any(key in r for r in m), key
    assert all(0.0 <= r["iou"] <= 1.0 for r in m if "iou" in r)
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["iteration"] == m[-1]["iteration"] and ck["net"] is not None


def test_resume_equals_uninterrupted(tiny_dataset: Path, tmp_path: Path) -> None:
    cfg = _cfg(checkpoint_every=17)
    a = train(tiny_dataset, tmp_path / "a", cfg, progress=False)
    # Interrupted inside the first scale phase (the depth cache must be rebuilt identically),
    # then again inside a field phase.
    b = train(tiny_dataset, tmp_path / "b", cfg, progress=False, max_iterations=35)
    train(None, b, resume=True, progress=False, max_iterations=45)
    train(None, b, resume=True, progress=False)
    sa = torch.load(a / "checkpoint.pt", weights_only=False)
    sb = torch.load(b / "checkpoint.pt", weights_only=False)
    for fa, fb in zip(sa["fields"], sb["fields"]):
        for k in fa:
            assert torch.equal(fa[k], fb[k]), k
    for k in sa["net"]:
        assert torch.equal(sa["net"][k], sb["net"][k]), k
    ma, mb = _metrics(a), _metrics(b)
    drop = ("wall_time",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in ma] == [{k: v for k, v in r.items() if k not in drop} for r in mb]


def test_resume_refuses_to_overwrite_and_needs_a_checkpoint(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        train(None, tmp_path / "nothing", resume=True, progress=False)
    out = tmp_path / "r"
    out.mkdir()
    # A run killed before its first checkpoint leaves metric lines and no checkpoint; a fresh
    # start must not keep them in front of its own curve.
    (out / "metrics.jsonl").write_text('{"iteration": 20, "stale": true}\n{"iteration": 40, "sta')
    run = train(tiny_dataset, out, _cfg(stage1_iters=2, rounds=0, final_scale_iters=0), progress=False)
    assert [m["iteration"] for m in _metrics(run)] == [2] and "stale" not in _metrics(run)[0]
    with pytest.raises(FileExistsError):
        train(tiny_dataset, run, _cfg(), progress=False)


@pytest.mark.parametrize("bad", [{"eval_every": 0}, {"checkpoint_every": 0}, {"samples": 0}, {"rounds": -1},
                                 {"valid_threshold": 1.5}, {"valid_threshold": 1.0}, {"rounds": "five"},
                                 {"label_replay": "high"}])
def test_config_rejects_values_that_would_divide_by_zero_or_mean_nothing(bad: dict, tmp_path: Path) -> None:
    (key, value), = bad.items()
    with pytest.raises(ValueError, match=f"{key} must"):
        _cfg(**bad)
    path = tmp_path / "c.yaml"
    path.write_text(f"{key}: {value}\n")
    with pytest.raises(ValueError, match=f"^{path}: training config: {key} must"):
        TrainConfig.from_yaml(path)


def test_single_object_skips_the_scale_network(tiny_dataset: Path, tmp_path: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    inputs.objects = [o for o in inputs.objects if o.id == inputs.anchor]
    tr = Trainer(inputs, _cfg(), torch.device("cpu"))
    assert tr.net is None and all(p.name != "scale" for p in tr.schedule)
    run = train(tiny_dataset, tmp_path / "one", _cfg(), inputs=inputs, progress=False)
    m = _metrics(run)
    assert "iou" not in m[-1] and "seg_acc" not in m[-1]
    assert m[-1]["iteration"] == 30 + 2 * 10


def test_field_phase_survives_an_untrained_network(tiny_dataset: Path, caplog) -> None:
    """No candidate above the threshold: the best one is used, a warning is logged, no crash."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(valid_threshold=0.999999), torch.device("cpu"))
    with caplog.at_level(logging.WARNING):
        out = tr.step_fields()
    assert np.isfinite(out["rgb"]) and np.isfinite(out["seg"]) and tr.fallbacks == 1
    with caplog.at_level(logging.WARNING):
        tr.step_fields()
    assert tr.fallbacks == 2 and caplog.text.count("no candidate scored above") == 1  # once per run, not per step


def test_field_phase_finds_a_tiny_valid_set_near_remembered_positives(tiny_dataset: Path) -> None:
    """A valid set far smaller than the box (as with many objects) that uniform candidates miss:
    candidates around the scale phase's remembered valid vectors find it, no fallback."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(candidates=64), torch.device("cpu"))
    centre = torch.tensor([0.7, 0.2])

    class Tiny(torch.nn.Module):  # valid only within 0.005 of centre: 1e-4 of the box
        num_free = 2

        def prob(self, s: torch.Tensor) -> torch.Tensor:
            return ((s - centre).abs().max(1).values < 0.005).float()

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
    assert np.abs(s - centre.numpy()).max() < 0.005


def test_without_depth_there_is_no_depth_loss(tiny_dataset: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    for o in inputs.objects:
        o.sparse_pix = [p[:0] for p in o.sparse_pix]
        o.sparse_depth = [d[:0] for d in o.sparse_depth]
        o.sparse_weight = [w[:0] for w in o.sparse_weight]
    tr = Trainer(inputs, _cfg(), torch.device("cpu"))
    assert not tr.st.has_depth
    assert tr.step_stage1()["depth"] == 0.0 and tr.step_fields()["depth"] == 0.0


def test_evaluator_is_exact_with_an_oracle_network(tiny_dataset: Path) -> None:
    """A network that is the exact region's indicator (computed from the dataset's region and
    units, not from the Evaluator's labels) scores IoU 1, and the labels are not trivial."""
    from scenecore import dataset as D

    inputs = oracle_inputs(tiny_dataset)
    tr = Trainer(inputs, _cfg(), torch.device("cpu"))
    ev = Evaluator(tr, tiny_dataset)
    assert 0.0 < ev.exact.mean() < 1.0  # some Monte-Carlo samples are valid, some are not
    region = D.load_valid_region(tiny_dataset)
    units = np.array([o.unit_to_world for o in inputs.objects])
    ranges = tr.st.ranges.cpu().numpy()
    free = [k for k in range(tr.st.K) if k != tr.st.anchor]
    assert all(region.contains(c.scales) for c in D.load_configurations(tiny_dataset))  # the dataset's promise

    class Oracle(torch.nn.Module):
        def forward(self, s: torch.Tensor) -> torch.Tensor:
            sbar = np.ones((len(s), tr.st.K))
            sbar[:, free] = ranges[free, 0] + s.double().cpu().numpy() * (ranges[free, 1] - ranges[free, 0])
            actual = sbar * units[tr.st.anchor] / units  # s_k = sbar_k u_anchor / u_k
            full = np.ones((len(s), region.num_objects))
            full[:, [o.id for o in inputs.objects]] = actual
            return torch.where(torch.from_numpy(np.asarray(region.contains(full))), 10.0, -10.0)

    tr.net = Oracle()
    m = ev()
    assert m["iou"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0 and m["scale_rel_err"] == 0.0


def test_built_in_defaults_are_the_cpu_config() -> None:
    root = Path(__file__).resolve().parents[3]
    assert TrainConfig() == TrainConfig.from_yaml(root / "configs" / "osn-cpu.yaml")
    with pytest.raises(ValueError, match="unknown training config keys"):
        TrainConfig.from_dict({"stage1_iter": 3})


def test_label_pool_drops_rays_with_a_semi_transparent_object(tiny_dataset: Path) -> None:
    """``uncertain_acc`` below the coverage threshold removes every ray on which some object's
    independent opacity is in between from the contested pool; equal to it, nothing is removed."""
    cfg = _cfg(coverage_threshold=0.9, uncertain_acc=0.05)
    tr = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    for _ in range(10):  # partly trained fields: opacities spread over (0, 1)
        tr.step_stage1()
    flat = tr._label_pixels()
    c = tr.render_alone_depths(flat)
    expected = ((c["acc"] > 0.05) & (c["acc"] <= 0.9)).any(1)
    assert torch.equal(c["uncertain"], expected) and expected.any() and (~expected).any()
    tr.ensure_cache(tr.schedule[1])
    assert not torch.isin(tr.cache["flat"], flat[expected]).any()
    tr.cfg = dataclasses.replace(cfg, uncertain_acc=0.9)
    assert not tr.render_alone_depths(flat)["uncertain"].any()


def test_scale_phase_warns_when_no_ray_constrains_overlapping_objects(tiny_dataset: Path, caplog) -> None:
    """Untrained fields are transparent, so no ray constrains a depth order: the scale phase
    would label every sample valid and learn nothing; it says so. Trained fields do not warn."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(coverage_threshold=0.9, uncertain_acc=0.05), torch.device("cpu"))
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


def test_resume_skips_a_metrics_line_cut_by_a_kill(tmp_path):
    from osn.train.loop import _truncate_metrics

    p = tmp_path / "metrics.jsonl"
    p.write_text('{"iteration": 100}\n{"iteration": 200}\n{"iteration": 3')
    _truncate_metrics(p, 150)
    assert p.read_text() == '{"iteration": 100}\n'


def test_free_pixels_are_the_anchor_near_each_object(tiny_dataset: Path) -> None:
    """``free_space: anchor``: an object's free pixels show the anchor (or nothing), lie within
    ``free_band`` pixels of its mask, in frames where it is present; the anchor gets none."""
    tr = Trainer(oracle_inputs(tiny_dataset), _cfg(), torch.device("cpu"))
    st, band = tr.st, tr.cfg.free_band
    lab = st.labels.reshape(st.T, st.H, st.W)
    for k in range(st.K):
        free = tr.free[k]
        if k == st.anchor:
            assert torch.all(st.labels.reshape(-1)[free] == -1)
            continue
        assert len(free) > 0
        t, y, x = free // (st.H * st.W), (free // st.W) % st.H, free % st.W
        assert torch.all(lab[t, y, x] == st.anchor) and torch.all(st.present[k, t])
        for i in range(0, len(free), max(1, len(free) // 20)):  # a spread of them: the mask is near
            win = lab[t[i], max(0, y[i] - band) : y[i] + band + 1, max(0, x[i] - band) : x[i] + band + 1]
            assert (win == k).any()
    assert all(len(f) == 0 for f in st.free_pixels("none", band))
    with pytest.raises(ValueError, match="free_space"):
        Trainer(oracle_inputs(tiny_dataset), _cfg(free_space="walls"), torch.device("cpu"))


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
            for k in range(tr.st.K):
                f = tr.free[k]
                if k == tr.st.anchor or not len(f):
                    continue
                HW = tr.st.H * tr.st.W
                out = render(tr.st.object_rays(tr.fields, f // HW, one, [k]), tr.st.dirs[f % HW], tr.cfg.samples)
                accs.append(out.acc.mean())
        return float(torch.stack(accs).mean())

    with_free, without = bleed(1.0), bleed(0.0)
    assert with_free < 0.8 * without, (with_free, without)  # measured 0.049 vs 0.070


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


def test_auto_label_stride_keeps_the_pool_size_of_a_128_pixel_frame():
    from osn.train.loop import label_stride

    assert [label_stride(0, s, s) for s in (32, 64, 128, 129, 256, 512)] == [1, 1, 1, 2, 2, 4]
    assert label_stride(0, 300, 512) == 4 and label_stride(3, 512, 512) == 3


def test_label_pool_uses_the_configured_or_automatic_stride(tiny_dataset: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    pools = {k: Trainer(inputs, _cfg(label_stride=k), torch.device("cpu"))._label_pixels() for k in (0, 1, 2)}
    W = inputs.images.shape[2]
    assert torch.equal(pools[0], pools[1])  # 32 px frames: automatic = every pixel
    x, y = pools[2] % W, (pools[2] // W) % inputs.images.shape[1]
    assert torch.all(x % 2 == 0) and torch.all(y % 2 == 0) and 0 < len(pools[2]) < len(pools[1]) / 3


def test_resume_refuses_a_new_config_or_inputs(tmp_path) -> None:
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "osn.cli", "train", str(tmp_path), "--out", str(tmp_path / "run"),
                        "--resume", "--inputs", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "drop --config/--inputs" in r.stderr and "Traceback" not in r.stderr


def test_metrics_reader_skips_a_line_cut_by_a_kill(tmp_path: Path) -> None:
    """The report and the CLI summary read metrics.jsonl after a kill mid-write: the cut line
    (and anything that is not a record) is skipped instead of failing the whole evaluation."""
    from osn.train.loop import read_metrics as training_curve  # what the report and the CLI read with

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"iteration": 20, "psnr": 20.5}\n[1, 2]\n\n{"iteration": 40, "psnr": 21.0}\n{"iteration": 60, "ps')
    assert [r["iteration"] for r in training_curve(path)] == [20, 40]
    assert training_curve(tmp_path / "absent.jsonl") == []


def test_resume_reads_the_checkpoint_onto_the_cpu(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    """Resume restores RNG states, which must be CPU byte tensors: the checkpoint is read onto
    the CPU whatever the training device (read onto CUDA, ``Generator.set_state`` raised)."""
    import osn.train.loop as T

    run = train(tiny_dataset, tmp_path / "r", _cfg(stage1_iters=4, rounds=0, final_scale_iters=0),
                progress=False, max_iterations=2)
    seen = []
    real = T.read_checkpoint
    monkeypatch.setattr(T, "read_checkpoint", lambda p, loc: seen.append(str(loc)) or real(p, loc))
    # Training "on another device" (a distinct CPU device object stands in for CUDA here).
    monkeypatch.setattr(T, "pick_device", lambda _: torch.device("cpu", 0))
    train(None, run, resume=True, progress=False)
    assert seen == ["cpu"] and _metrics(run)[-1]["iteration"] == 4


def test_diverging_training_stops_with_one_line_and_keeps_the_last_checkpoint(
    tiny_dataset: Path, tmp_path: Path, monkeypatch
) -> None:
    """A field that blows up (its grid turned NaN at iteration 27, as a diverging optimiser
    would): training stops at the first non-finite loss, naming the run, iteration, phase and
    loss, and the checkpoint of iteration 25 stays as it was, finite and resumable."""
    from osn.train.loop import TrainingDiverged

    real = Trainer.step_stage1

    def poisoned(self: Trainer) -> dict[str, float]:
        if self.iteration == 27:
            with torch.no_grad():
                self.fields[0].grid.fill_(float("nan"))
        return real(self)

    monkeypatch.setattr(Trainer, "step_stage1", poisoned)
    with pytest.raises(TrainingDiverged, match=r"r: training diverged at iteration 28 \(stage1 phase\): loss .* is nan"):
        train(tiny_dataset, tmp_path / "r", _cfg(), progress=False)
    state = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=False)
    assert state["iteration"] == 25
    assert all(torch.isfinite(v).all() for sd in state["fields"] for v in sd.values())

    # Weights that turn NaN in an update whose loss was still finite (after the step of
    # iteration 24): the checkpoint of iteration 25 is refused, not written with NaNs.
    def poisoned_after(self: Trainer) -> dict[str, float]:
        losses = real(self)
        if self.iteration == 24:
            with torch.no_grad():
                self.fields[1].grid.fill_(float("nan"))
        return losses

    monkeypatch.setattr(Trainer, "step_stage1", poisoned_after)
    with pytest.raises(TrainingDiverged, match=r"r2: training diverged at iteration 25 .*non-finite weights in field"):
        train(tiny_dataset, tmp_path / "r2", _cfg(), progress=False)
    assert not (tmp_path / "r2" / "checkpoint.pt").exists()


@pytest.mark.parametrize("bad", [{"resolution": 1}, {"initial_resolution": 0}, {"kind": "mlp"}, {"lr_grid": 0.0},
                                 {"upsample_steps": 1.5}, {"hidden": 64.5}, {"app_dim": True}])
def test_field_config_rejects_impossible_values(bad: dict) -> None:
    (key, _), = bad.items()
    with pytest.raises(ValueError, match=f"field.{key} must"):
        FieldConfig(**bad)

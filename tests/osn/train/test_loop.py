"""Whole training runs on the real ``tiny`` dataset: it learns, resumes exactly, stops on divergence,
and measures only against the region its caller gives."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from scenecore.validity import ValidRegion

import osn.train.loop as T
from osn.cli.train import dataset_region
from osn.preprocess.oracle import oracle_inputs
from osn.train import Trainer, TrainingDiverged, read_metrics, train
from osn.train.checkpoint import truncate_metrics
from osn.train.environment import same_kernels
from tests.osn.train.common import metrics as _metrics
from tests.osn.train.common import small_config as _cfg


def test_training_improves_psnr_and_writes_metrics(tiny_dataset: Path, tiny_region: ValidRegion, tmp_path: Path) -> None:
    run = train(tmp_path / "run", _cfg(), inputs=oracle_inputs(tiny_dataset), region=tiny_region, progress=False)
    m = _metrics(run)
    assert m[-1]["iteration"] == 30 + 2 * (10 + 10) + 10
    assert m[-1]["psnr"] > m[0]["psnr"] + 3.0
    for key in ("wall_time", "rgb", "iou", "precision", "recall", "scale_rel_err"):
        assert any(key in r for r in m), key
    assert all(0.0 <= r["iou"] <= 1.0 for r in m if "iou" in r)
    scale = [r for r in m if r["phase"] == "scale"]  # the pool's measured room bias, one per object
    assert scale and all(len(r["anchor_bias"]) == 3 and all(math.isfinite(b) for b in r["anchor_bias"]) for r in scale)
    assert all("anchor_bias" not in r for r in m if r["phase"] != "scale")
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    assert ck["iteration"] == m[-1]["iteration"] and ck["net"] is not None


def test_resume_equals_uninterrupted(tiny_dataset: Path, tiny_region: ValidRegion, tmp_path: Path) -> None:
    cfg = _cfg(eval_every=17)
    a = train(tmp_path / "a", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region, progress=False)
    # Interrupted inside the first scale phase (the depth cache must be rebuilt identically),
    # then again inside a field phase.
    b = train(tmp_path / "b", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region, progress=False, max_iterations=35)
    train(b, resume=True, region=tiny_region, progress=False, max_iterations=45)
    train(b, resume=True, region=tiny_region, progress=False)
    sa = torch.load(a / "checkpoint.pt", weights_only=True)
    sb = torch.load(b / "checkpoint.pt", weights_only=True)
    for fa, fb in zip(sa["fields"], sb["fields"]):
        for k in fa:
            assert torch.equal(fa[k], fb[k]), k
    for k in sa["net"]:
        assert torch.equal(sa["net"][k], sb["net"][k]), k
    ma, mb = _metrics(a), _metrics(b)
    drop = ("wall_time",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in ma] == [{k: v for k, v in r.items() if k not in drop} for r in mb]


def test_training_measures_only_against_the_region_its_caller_gives(
    tiny_dataset: Path, tiny_region: ValidRegion, tmp_path: Path
) -> None:
    """run.json records the dataset as provenance, but training never reads it back: a resume
    without a region writes no valid-set metrics; the region alone (no dataset path) suffices."""
    cfg = _cfg(stage1_iters=40, rounds=0, final_scale_iters=10)
    run = train(tmp_path / "r", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region, dataset=tiny_dataset,
                progress=False, max_iterations=20)
    assert json.loads((run / "run.json").read_text())["dataset"] == str(tiny_dataset)
    train(run, resume=True, progress=False)
    m = _metrics(run)
    assert [r["iteration"] for r in m] == [20, 40, 50] and "iou" in m[0] and not any("iou" in r for r in m[1:])
    anonymous = train(tmp_path / "anonymous", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region,
                      progress=False, max_iterations=20)
    assert json.loads((anonymous / "run.json").read_text())["dataset"] is None and "iou" in _metrics(anonymous)[0]


def test_run_json_records_what_the_run_computed_on_and_a_resume_elsewhere(
    tiny_dataset: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """run.json names the torch build, device and CPU kernel set a run trained with (a training
    reproduces to the digit only on the same kind); a resume on the same kind adds nothing, a
    resume on another is listed under resumed_on with a warning."""
    cfg = _cfg(stage1_iters=20, rounds=0, final_scale_iters=10)
    run = train(tmp_path / "r", cfg, inputs=oracle_inputs(tiny_dataset), progress=False, max_iterations=10)
    rec = json.loads((run / "run.json").read_text())
    env = rec["environment"]
    assert env["torch"] == torch.__version__ and env["device"] == "cpu" and env["threads"] == torch.get_num_threads()
    assert env["cpu_capability"] == torch.backends.cpu.get_cpu_capability() and env["cpu"]
    assert "resumed_on" not in rec
    train(run, resume=True, progress=False, max_iterations=15)
    assert json.loads((run / "run.json").read_text()) == rec  # same kind: nothing to note
    other = {**env, "cpu_capability": "AVX512" if env["cpu_capability"] != "AVX512" else "AVX2"}
    (run / "run.json").write_text(json.dumps({**rec, "environment": other}))
    with caplog.at_level("WARNING", logger="osn.train.loop"):
        train(run, resume=True, progress=False)
    after = json.loads((run / "run.json").read_text())
    assert after["environment"] == other and after["resumed_on"] == [env]
    assert "rounds differently" in caplog.text
    gpu = {**env, "device": "cuda:0", "gpu": "NVIDIA H200"}
    assert same_kernels(gpu, {**gpu, "device": "cuda:1", "threads": 16}) and not same_kernels(gpu, {**gpu, "gpu": "NVIDIA H100"})


def test_osn_train_reads_the_region_of_a_dataset_that_has_one(tiny_dataset: Path, tmp_path: Path) -> None:
    assert dataset_region(tiny_dataset).num_objects == 3
    assert dataset_region(tmp_path) is None and dataset_region(None) is None


def test_resume_refuses_to_overwrite_and_needs_a_checkpoint(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        train(tmp_path / "nothing", resume=True, progress=False)
    with pytest.raises(ValueError, match="a new run needs its per-object inputs"):
        train(tmp_path / "no-inputs", _cfg(), progress=False)
    assert not (tmp_path / "no-inputs").exists()
    out = tmp_path / "r"
    out.mkdir()
    # A run killed before its first checkpoint leaves metric lines and no checkpoint; a fresh
    # start must not keep them in front of its own curve.
    (out / "metrics.jsonl").write_text('{"iteration": 20, "stale": true}\n{"iteration": 40, "sta')
    run = train(out, _cfg(stage1_iters=2, rounds=0, final_scale_iters=0), inputs=oracle_inputs(tiny_dataset), progress=False)
    assert [m["iteration"] for m in _metrics(run)] == [2] and "stale" not in _metrics(run)[0]
    with pytest.raises(FileExistsError):
        train(run, _cfg(), inputs=oracle_inputs(tiny_dataset), progress=False)


def test_single_object_trains_without_scale_phases(tiny_dataset: Path, tiny_region: ValidRegion, tmp_path: Path) -> None:
    inputs = oracle_inputs(tiny_dataset)
    inputs.objects = [o for o in inputs.objects if o.id == inputs.anchor]
    run = train(tmp_path / "one", _cfg(), inputs=inputs, region=tiny_region, progress=False)
    m = _metrics(run)
    assert "iou" not in m[-1] and "seg_acc" not in m[-1]
    assert m[-1]["iteration"] == 30 + 2 * 10


def test_resume_skips_a_metrics_line_cut_by_a_kill(tmp_path: Path) -> None:
    p = tmp_path / "metrics.jsonl"
    p.write_text('{"iteration": 100}\n{"iteration": 200}\n{"iteration": 3')
    truncate_metrics(p, 150)
    assert p.read_text() == '{"iteration": 100}\n'


def test_resume_refuses_a_new_config_or_inputs(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "osn.cli", "train", "--data", str(tmp_path), "--out", str(tmp_path / "run"),
                        "--resume", "--inputs", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "drop --inputs" in r.stderr and "Traceback" not in r.stderr


def test_resume_without_the_dataset_it_started_with_is_refused(tiny_dataset: Path, tmp_path: Path) -> None:
    """Resumed without DATASET, a monitored run would drop its valid-set columns halfway through
    metrics.jsonl (seen on a GPU run): the CLI names the dataset to pass instead."""
    run = tmp_path / "run"
    train(run, _cfg(stage1_iters=2, rounds=0, final_scale_iters=0), inputs=oracle_inputs(tiny_dataset),
          dataset=tiny_dataset, progress=False)
    r = subprocess.run([sys.executable, "-m", "osn.cli", "train", "--out", str(run), "--resume"], capture_output=True, text=True)
    assert r.returncode == 2 and f"pass it again: osn train --data {tiny_dataset} --out {run} --resume" in r.stderr
    assert "Traceback" not in r.stderr


def test_metrics_reader_skips_a_line_cut_by_a_kill(tmp_path: Path) -> None:
    """The report and the CLI summary read metrics.jsonl after a kill mid-write: the cut line
    (and anything that is not a record) is skipped instead of failing the whole evaluation."""
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"iteration": 20, "psnr": 20.5}\n[1, 2]\n\n{"iteration": 40, "psnr": 21.0}\n{"iteration": 60, "ps')
    assert [r["iteration"] for r in read_metrics(path)] == [20, 40]
    assert read_metrics(tmp_path / "absent.jsonl") == []


def test_resume_reads_the_checkpoint_onto_the_cpu(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    """Resume restores RNG states, which must be CPU byte tensors: the checkpoint is read onto
    the CPU whatever the training device (read onto CUDA, ``Generator.set_state`` raised)."""
    run = train(tmp_path / "r", _cfg(stage1_iters=4, rounds=0, final_scale_iters=0), inputs=oracle_inputs(tiny_dataset),
                progress=False, max_iterations=2)
    seen = []
    real = T.read_checkpoint
    monkeypatch.setattr(T, "read_checkpoint", lambda p, loc: seen.append(str(loc)) or real(p, loc))
    # Training "on another device" (a distinct CPU device object stands in for CUDA here).
    monkeypatch.setattr(T, "pick_device", lambda _: torch.device("cpu", 0))
    train(run, resume=True, progress=False)
    assert seen == ["cpu"] and _metrics(run)[-1]["iteration"] == 4


def test_diverging_training_stops_with_one_line_and_keeps_the_last_checkpoint(
    tiny_dataset: Path, tmp_path: Path, monkeypatch
) -> None:
    """A field that blows up (its grid turned NaN at iteration 27, as a diverging optimiser
    would): training stops at the first non-finite loss, naming the run, iteration, phase and
    loss, and the checkpoint of iteration 25 stays as it was, finite and resumable."""
    real = Trainer.step_stage1

    def poisoned(self: Trainer) -> dict[str, float]:
        if self.iteration == 27:
            with torch.no_grad():
                self.fields[0].grid.fill_(float("nan"))
        return real(self)

    monkeypatch.setattr(Trainer, "step_stage1", poisoned)
    with pytest.raises(TrainingDiverged, match=r"r: training diverged at iteration 28 \(stage1 phase\): loss .* is nan"):
        train(tmp_path / "r", _cfg(eval_every=25), inputs=oracle_inputs(tiny_dataset), progress=False)
    state = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
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
        train(tmp_path / "r2", _cfg(eval_every=25), inputs=oracle_inputs(tiny_dataset), progress=False)
    assert not (tmp_path / "r2" / "checkpoint.pt").exists()


def test_alone_terms_and_scale_lr_decay_train_and_resume_exactly(tiny_dataset: Path, tiny_region: ValidRegion, tmp_path: Path) -> None:
    """`w_alone` adds each object's stage-1 objective to every field step (logged as `alone_*`);
    `scale_lr_final` decays the scale network's rate by a cosine within every scale phase, from
    `scale_lr` at its first step to `scale_lr * scale_lr_final` at its last; both survive a resume
    bit for bit (the rate is a function of the iteration)."""
    cfg = _cfg(w_alone=1.0, scale_lr_final=0.1, eval_every=17)
    trainer = Trainer(oracle_inputs(tiny_dataset), cfg, torch.device("cpu"))
    scale = [p for p in trainer.schedule if p.name == "scale"][0]
    trainer.iteration = scale.start
    assert trainer.scale_lr_at(scale) == pytest.approx(cfg.scale_lr)
    trainer.iteration = scale.end - 1
    assert trainer.scale_lr_at(scale) == pytest.approx(cfg.scale_lr * 0.1)
    a = train(tmp_path / "a", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region, progress=False)
    b = train(tmp_path / "b", cfg, inputs=oracle_inputs(tiny_dataset), region=tiny_region, progress=False, max_iterations=45)
    train(b, resume=True, region=tiny_region, progress=False)
    sa, sb = (torch.load(r / "checkpoint.pt", weights_only=True) for r in (a, b))
    assert all(torch.equal(sa["net"][k], sb["net"][k]) for k in sa["net"])
    assert all(torch.equal(fa[k], fb[k]) for fa, fb in zip(sa["fields"], sb["fields"]) for k in fa)
    assert any("alone_rgb" in r for r in _metrics(a))


def test_report_names_what_the_run_trained_with(tmp_path: Path) -> None:
    """report.md's environment line: the record's torch build and kernel set (or GPU), what
    reproduces on a CPU and what CUDA does not promise, resumes elsewhere; nothing for runs
    trained before runs recorded it."""
    from osn.evaluate.report import _environment_lines
    from osn.train.environment import environment

    cpu = environment(torch.device("cpu"))
    (tmp_path / "run.json").write_text(json.dumps({"dataset": None, "environment": cpu}))
    line = _environment_lines(tmp_path)[0]
    assert f"torch {torch.__version__} on cpu (" in line and f"{cpu['cpu_capability']} kernels" in line
    assert "reproduces to the last digit" in line and "Resumed" not in line
    gpu = {**cpu, "device": "cuda:0", "gpu": "NVIDIA H200"}
    (tmp_path / "run.json").write_text(json.dumps({"dataset": None, "environment": gpu, "resumed_on": [cpu]}))
    line = _environment_lines(tmp_path)[0]
    assert "on cuda:0 (NVIDIA H200)" in line and "only up to rounding" in line and "Resumed with torch" in line
    (tmp_path / "run.json").write_text(json.dumps({"dataset": None}))
    assert _environment_lines(tmp_path) == []

"""Values outside their range are one-line errors before any work: sampling thresholds and counts,
every training option (NaN, negative weights, fractional seeds, sizes that would allocate many
GB) and benchmark sizes."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from osn.model.fields import FieldConfig, _FIELD_RULES
from osn.train import TrainConfig, train
from osn.train.config import _RULES
from osn.preprocess.oracle import oracle_inputs
from osn.sample.configurations import MAX_SAMPLES, sample_configurations
from tests.osn.train.common import small_config
from tests.test_robustness import _assert_user_error, _cli, _cli_many


@pytest.fixture(scope="module")
def small_run(tiny_dataset: Path, tmp_path_factory) -> Path:
    """A few steps of training: enough for a scale network to sample from."""
    cfg = small_config(stage1_iters=4, rounds=1, field_iters=2, scale_iters=2, final_scale_iters=2, eval_every=100)
    return train(tmp_path_factory.mktemp("ranges") / "run", cfg, inputs=oracle_inputs(tiny_dataset), progress=False)


def test_sample_refuses_a_threshold_or_count_outside_its_range(small_run: Path) -> None:
    """On the command line (one line, nothing written) and in the library, before any draw."""
    from osn.model.run import load_run

    out = small_run / "s.npz"
    calls = [("osn", "sample", small_run, "-n", "5", "--threshold", "nan", "--out", out),
             ("osn", "sample", small_run, "-n", str(MAX_SAMPLES + 1), "--out", out)]
    thr, many = _cli_many(calls)
    _assert_user_error(thr, "threshold", "[0, 1)", "nan")
    _assert_user_error(many, "number of samples", f"1..{MAX_SAMPLES:,}")
    assert not out.exists()
    run = load_run(small_run)
    for threshold in (1.5, math.inf, -1.0, 1.0, math.nan):
        with pytest.raises(ValueError, match=r"threshold must be a number in \[0, 1\)"):
            sample_configurations(run, 5, threshold=threshold)
    for n in (0, -3, 2.5, MAX_SAMPLES + 1):
        with pytest.raises(ValueError, match="number of samples"):
            sample_configurations(run, n)


def test_many_samples_are_drawn_in_bounded_batches(small_run: Path) -> None:
    """Memory follows the kept samples, not n times the rejection rate: the scale network scores
    at most one batch at a time, and the result is the same draw whatever the batch."""
    from osn.model.run import load_run
    import osn.sample.configurations as C

    run = load_run(small_run)
    seen: list[int] = []
    scores = run.scores
    run.scores = lambda s: (seen.append(len(s)), scores(s))[1]  # record batch sizes of the real network
    a = sample_configurations(run, 20_000, threshold=0.0, seed=3)
    assert max(seen) <= C.BATCH and len(a.sbar) == 20_000 and np.isfinite(a.sbar).all()
    b = sample_configurations(run, 20_000, threshold=0.0, seed=3)
    assert np.array_equal(a.s_free, b.s_free)


BAD_TRAINING = {
    "w_opacity": math.nan, "w_free": -5, "w_distortion": math.nan, "seed": 1.5, "samples": 100_000_000,
    "rays": 10**9, "scale_samples": 10**10, "device": "gpu", "scale_lr": 0.0,
    "w_alone": math.inf,
}


def test_training_yaml_with_a_value_out_of_range_is_one_line(tiny_dataset: Path, tmp_path: Path) -> None:
    """Each value is refused naming the file and the key; the command line writes no run."""
    for key, value in BAD_TRAINING.items():
        cfg = tmp_path / f"{key}.yaml"
        cfg.write_text(yaml.safe_dump({key: value}))
        with pytest.raises(ValueError, match=rf"{cfg}: training config: {key} must be"):
            TrainConfig.from_yaml(cfg)
    r = _cli("osn", "train", "--data", tiny_dataset, "--out", tmp_path / "run", "--config", tmp_path / "w_opacity.yaml")
    _assert_user_error(r, tmp_path / "w_opacity.yaml", "w_opacity must be a number >= 0, got nan")
    assert not (tmp_path / "run").exists()


def test_field_sizes_that_would_allocate_many_gb_are_refused() -> None:
    for bad in ({"resolution": 100_000}, {"object_resolution": 5000}, {"anchor_planes": 10**6},
                {"initial_resolution": 10**7}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TrainConfig.from_dict({"field": bad})


def test_every_training_and_field_option_has_a_rule() -> None:
    """A new option cannot skip validation: NaN, a wrong type or an absurd size must be caught."""
    assert [f.name for f in dataclasses.fields(TrainConfig) if f.name not in _RULES] == []
    assert [f.name for f in dataclasses.fields(FieldConfig) if f.name not in _FIELD_RULES] == []
    configs = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
    assert len(configs) >= 4
    for path in configs:  # every shipped config passes its rules
        TrainConfig.from_yaml(path)


def test_benchgen_sizes_out_of_range_are_refused_before_rendering(tmp_path: Path) -> None:
    from benchgen.scene.spec import SpecError, load_preset

    spec = load_preset("tiny")
    for key, value in (("resolution", 100_000), ("configs", 1_000_000), ("samples", 10_000_000)):
        with pytest.raises(SpecError, match=f"{key}.*must be <="):
            spec.with_overrides(**{key: value})
    r = _cli("benchgen", "generate", "--preset", "tiny", "--out", tmp_path / "d", "--resolution", "100000")
    _assert_user_error(r, "tiny.yaml", "resolution[0]", "must be <= 8,192")
    assert not (tmp_path / "d").exists()
